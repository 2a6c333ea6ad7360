"""Physical checks against closed-form answers, sign conventions, limits, and world independence."""
import math

import numpy as np
import pytest

import abd_gym as ag
from abd_gym.sim import mechanisms
from abd_gym.sim.scene import PRISMATIC


def rot(axis, angle):
    """Right-hand rotation about a unit axis (Rodrigues), independent of the simulator's code."""
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def test_pendulum_small_oscillation_period():
    """A compound pendulum's period T = 2π√(I_pivot/(m g d)) within 0.5% at dt = 1e-3."""
    L, m, w = 0.5, 1.0, 0.04
    sim = ag.Simulator(mechanisms.pendulum(length=L, mass=m), num_worlds=1, dt=1e-3, dtype="float64")
    sim.set_joint_state([[0.05]])
    xs = np.empty(2600)
    for i in range(len(xs)):
        sim.step()
        xs[i] = sim.joint_coordinates()[0, 0]
    t = np.arange(1, len(xs) + 1) * 1e-3
    k = np.flatnonzero((xs[:-1] > 0) & (xs[1:] <= 0))
    crossings = t[k] + 1e-3 * xs[k] / (xs[k] - xs[k + 1])
    assert len(crossings) >= 2
    period = np.diff(crossings).mean()
    inertia = m * (w**2 / 4 + L**2) / 12 * 1 + m * (L / 2) ** 2  # box about its centre, plus m d²
    inertia = m / 3 * ((w / 2) ** 2 + (L / 2) ** 2) + m * (L / 2) ** 2
    closed = 2 * math.pi * math.sqrt(inertia / (9.81 * m * L / 2))
    assert abs(period - closed) / closed < 5e-3, (period, closed)
    assert sim.converged().all()


def test_slider_under_gravity_follows_half_g_t_squared():
    """A block on a slider tilted 30° from vertical: x(t) = ½ g cos30° t² within 1%."""
    axis = np.array([math.sin(math.pi / 6), 0.0, -math.cos(math.pi / 6)])
    sim = ag.Simulator(mechanisms.slider(axis=axis), num_worlds=1, dt=1e-3, dtype="float64")
    steps = 400
    sim.step(steps)
    t = steps * 1e-3
    expected = 0.5 * 9.81 * math.cos(math.pi / 6) * t**2
    x = sim.joint_coordinates()[0, 0]
    assert abs(x - expected) / expected < 0.01, (x, expected)
    # the block stays on its axis
    p = sim.body_positions()[0, 1]
    assert np.linalg.norm(np.cross(p, axis)) < 1e-6
    assert sim.joint_violation()[0] < 1e-6


def test_double_pendulum_joint_residual_default_strength():
    """1000 steps of a swinging double pendulum at dt = 1e-2, default strength and precision:
    the joint residual stays under 1e-4 m."""
    sim = ag.Simulator(mechanisms.double_pendulum(), num_worlds=2, dt=1e-2)
    sim.set_joint_state([[1.0, -0.5], [2.0, 1.0]])
    worst = 0.0
    for _ in range(1000):
        sim.step()
        worst = max(worst, sim.joint_violation().max())
    assert worst < 1e-4, worst
    assert not sim.failed_worlds().size


def _angle_sign_scene(kind):
    scene = ag.Scene(gravity=(0, 0, 0))
    a = scene.add_body(ag.Box((0.1, 0.1, 0.1)), mass=1.0)
    b = scene.add_body(ag.Box((0.1, 0.1, 0.1)), mass=1.0, position=(0.3, 0.0, 0.0))
    axis = np.array([1.0, 2.0, 2.0]) / 3.0
    add = scene.add_revolute_joint if kind == "revolute" else scene.add_prismatic_joint
    add(a, b, anchor=(0.15, 0, 0), axis=axis)
    return scene, axis


@pytest.mark.parametrize("angle", [0.4, -1.2, 3.0])
def test_revolute_sign_convention(angle):
    """A right-hand rotation of the second body about the joint axis reads as a positive angle."""
    scene, axis = _angle_sign_scene("revolute")
    sim = ag.Simulator(scene, num_worlds=1, dt=0.01, dtype="float64")
    R = rot(axis, angle)
    anchor = np.array([0.15, 0, 0])
    p_b = anchor + R @ (np.array([0.3, 0, 0]) - anchor)
    sim.set_body_states([[[0, 0, 0], p_b]], [[np.eye(3), R]])
    assert sim.joint_coordinates()[0, 0] == pytest.approx(angle, abs=1e-9)
    # and spinning it about +axis gives a positive rate
    sim.set_body_states([[[0, 0, 0], p_b]], [[np.eye(3), R]], angular_velocities=[[[0, 0, 0], 0.5 * axis]],
                        linear_velocities=[[[0, 0, 0], np.cross(0.5 * axis, p_b - anchor)]])  # fmt: skip
    assert sim.joint_velocities()[0, 0] == pytest.approx(0.5, rel=1e-6)


