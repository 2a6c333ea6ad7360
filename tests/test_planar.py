"""Planar scenes solved with 6 unknowns a body (abd_gym/sim/planar.py): which scenes are planar, the
same trajectories as the 12-unknown step on every registered task and every layout, states that
would leave the plane refused."""
import math

import gymnasium as gym
import numpy as np
import pytest

import abd_gym as ag
import abd_gym.envs  # noqa: F401  (registers the tasks)
from abd_gym.sim import planar
from abd_gym.vector.registration import TASKS

# the plane each registered task moves in (None: a 3-D mechanism)
PLANES = {"Pendulum-v0": "xz", "CartPole-v0": "xz", "CartPoleSwingUp-v0": "xz", "DoublePendulumCart-v0": "xz",
          "Acrobot-v0": "xz", "TwoLinkReacher-v0": "xy", "FourBar-v0": "xz", "SliderCrank-v0": "xz",
          "InvertedPendulum-v5": "xz", "InvertedDoublePendulum-v5": "xz", "Reacher-v5": "xy", "ArmReach-v0": None}
PLANAR_TASKS = [name for name, plane in PLANES.items() if plane]


@pytest.fixture(scope="module")
def scenes():
    """Each registered task's scene (as its vector env builds it)."""
    out = {}
    for name in TASKS:
        env = gym.make_vec(f"abd_gym/{name}", num_envs=1, vectorization_mode="vector_entry_point")
        out[name] = env.unwrapped.sim.scene
        env.close()
    return out


def test_every_task_is_listed():
    assert set(PLANES) == set(TASKS)


def test_each_task_gets_its_plane(scenes):
    for name, want in PLANES.items():
        scene = scenes[name]
        scene.planar = None
        got = planar.plane_of(scene)
        assert (None if got is None else str(got)) == want, (name, planar.explain(scene))
        assert (planar.explain(scene) == []) == (want is not None)


def test_planar_option_forces_or_turns_off(scenes):
    arm = scenes["ArmReach-v0"]
    arm.planar = True
    with pytest.raises(ValueError, match="does not move in a plane: joint .* hinge axis"):
        planar.plane_of(arm)
    arm.planar = None
    pend = scenes["Pendulum-v0"]
    pend.planar = False
    assert planar.plane_of(pend) is None
    pend.planar = True
    assert str(planar.plane_of(pend)) == "xz"
    pend.planar = None
    with pytest.raises(TypeError, match="planar must be None, True or False"):
        pend.planar = "yes"


def _mirror_broken_scene():
    """A double pendulum in the xz plane whose lower link's anchor lies off its body's plane."""
    scene = ag.Scene()
    base = scene.add_body(ag.Box((0.1, 0.1, 0.1)), fixed=True)
    a = scene.add_body(ag.Capsule(0.02, 0.3), mass=1.0, position=(0.0, 0.0, -0.15))
    b = scene.add_body(ag.Capsule(0.02, 0.3), mass=1.0, position=(0.0, 0.05, -0.45))
    scene.add_revolute_joint(base, a, anchor=(0.0, 0.0, 0.0), axis=(0.0, 1.0, 0.0))
    scene.add_revolute_joint(a, b, anchor=(0.0, 0.0, -0.3), axis=(0.0, 1.0, 0.0))
    return scene


def test_asymmetric_data_is_planar_only_when_forced():
    scene = _mirror_broken_scene()
    assert planar.plane_of(scene) is None
    assert any("off body" in why for why in planar.explain(scene))
    scene.planar = True
    assert str(planar.plane_of(scene)) == "xz"


# the 12-unknown reference: the staged step (its kernels serve every scene; tests/test_solver.py holds
# the fused 12-unknown step to it)
STAGED = {"fused": False}


def _trajectory(scene, planar_mode, integrator="bdf2", plan=None, steps=100, worlds=4):
    """Joint coordinates (steps, worlds, joints) from random joint states, float64, dt 0.01."""
    scene.planar = planar_mode
    sim = ag.Simulator(scene, num_worlds=worlds, dt=0.01, dtype="float64", integrator=integrator, plan=plan,
                       device="cpu")  # fmt: skip
    assert (sim.plane is not None) == (planar_mode is not False and plan is not STAGED)
    rng = np.random.default_rng(7)
    x = sim.joint_coordinates()
    if sim.loops is None:  # (a closed loop's coordinates must close it: it starts from its zero pose)
        x = x + rng.uniform(-0.2, 0.2, x.shape)
    sim.set_joint_state(x, rng.uniform(-1.0, 1.0, x.shape))
    out = []
    for _ in range(steps):
        sim.step()
        out.append(sim.joint_coordinates())
    scene.planar = None
    return np.array(out), sim


# Reacher-v5 lies flat with gravity along the plane's normal: the 12-unknown step lets its links sag
# out of the plane against their joints (m g/K) and its in-plane angles differ by 2.8e-8 rad over
# 1 s; the planar step holds the plane, as a rigid hinge does
TOLERANCE = {"Reacher-v5": 1e-7}
# energies: the kinetic energy's velocities are difference quotients (Δq/h), so 1e-10 m of q is
# 1e-8 of q̇; Reacher-v5's sag (above) lowers its gravity energy by 4e-6 J
ENERGY_ATOL = {"Reacher-v5": 1e-5}


