"""Scale-aware defaults: κ from the body's density, a joint strength that holds the load it
carries, and a warning for stiffnesses the dtype cannot solve."""
import warnings

import gymnasium as gym
import numpy as np
import pytest

import abd_gym as ag
import abd_gym.vector.vector_env as vector_env
from abd_gym.sim import conditioning, mechanisms
from abd_gym.sim.mechanisms import link_shape
from abd_gym.vector.registration import env_ids
from abd_gym.sim.scene import LOAD_STRENGTH_RATIO, STIFFNESS_PER_DENSITY


def hanging_chain(masses, strength_ratio=None, stiffness=None, length=0.5):
    """Links of ``masses`` [kg] hanging along −z from a fixed 1 kg base by hinges about +y."""
    scene = ag.Scene()
    parent = scene.add_body(ag.Box(half_extents=(0.05, 0.05, 0.05)), fixed=True, name="base")
    for k, m in enumerate(masses):
        link = scene.add_body(link_shape(length), mass=m, position=(0, 0, -(k + 0.5) * length), stiffness=stiffness,
                              name=f"link{k}")  # fmt: skip
        scene.add_revolute_joint(parent, link, anchor=(0, 0, -k * length), axis=(0, 1, 0), strength_ratio=strength_ratio,
                                 name=f"hinge{k}")  # fmt: skip
        parent = link
    return scene


def test_default_stiffness_scales_with_density():
    """κ = 1e5 m²/s² · ρ: 1e8 Pa for 1000 kg/m³, 2e9 Pa for a 20,000 kg/m³ rod, 1.25e5 Pa for a 1 g
    link of 8e-4 m³; an explicit κ is kept; the model's κ·vol follows."""
    scene = ag.Scene()
    water = scene.add_body(ag.Box(half_extents=(0.1, 0.2, 0.3)))
    dense = scene.add_body(link_shape(0.5), density=20000.0)
    light = scene.add_body(link_shape(0.5), mass=0.001)
    given = scene.add_body(link_shape(0.5), mass=0.001, stiffness=3e7)
    kappa = [scene.bodies[k].stiffness for k in (water, dense, light, given)]
    np.testing.assert_allclose(kappa, [1e8, 2e9, 1.25e5, 3e7], rtol=1e-12)
    assert STIFFNESS_PER_DENSITY == 1e5
    model = ag.Simulator(scene, num_worlds=1).model
    vol = [b.shape.volume() for b in scene.bodies]
    np.testing.assert_allclose(model.kv.numpy()[0], np.multiply(kappa, vol), rtol=1e-6)


def test_light_link_under_heavy_one_converges_in_float32():
    """A 1 g link under a 1 kg one, float32 implicit Euler at dt 0.05, 16 worlds released at up to
    2.5 rad: every step converges (with κ = 1e8 Pa every world failed)."""
    sim = ag.Simulator(hanging_chain([1.0, 0.001]), num_worlds=16, dt=0.05)
    sim.set_joint_state(np.random.default_rng(0).uniform(-2.5, 2.5, (16, 2)))
    for _ in range(20):
        sim.step()
        assert sim.converged().all()
        assert sim.failed_worlds().size == 0
    assert sim.joint_violation().max() < 1e-3


def test_derived_strength_ratio_carries_the_load():
    """γ = 100·max(1, M/(m_i + m_j)), M the mass beyond the joint; an explicit ratio is kept."""
    scene = hanging_chain([1.0, 1000.0])
    np.testing.assert_allclose(scene.supported_masses(), [1001.0, 1000.0])
    np.testing.assert_allclose(scene.strength_ratios(), [LOAD_STRENGTH_RATIO * 1001.0 / 2.0, LOAD_STRENGTH_RATIO])
    np.testing.assert_allclose(hanging_chain([1.0, 1000.0], strength_ratio=30.0).strength_ratios(), [30.0, 30.0])
    K = ag.Simulator(scene, num_worlds=1).model.K.numpy()[0]
    np.testing.assert_allclose(K, [100.0 * 1001.0, 100.0 * 1001.0], rtol=1e-6)


def test_loop_joints_carry_their_component():
    """A four-bar (ground, crank 1 kg, coupler 2 kg, rocker 3 kg): every joint is on the loop and
    counts the 6 kg the loop holds; a 4 kg pendulum hanging from the coupler adds to it."""
    scene = ag.Scene()
    ground = scene.add_body(ag.Box(half_extents=(0.05, 0.05, 0.05)), fixed=True)
    crank = scene.add_body(ag.Box(half_extents=(0.05, 0.01, 0.01)), mass=1.0)
    coupler = scene.add_body(ag.Box(half_extents=(0.05, 0.01, 0.01)), mass=2.0)
    rocker = scene.add_body(ag.Box(half_extents=(0.05, 0.01, 0.01)), mass=3.0)
    for a, b in ((ground, crank), (crank, coupler), (coupler, rocker), (rocker, ground)):
        scene.add_revolute_joint(a, b, anchor=(0, 0, 0), axis=(0, 1, 0))
    np.testing.assert_allclose(scene.supported_masses(), [6.0] * 4)
    bob = scene.add_body(ag.Box(half_extents=(0.01, 0.01, 0.05)), mass=4.0)
    scene.add_revolute_joint(coupler, bob, anchor=(0, 0, 0), axis=(0, 1, 0))
    np.testing.assert_allclose(scene.supported_masses(), [10.0] * 4 + [4.0])