def test_prismatic_sign_convention():
    """Moving the second body along +axis reads as a positive displacement."""
    scene, axis = _angle_sign_scene("prismatic")
    sim = ag.Simulator(scene, num_worlds=1, dt=0.01, dtype="float64")
    sim.set_body_states([[[0, 0, 0], np.array([0.3, 0, 0]) + 0.2 * axis]], [[np.eye(3), np.eye(3)]])
    assert sim.joint_coordinates()[0, 0] == pytest.approx(0.2, abs=1e-12)


def test_set_joint_state_round_trip():
    """Forward kinematics from joint coordinates reads the same coordinates and rates back."""
    sim = ag.Simulator(mechanisms.cartpole(), num_worlds=3, dt=0.01, dtype="float64")
    x = np.array([[0.3, 0.2], [-1.0, 3.0], [2.0, -2.5]])
    v = np.array([[0.5, -1.0], [0.0, 2.0], [-1.0, 0.3]])
    sim.set_joint_state(x, v)
    np.testing.assert_allclose(sim.joint_coordinates(), x, atol=1e-12)
    np.testing.assert_allclose(sim.joint_velocities(), v, atol=1e-12)
    assert sim.joint_violation().max() < 1e-12


def _energy(sim):
    return sum(sim.energies().values())


def test_revolute_limit_holds_with_bounded_overshoot():
    """A pendulum released at −1 rad swings into an upper limit at 0.3 rad.  Implicit Euler only
    dissipates, so the overshoot e obeys s·e³ ≤ KE at the bound: e ≤ (m g d (cos 0.3 − cos 1)/s)^{1/3}
    (the documented bound), and a 100× stronger limit cuts it by ~100^{1/3}."""
    overshoot = {}
    for s in (1e3, 1e5):
        scene = mechanisms.pendulum(limit=(-math.pi, 0.3, s))
        sim = ag.Simulator(scene, num_worlds=1, dt=2e-3, dtype="float64")
        sim.set_joint_state([[-1.0]])
        xs = []
        for _ in range(600):
            sim.step()
            xs.append(sim.joint_coordinates()[0, 0])
        overshoot[s] = max(xs) - 0.3
        ke = 1.0 * 9.81 * 0.25 * (math.cos(0.3) - math.cos(1.0))
        assert 0 < overshoot[s] <= (ke / s) ** (1 / 3), (s, overshoot[s])
        assert min(xs[-100:]) < 0.3  # it bounced back
    assert overshoot[1e5] < overshoot[1e3] / 3


@pytest.fixture(scope="module")
def spinning_wheel():
    """A wheel on a hinge (no gravity) spun at 20 rad/s into limits at ±(π − 0.05)."""

    def run(strength, steps=300, dt=5e-3, integrator="implicit_euler"):
        scene = ag.Scene(gravity=(0, 0, 0))
        base = scene.add_body(ag.Box((0.05, 0.05, 0.05)), fixed=True)
        wheel = scene.add_body(ag.Cylinder(0.2, 0.02), mass=1.0, rotation=rot((1, 0, 0), math.pi / 2))
        j = scene.add_revolute_joint(base, wheel, anchor=(0, 0, 0), axis=(0, 1, 0))
        scene.add_revolute_limit(j, -(math.pi - 0.05), math.pi - 0.05, strength)
        sim = ag.Simulator(scene, num_worlds=2, dt=dt, dtype="float64", integrator=integrator)
        sim.set_joint_state([[0.0], [0.0]], [[20.0], [-20.0]])
        xs, vs = [], []
        for _ in range(steps):
            sim.step()
            xs.append(sim.joint_coordinates()[:, 0])
            vs.append(sim.joint_velocities()[:, 0])
        return np.array(xs), np.array(vs), sim

    return run


def test_limit_angle_stays_on_principal_branch_plus_one_increment(spinning_wheel):
    """Through ±180°, x = θ0 + δ never leaves (−π − |δ|, π + |δ|]: the seed's atan2 form."""
    for strength in (10.0, 1e5):  # weak: spins through the limit; strong: held
        xs, vs, _ = spinning_wheel(strength)
        inc = np.abs(vs) * 5e-3
        assert np.all(np.abs(xs) <= math.pi + inc + 1e-12)


