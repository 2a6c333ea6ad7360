"""Bad input to the state setters: a ValueError that names the argument, the world, the joint or
body and the value, and no world changed."""
import numpy as np
import pytest

import abd_gym as ag
from abd_gym.sim import mechanisms


@pytest.fixture(scope="module")
def sim():
    scene = mechanisms.chain(2)
    scene.add_revolute_limit(1, -1.0, 1.0, 1e3)
    return ag.Simulator(scene, num_worlds=3, dt=0.01)


def test_non_finite_joint_state_names_world_and_joint(sim):
    x = np.zeros((3, 2))
    x[2, 1] = np.nan
    with pytest.raises(ValueError, match=r"coordinates has a non-finite value nan in world 2, joint 'revolute1'"):
        sim.set_joint_state(x)
    with pytest.raises(ValueError, match=r"velocities has a non-finite value inf in world 1, joint 'revolute0'"):
        sim.set_joint_state(np.zeros((2, 2)), [[0.0, 0.0], [np.inf, 0.0]], worlds=[0, 1])


def test_non_finite_body_state_names_world_and_body(sim):
    q = sim.body_q()
    p, R = q[..., :3].copy(), q[..., 3:].reshape(3, 3, 3, 3).copy()
    p[1, 2, 0] = np.inf
    with pytest.raises(ValueError, match=r"positions has a non-finite value inf in world 1, body 'link1'"):
        sim.set_body_states(p, R)


def test_joint_outside_its_limit_is_refused(sim):
    """Beyond a revolute limit by more than 1 rad (where its energy s·d³ reaches its strength)."""
    with pytest.raises(ValueError, match=r"joint 'revolute1' in world 0 is at 2\.2, outside its limit \[-1\.0, 1\.0\] by more"):
        sim.set_joint_state([[0.0, 2.2]], worlds=[0])
    sim.set_joint_state([[0.0, 1.2]], worlds=[0])  # a penetration the limit holds
    sim.set_limit(1, lower=-1.5, upper=1.5, worlds=[0])  # per-world bounds are the ones checked
    sim.set_joint_state([[0.0, 2.2]], worlds=[0])
    with pytest.raises(ValueError, match=r"in world 1 is at 2\.2"):
        sim.set_joint_state([[0.0, 2.2]], worlds=[1])
    sim.set_limit(1, lower=-1.0, upper=1.0, worlds=[0], check_state=False)


def test_rate_that_turns_pi_in_a_step_is_refused(sim):
    """|ẋ|·dt beyond what a step produces: 4π with the retry's quarter substeps (1256.6 rad/s at
    dt 0.01: -1260 rad/s refused, 1250 accepted); without the retry 2π under BDF2 and π under
    implicit Euler."""
    with pytest.raises(ValueError, match=r"velocities: revolute joint 'revolute0' in world 2 has rate 100000\.0 rad/s"):
        sim.set_joint_state(np.zeros((3, 2)), [[0.0, 0.0], [0.0, 0.0], [1e5, 0.0]])
    with pytest.raises(ValueError, match=r"rate -1260\.0 rad/s, which turns it by 4 pi or more"):
        sim.set_joint_state(np.zeros((3, 2)), [[0.0, -1260.0], [0.0, 0.0], [0.0, 0.0]])
    sim.set_joint_state(np.zeros((3, 2)), [[1250.0, 0.0], [0.0, 0.0], [0.0, 0.0]])
    for integrator, turn in (("bdf2", 2 * np.pi), ("implicit_euler", np.pi)):
        plain = ag.Simulator(sim.scene, num_worlds=1, dt=0.01, integrator=integrator, retry=False)
        with pytest.raises(ValueError, match=r"revolute joint 'revolute1' in world 0 has rate"):
            plain.set_joint_state(np.zeros((1, 2)), [[0.0, 1.01 * turn / 0.01]])
        plain.set_joint_state(np.zeros((1, 2)), [[0.0, 0.99 * turn / 0.01]])


def test_a_refused_state_changes_no_world(sim):
    sim.set_joint_state([[0.1, 0.2], [0.3, 0.4], [0.5, 0.6]])
    before = sim.body_q()
    with pytest.raises(ValueError):
        sim.set_joint_state([[0.0, 0.0], [0.0, 0.0], [0.0, 4.0]])
    np.testing.assert_array_equal(sim.body_q(), before)


def test_joint_state_ok_agrees_with_check_joint_state():
    """The whole-array check set_joint_state runs first passes exactly the states that
    check_joint_state passes: values at, just inside and just beyond each widened bound and at the
    rate bound π/dt, for a limited revolute, a limited prismatic and an unlimited revolute joint,
    in two worlds whose bounds differ."""
    from abd_gym.sim import inputs

    dt, names, revolute = 0.01, ["a", "b", "c"], np.array([True, False, True])
    limits = {0: (np.array([-1.0, -0.5]), np.array([1.0, 0.5]), True),
              1: (np.array([0.0, -2.0]), np.array([0.3, 2.0]), False)}  # fmt: skip
    bounds = inputs.joint_state_bounds(limits, revolute, 2)
    edges = [-2.0, -1.5, 2.0, 1.5, -0.3, 0.6, -4.0, 6.0]  # the widened bounds of both worlds
    values = sorted({v for e in edges for v in (e, np.nextafter(e, -np.inf), np.nextafter(e, np.inf))} | {0.0})
    rate = np.pi / dt
    rates = [0.0, rate, np.nextafter(rate, 0.0), -rate, 1e5]
    rng = np.random.default_rng(0)
    for _ in range(400):
        w = rng.integers(0, 2, size=1)
        x = rng.choice(values, size=(1, 3))
        xd = rng.choice(rates, size=(1, 3))
        try:
            inputs.check_joint_state(names, revolute, x, xd, w, dt, limits)
            passed = True
        except ValueError:
            passed = False
        assert inputs.joint_state_ok(x, xd, w, dt, bounds) == passed, (w, x, xd)


def test_finite_array_takes_every_value_within_its_bound_and_no_other():
    """Entries at the bound (many of them: beyond the one-product shortcut) are taken; one just
    beyond it, NaN or inf is refused, named by world and item."""
    from abd_gym.sim import inputs

    bound = 1e6
    at_bound = np.full((2, 3), -bound)
    assert inputs.finite_array("v", at_bound, (2, 3), bound=bound) is not None
    assert inputs.finite_array("v", np.full((2, 3), 1e200), (2, 3)) is not None  # no bound: Σ a² overflows
    cases = ((np.nextafter(bound, np.inf), "value 1000000.0000000001 beyond"), (np.nan, "non-finite value nan"),
             (-np.inf, "non-finite value -inf"))  # fmt: skip
    for bad, what in cases:
        v = at_bound.copy()
        v[1, 2] = bad
        with pytest.raises(ValueError, match=rf"v has a {what}.* in world 7, joint 'c'"):
            inputs.finite_array("v", v, (2, 3), worlds=[3, 7], items=["a", "b", "c"], item="joint", bound=bound)