@pytest.mark.parametrize("dt, bound", [(0.01, 5e-4), (0.03, 2e-3)])
def test_heavy_load_under_light_link_keeps_the_joints_closed(dt, bound):
    """1000 kg hanging under a 1 kg link, released at up to 1.5 rad, 1 s: the joints open less
    than 0.5 mm at dt 0.01 and 2 mm at dt 0.03 (with γ = 100: 20 mm and 91 mm)."""
    sim = ag.Simulator(hanging_chain([1.0, 1000.0]), num_worlds=8, dt=dt)
    sim.set_joint_state(np.random.default_rng(1).uniform(-1.5, 1.5, (8, 2)))
    gap = 0.0
    for _ in range(int(round(1.0 / dt))):
        sim.step()
        gap = max(gap, sim.joint_violation().max())
    assert sim.failed_worlds().size == 0
    assert gap < bound


def test_unsolvable_strength_warns_at_build():
    """strength_ratio 1e8 in float32 (K/m = 2e8): a RuntimeWarning naming the joint and the value."""
    scene = hanging_chain([1.0, 1.0], strength_ratio=1e8)
    with pytest.warns(RuntimeWarning) as caught:
        ag.Simulator(scene, num_worlds=1)
    assert sorted(str(w.message).split(":")[0] for w in caught) == ["joint 'hinge0'", "joint 'hinge1'"]
    assert all("strength ratio 1e+08" in str(w.message) for w in caught)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ag.Simulator(scene, num_worlds=1, dtype="float64")


def test_unsolvable_stiffness_warns_at_build():
    """κ = 1e12 Pa on a 1 kg, 0.5 m × 4 cm link at dt 0.01 in float32 (4κ·vol·dt²/λ_min(S) = 2.4e9)."""
    with pytest.warns(RuntimeWarning, match=r"body 'link0': stiffness 1e\+12 Pa"):
        ag.Simulator(hanging_chain([1.0], stiffness=1e12), num_worlds=1, dt=0.01)


class _Built(Exception):
    pass


def task_scene(env_id):
    """(scene, dt) of a task, taken from its constructor before any simulator is built."""
    spec = gym.registry[env_id]
    make = gym.envs.registration.load_env_creator(spec.vector_entry_point)
    built = {}

    def capture(scene, num_worlds, dt, **kw):
        built.update(scene=scene, dt=dt)
        raise _Built

    original, vector_env.Simulator = vector_env.Simulator, capture
    try:
        make(num_envs=1, **spec.kwargs)
    except _Built:
        pass
    finally:
        vector_env.Simulator = original
    return built["scene"], built["dt"]


@pytest.mark.parametrize("env_id", env_ids())
def test_no_warning_on_shipped_tasks(env_id):
    """Every task, in both dtypes, at its own dt and at 0.05 s: nothing is out of reach."""
    scene, dt = task_scene(env_id)
    for dtype in ("float32", "float64"):
        for step in (dt, 0.05):
            assert conditioning.unsolvable(scene, step, dtype) == []
    assert conditioning.step_too_large(scene, dt) == []


def test_no_warning_on_mechanisms():
    scenes = [mechanisms.chain(20, length=0.1), mechanisms.double_pendulum(), mechanisms.cartpole(), mechanisms.slider()]
    for scene in scenes:
        for dtype in ("float32", "float64"):
            assert conditioning.unsolvable(scene, 0.05, dtype) == []


def test_a_step_beyond_the_fastest_mode_warns_at_build():
    """0.5 m links (√(g/r) = 6.2 rad/s): dt 0.2 turns them 1.25 rad a step, dt 0.1 0.62."""
    with pytest.warns(RuntimeWarning, match=r"dt 0\.2 s is beyond what body 'link[01]' \(gravity over its size\) can take"):
        ag.Simulator(mechanisms.double_pendulum(), num_worlds=1, dt=0.2)
    assert conditioning.step_too_large(mechanisms.double_pendulum(), 0.1) == []


def test_a_drive_moves_the_inertia_beyond_its_joint():
    """A hinge drive moves every body beyond its joint about the hinge axis: a 0.5 m, 1 kg link
    about its end m·L²/3, the second link of a double pendulum as well (m·L²/12 + m·(1.5 L)²); a
    slide moves its bodies' mass (the cart-pole's cart and pole)."""
    scene = mechanisms.double_pendulum()
    L = 0.5
    assert conditioning.driven_inertia(scene, 1) == pytest.approx(L * L / 3, rel=0.02)
    assert conditioning.driven_inertia(scene, 0) == pytest.approx(L * L / 3 + L * L / 12 + (1.5 * L) ** 2, rel=0.02)
    assert conditioning.driven_inertia(mechanisms.cartpole(), 0) == pytest.approx(1.1)


def test_a_stiff_position_drive_warns_unless_damped_past_critical():
    """kp 400 N·m/rad on a link of I = 1/12 kg·m² oscillates at 69 rad/s: 0.69 rad a 0.01 s step
    undamped, over 1 rad at 0.02; kv 40 (ζ ≈ 3.5) leaves a slow mode of kp/kv ≈ 10 rad/s, which
    any of these steps resolves."""
    for damping, warns in ((0.0, True), (40.0, False)):
        scene = mechanisms.pendulum(gravity=(0, 0, 0))
        scene.add_drive(0, mode="position", stiffness=400.0, damping=damping)
        messages = conditioning.step_too_large(scene, 0.02)
        assert bool(messages) == warns, messages
        if warns:
            assert "position drive of joint" in messages[0]
        assert conditioning.step_too_large(scene, 0.01) == []