@pytest.mark.parametrize("integrator", ["implicit_euler", "bdf2"])
def test_strong_limit_stops_a_20_rad_per_s_spin(spinning_wheel, integrator):
    """Hard case: 20 rad/s into a stiff limit near ±π: held within 0.05 rad past the bound,
    no NaN, slowed, under implicit Euler and BDF2."""
    xs, vs, sim = spinning_wheel(1e5, integrator=integrator)
    assert np.all(np.abs(xs) < math.pi)  # never wrapped through ±π
    assert np.all(np.abs(xs) <= math.pi - 0.05 + 0.05)
    assert np.all(np.isfinite(xs)) and not sim.failed_worlds().size
    assert np.abs(vs[-1]).max() < 20.0


def test_worlds_are_independent_and_a_failed_world_is_reset():
    """Randomising world 1's masses changes only world 1; a world driven to NaN is flagged,
    keeps its last good state, leaves the others bit-identical, and resets cleanly."""
    scene = mechanisms.double_pendulum()
    x0 = [[0.5, 0.2]] * 3

    def run(setup):
        sim = ag.Simulator(scene, num_worlds=3, dt=0.01, dtype="float64")
        sim.set_joint_state(x0)
        setup(sim)
        sim.step(30)
        return sim

    ref = run(lambda s: None)
    heavy = run(lambda s: s.set_body_mass([[5.0, 0.2]], bodies=[1, 2], worlds=[1]))
    q_ref, q_heavy = ref.body_q(), heavy.body_q()
    np.testing.assert_array_equal(q_ref[[0, 2]], q_heavy[[0, 2]])
    assert np.abs(q_ref[1] - q_heavy[1]).max() > 1e-3

    def poison(sim):
        q = sim.state.q.numpy()
        q[1, 1, 0] = np.nan
        sim.state.q.assign(q)

    bad = run(poison)
    assert bad.failed_worlds().tolist() == [1]
    np.testing.assert_array_equal(bad.body_q()[[0, 2]], q_ref[[0, 2]])
    bad.reset(worlds=[1])
    assert bad.failed_worlds().size == 0
    bad.set_joint_state([[0.5, 0.2]], worlds=[1])
    bad.step(30)
    np.testing.assert_allclose(bad.body_q()[1], q_ref[1], atol=1e-9)

    # a world given an absurd body velocity is reported the same way, and keeps its state
    sim = ag.Simulator(scene, num_worlds=2, dt=0.01)
    sim.set_joint_state([[0.5, 0.2], [0.5, 0.2]])
    p, R = sim.body_positions(), sim.body_rotations()
    qd = np.zeros((1, 3, 12))
    qd[:, :, :3] = 1e25  # past the setters' checks, which refuse it (inputs.state_bound)
    sim._set_q(np.array([1]), sim.body_q()[1:], qd)
    q_set = sim.body_q()[1].copy()
    sim.step(2)
    assert sim.failed_worlds().tolist() == [1]
    assert np.isfinite(sim.body_q()[0]).all()
    np.testing.assert_array_equal(sim.body_q()[1], q_set)


def test_setting_some_worlds_writes_only_their_rows():
    """set_joint_state(worlds=...) scatters on the device: the listed worlds match a simulator set in
    full, every other world's state and history are untouched bit for bit."""
    scene = mechanisms.double_pendulum()
    sim = ag.Simulator(scene, num_worlds=4, dt=0.01, integrator="bdf2")
    sim.set_joint_state([[0.3, -0.2]] * 4, [[1.0, 0.5]] * 4)
    sim.step(5)
    st = sim.state
    names = ("q", "qd", "q_prev", "q_hist", "qd_hist", "unwrapped", "x_hist", "theta0", "status", "fresh")
    before = {n: getattr(st, n).numpy().copy() for n in names}
    sim.set_joint_state([[7.0, 0.1], [-0.4, 0.2]], [[0.5, 0.0], [0.0, -1.0]], worlds=[3, 1])
    after = {n: getattr(st, n).numpy() for n in names}
    for n in names:
        np.testing.assert_array_equal(after[n][[0, 2]], before[n][[0, 2]], err_msg=n)
    full = ag.Simulator(scene, num_worlds=2, dt=0.01, integrator="bdf2")
    full.set_joint_state([[7.0, 0.1], [-0.4, 0.2]], [[0.5, 0.0], [0.0, -1.0]])
    for n in names:
        np.testing.assert_allclose(after[n][[3, 1]], getattr(full.state, n).numpy(), atol=1e-6, err_msg=n)
    # the multi-turn angle keeps the 7 rad given (not its principal value)
    assert abs(sim.joint_angles_unwrapped()[3, 0] - 7.0) < 1e-5
    sim.set_joint_state(np.zeros((0, 2)), worlds=[])  # nothing to write is not an error