@pytest.mark.parametrize("name", PLANAR_TASKS)
def test_planar_step_is_the_12_unknown_step(scenes, name):
    """1 s from the same random states, both integrators: ≤ 1e-9 rad (or m) apart in float64."""
    scene = scenes[name]
    # with limits, the fused 12-unknown step: the staged one models no limit along its line search,
    # and its solutions differ by up to 1e-10 a step
    reference = STAGED if not any(j.has_limit for j in scene.joints) else None
    for integrator in ("bdf2", "implicit_euler"):
        full, sim_full = _trajectory(scene, False if reference is None else None, integrator, plan=reference)
        reduced, sim = _trajectory(scene, None, integrator)
        assert sim.model.num_dofs * 2 == sim_full.model.num_dofs
        np.testing.assert_array_equal(sim.world_status(), sim_full.world_status())
        err = np.abs(reduced - full).max()
        assert err <= TOLERANCE.get(name, 1e-9), (name, integrator, err)
        e_full, e_red = sim_full.energies(), sim.energies()
        for term in e_full:
            np.testing.assert_allclose(e_red[term], e_full[term], rtol=1e-7, atol=ENERGY_ATOL.get(name, 1e-12),
                                       err_msg=f"{name} {term}")  # fmt: skip


@pytest.mark.parametrize("name, plan", [
    ("DoublePendulumCart-v0", {"scratch": "lanes", "block_dim": 8}),
    ("DoublePendulumCart-v0", {"scratch": "shared"}),
    ("DoublePendulumCart-v0", {"scratch": "global", "envelope": True}),
    ("InvertedPendulum-v5", {"scratch": "global", "limit_secant": True})], ids=["lanes", "shared", "envelope", "secant"])
def test_every_layout_steps_the_plane(scenes, name, plan):
    """The layouts besides the CPU's default ("global"), on a 3-body chain (18 unknowns and 2 padding
    rows; its envelope: each body's rows from the one before it) and on a 2-body scene with a limit,
    against the default layout's planar step (the 12-unknown step's to 1e-9: above)."""
    full, _ = _trajectory(scenes[name], None, steps=50)
    reduced, sim = _trajectory(scenes[name], None, plan=plan, steps=50)
    assert sim.plan.scratch == plan["scratch"]
    if plan.get("envelope"):
        np.testing.assert_array_equal(sim.model.first_np, [0] * 6 + [0] * 6 + [6] * 6 + [18, 19])
    assert np.abs(reduced - full).max() <= 1e-9


@pytest.fixture(scope="module")
def acrobot(scenes):
    scene = scenes["Acrobot-v0"]
    scene.planar = None
    return ag.Simulator(scene, num_worlds=2, dt=0.01, dtype="float64", device="cpu")


def test_repr_and_memory_say_the_form(acrobot, scenes):
    assert "12 unknowns a world (6 a body in the xz plane)" in repr(acrobot)
    scene = scenes["Acrobot-v0"]
    scene.planar = False
    full = ag.Simulator(scene, num_worlds=2, dt=0.01, dtype="float64", device="cpu")
    scene.planar = None
    assert "24 unknowns a world (12 a body)" in repr(full)
    assert acrobot.memory_bytes()["solver"] * 2 <= full.memory_bytes()["solver"]


def test_a_state_off_the_plane_is_refused(acrobot):
    sim = acrobot
    sim.step(3)
    before = sim.get_state()
    P, R = sim.body_positions(), sim.body_rotations()
    turn = np.array([[math.cos(0.1), -math.sin(0.1), 0.0], [math.sin(0.1), math.cos(0.1), 0.0], [0.0, 0.0, 1.0]])
    R_out = R.copy()
    R_out[1, 1] = turn @ R_out[1, 1]
    with pytest.raises(ValueError, match=r"body 'link1' in world 1 leaves the plane .* A\[0, 1\]"):
        sim.set_body_states(P, R_out)
    P_out = P.copy()
    P_out[0, 2, 1] += 1e-3
    with pytest.raises(ValueError, match=r"body 'link2' in world 0 leaves the plane .* p\[1\] = 0.001"):
        sim.set_body_states(P_out, R)
    with pytest.raises(ValueError, match="leaves the plane"):
        sim.set_body_states(P, R, angular_velocities=np.tile([1.0, 0.0, 0.0], (2, 3, 1)))
    state = dict(before)
    state["q"] = before["q"].copy()
    state["q"][0, 1, 1] = 0.5
    with pytest.raises(ValueError, match=r"state\['q'\]: body 'link1' in world 0 leaves the plane"):
        sim.set_state(state)
    after = sim.get_state()
    for key in before:
        np.testing.assert_array_equal(after[key], before[key])
    sim.set_state(before)  # a state the simulator made is taken back
    sim.set_body_states(P, R)


DM_CONTROL = {"cartpole": "xz", "acrobot": "xz", "pendulum": "xz", "reacher": "xy"}
# dm_control's reacher lies flat under gravity along its plane's normal, as Reacher-v5 (TOLERANCE):
# its lighter links sag further, 2.1e-6 rad over 0.5 s apart (1.5e-15 with gravity off)
DM_TOLERANCE = {"reacher": 1e-5}


@pytest.mark.parametrize("model, plane", DM_CONTROL.items())
def test_imported_planar_models_are_solved_in_their_plane(model, plane):
    """dm_control's planar models (tests/data/dm_control, imported without their contacts) get their
    plane automatically; 0.5 s from random joint states equals the 12-unknown step (float64)."""
    import os
    import warnings

    path = os.path.join(os.path.dirname(__file__), "data", "dm_control", f"{model}.xml")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # "imported without contacts"
        scene = ag.Scene.from_mjcf(path, ignore_contacts=True)
    assert str(planar.plane_of(scene)) == plane
    reference = STAGED if not any(j.has_limit for j in scene.joints) else None
    full, _ = _trajectory(scene, False if reference is None else None, plan=reference, steps=50, worlds=2)
    reduced, sim = _trajectory(scene, None, steps=50, worlds=2)
    assert str(sim.plane) == plane
    assert np.abs(reduced - full).max() <= DM_TOLERANCE.get(model, 1e-9)
