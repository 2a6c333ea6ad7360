"""Coordinates of a closed loop: ``set_joint_state`` refuses those that leave the loop open (the gap
at the closing joint beyond loops.LOOP_TOL of its half_length), naming the argument, the world,
the joint and the gap, with nothing written, on the four-bar (a revolute joint closes it) and the
slider-crank (a prismatic joint); the coordinates that a step produced, read back after steps at
dt 0.1 s with the drive pushing, are accepted.  The host placement the check measures is the
device kernel's."""
import warnings

import numpy as np
import pytest

import abd_gym as ag
from abd_gym.bench import robustness
from abd_gym.sim import loops

W = 4


@pytest.fixture(scope="module", params=["fourbar", "slider_crank"])
def loop(request):
    """(name, scene, coordinates and rates of W worlds from the task's reset, the closing joint's name)."""
    scene, draw = robustness._fourbar() if request.param == "fourbar" else robustness._slider_crank()
    x, xd = draw(np.random.default_rng(3), W)
    return request.param, scene, (x, xd), "D" if request.param == "fourbar" else "slider"


def _same(a: dict, b: dict):
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def test_the_host_placement_is_the_kernels(loop):
    _, scene, (x, xd), _ = loop
    sim = ag.Simulator(scene, num_worlds=W, dtype="float64")
    x = x + np.random.default_rng(0).uniform(-0.01, 0.01, x.shape)  # a loop left slightly open
    sim.set_joint_state(x, xd)
    R, p = sim.loops.place(x)
    np.testing.assert_allclose(sim.body_positions(), p, atol=1e-12)
    np.testing.assert_allclose(sim.body_rotations(), R, atol=1e-12)
    gaps = sim.loops.gaps(x)[:, 0]
    assert gaps.max() > 1e-4  # open, within the tolerance
    # the residual the joint's energy sees: the gap itself (revolute), its offset part (prismatic)
    violation = sim.joint_violation(sim.loops.closing)
    if scene.joints[sim.loops.closing[0]].kind == "revolute":
        np.testing.assert_allclose(violation, gaps, rtol=1e-9)
    else:
        assert np.all(violation <= gaps * (1 + 1e-9))


def test_coordinates_that_leave_a_loop_open_are_refused(loop):
    name, scene, (x, xd), joint = loop
    for worlds in (W, 1):  # the batched door and a one-world simulator's (its own path on the CPU)
        sim = ag.Simulator(scene, num_worlds=worlds, dtype="float64")
        sim.set_joint_state(x[:worlds], xd[:worlds])
        before = sim.get_state()
        bad = x[:worlds].copy()
        bad[-1, 0] += 0.3  # the crank turned, the others left where they were
        with pytest.raises(ValueError, match=rf"coordinates: the coordinates in world {worlds - 1} leave the loop "
                                             rf"that joint '{joint}' closes open by \d"):  # fmt: skip
            sim.set_joint_state(bad, xd[:worlds])
        _same(sim.get_state(), before)
        with pytest.raises(ValueError, match=f"joint '{joint}'"):
            crank_only = np.where(np.arange(bad.shape[1]) == 0, 0.5, 0.0)[None].repeat(worlds, 0)
            sim.set_joint_state(crank_only)
        _same(sim.get_state(), before)
    gap = sim.loops.gaps(bad)[0, 0]
    assert gap > loops.LOOP_TOL * sim.loops.scale[0]


@pytest.mark.parametrize("integrator, dtype", [("bdf2", "float32"), ("implicit_euler", "float64")])
def test_states_a_step_produced_are_accepted(loop, integrator, dtype):
    """At dt 0.1 s with the crank's drive at full torque, either way at random: the joints' stretch
    reopens the loop when the read-back coordinates are placed again, and those are accepted, as
    are the joint rates and body spins read back (beyond pi a step)."""
    _, scene, (x, xd), _ = loop
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # dt 0.1 s is beyond what the scene's terms take
        sim = ag.Simulator(scene, num_worlds=W, dt=0.1, integrator=integrator, dtype=dtype)
    sim.set_joint_state(x, xd)
    rng = np.random.default_rng(1)
    worst = 0.0
    for _ in range(6):
        sim.set_controls(rng.choice([-1.0, 1.0], (W, 1)))
        sim.step()
        x_back, xd_back = sim.joint_coordinates(), sim.joint_velocities()
        worst = max(worst, float(sim.loops.gaps(x_back).max()))
        saved = sim.get_state()
        sim.set_joint_state(x_back, xd_back)
        sim.set_state(saved)
        # the bodies' produced state too: a crank at up to 40 rad/s, 4 rad a step (beyond pi: the
        # retry's substeps and BDF2's rate produce it, inputs.max_turn)
        sim.set_body_states(sim.body_positions(), sim.body_rotations(), sim.body_velocities()[..., :3],
                            sim.body_angular_velocities())  # fmt: skip
        sim.set_state(saved)
    assert worst > 1e-4  # the stretch reopened the loop (it is not closed by construction)


def test_a_task_whose_reset_leaves_its_loop_open_is_refused():
    from abd_gym.envs.fourbar import FourBarVectorEnv

    class OpenFourBar(FourBarVectorEnv):
        def initial_state(self, n, rng, options):
            x, xd = super().initial_state(n, rng, options)
            x[:, 0] += 0.3  # the crank turned, the others left where they were
            return x, xd

    env = OpenFourBar(num_envs=2)
    with pytest.raises(ValueError, match=r"coordinates: the coordinates in world 0 leave the loop that joint 'D'"):
        env.reset(seed=0)
    env.close()