def test_parameter_setters_write_listed_worlds_and_reject_before_writing():
    """set_body_mass / set_limit change only the listed worlds' rows; a bad limit changes nothing."""
    sim = ag.Simulator(mechanisms.cartpole(), num_worlds=3, dt=0.01)
    m = sim.model
    before = {n: getattr(m, n).numpy().copy() for n in ("mass", "mc", "S", "K")}
    sim.set_body_mass([[2.0, 0.3]], bodies=["cart", "pole"], worlds=[1])
    for n, b in before.items():
        after = getattr(m, n).numpy()
        np.testing.assert_array_equal(after[[0, 2]], b[[0, 2]], err_msg=n)
        assert n == "mc" or not np.array_equal(after[1], b[1]), n  # mc = m·com is 0 for these bodies
    np.testing.assert_allclose(m.mass.numpy()[1, 1:], [2.0, 0.3], rtol=1e-6)
    limits = [a.numpy().copy() for a in m.limit_params[PRISMATIC]]
    with pytest.raises(ValueError, match="must not exceed upper"):
        sim.set_limit(0, lower=[-0.5, 0.9], upper=[0.5, 0.1], worlds=[0, 2])
    for a, b in zip(m.limit_params[PRISMATIC], limits):
        np.testing.assert_array_equal(a.numpy(), b)  # world 0's valid half was not written either
    sim.set_limit(0, lower=-0.4, upper=0.3, worlds=[2])
    lo, up, _ = (a.numpy()[:, 0] for a in m.limit_params[PRISMATIC])
    np.testing.assert_allclose([lo[2], up[2]], [-0.4, 0.3], rtol=1e-6)
    np.testing.assert_array_equal(lo[:2], limits[0][:2, 0])


def test_bad_input_raises_clear_errors():
    scene = ag.Scene()
    base = scene.add_body(ag.Box((0.1, 0.1, 0.1)), fixed=True)
    link = scene.add_body(ag.Box((0.1, 0.1, 0.1)), mass=1.0)
    with pytest.raises(ValueError, match="axis"):
        scene.add_revolute_joint(base, link, anchor=(0, 0, 0), axis=(0, 0, 0))
    with pytest.raises(ValueError, match="mass"):
        scene.add_body(ag.Box((0.1, 0.1, 0.1)), mass=-1.0)
    with pytest.raises(ValueError, match="half_extents"):
        ag.Box((0.1, 0.0, 0.1))
    with pytest.raises(ValueError, match="unknown body"):
        scene.add_revolute_joint(base, 7, anchor=(0, 0, 0), axis=(0, 1, 0))
    with pytest.raises(ValueError, match="unknown body"):
        scene.add_revolute_joint(base, "nope", anchor=(0, 0, 0), axis=(0, 1, 0))
    with pytest.raises(ValueError, match="strength_ratio"):
        scene.add_revolute_joint(base, link, anchor=(0, 0, 0), axis=(0, 1, 0), strength_ratio=-1)
    hinge = scene.add_revolute_joint(base, link, anchor=(0, 0, 0), axis=(0, 1, 0))
    with pytest.raises(ValueError, match=r"lower \(1.0\) must not exceed upper \(-1.0\)"):
        scene.add_revolute_limit(hinge, 1.0, -1.0)
    with pytest.raises(ValueError, match="strength"):
        scene.add_revolute_limit(hinge, -1.0, 1.0, strength=-5.0)
    with pytest.raises(ValueError, match="needs a prismatic joint"):
        scene.add_prismatic_limit(hinge, -1.0, 1.0)
    other = scene.add_body(ag.Box((0.1, 0.1, 0.1)), mass=1.0)
    slide = scene.add_prismatic_joint(link, other, anchor=(0, 0, 0), axis=(1, 0, 0))
    with pytest.raises(ValueError, match="needs a revolute joint"):
        scene.add_revolute_limit(slide, -1.0, 1.0)
    scene.add_revolute_limit(hinge, -1.0, 1.0)
    assert scene.joints[hinge].meta["extra_constitution_uids"] == [670]
    assert scene.joints[hinge].attributes == {"limit/lower": -1.0, "limit/upper": 1.0, "limit/strength": 1e3}
    sim = ag.Simulator(mechanisms.cartpole(), num_worlds=2, dt=0.01)
    with pytest.raises(ValueError, match="non-finite"):
        sim.set_joint_state([[0.0, np.nan], [0.0, 0.0]])
    with pytest.raises(ValueError, match="non-finite"):
        sim.set_controls([[np.nan], [0.0]])
    with pytest.raises(ValueError, match="positions"):
        sim.set_body_states(np.full((2, 3, 3), np.nan), np.tile(np.eye(3), (2, 3, 1, 1)))
    with pytest.raises(ValueError, match="dt"):
        ag.Simulator(mechanisms.cartpole(), dt=0.0)
    with pytest.raises(ValueError, match="world indices"):
        sim.reset(worlds=[5])
