"""A failed step is retried as 2, then 4 substeps before it is rejected (solver/retry.py): only the
failed worlds step again, a retried world takes the step a simulator of dt/2 (dt/4) takes, the
worlds that converge are bit-identical to a batch without retries, and a world that fails at 4
substeps too keeps its state."""
import numpy as np
import pytest

import abd_gym as ag
from abd_gym import WorldStatus
from abd_gym.sim import mechanisms

W, DT = 16, 0.2
# dt 0.2 s turns these links 1.25 rad a step: the build warns (conditioning.step_too_large)
pytestmark = pytest.mark.filterwarnings("ignore:dt 0.2 s is beyond what body")


def _start():
    """Double pendulums released from ±2.5 rad at ±3 rad/s: at dt 0.2 s a few fail their first
    steps (Newton does not converge in 50 iterations)."""
    rng = np.random.default_rng(0)
    return rng.uniform(-2.5, 2.5, (W, 2)), rng.uniform(-3.0, 3.0, (W, 2))


def _sim(dt=DT, integrator="implicit_euler", **kw):
    kw.setdefault("retry", True)  # the default on the CPU; on a GPU the retry is asked for
    sim = ag.Simulator(mechanisms.double_pendulum(), num_worlds=W, dt=dt, integrator=integrator, dtype="float64", **kw)
    sim.set_joint_state(*_start())
    return sim


@pytest.mark.parametrize("integrator", ["implicit_euler", "bdf2"])
def test_failed_worlds_are_retried_and_the_others_are_untouched(integrator):
    plain, retried = _sim(integrator=integrator, retry=False), _sim(integrator=integrator)
    healthy = np.ones(W, dtype=bool)  # every step so far OK without retries, and 1 substep with them
    counts = np.zeros(5, dtype=int)
    for _ in range(5):
        plain.step()
        retried.step()
        n = retried.substeps()
        counts += np.bincount(n, minlength=5)
        healthy &= (plain.world_status() == WorldStatus.OK) & (n == 1)
        np.testing.assert_array_equal(retried.body_q()[healthy], plain.body_q()[healthy])
        np.testing.assert_array_equal(retried.joint_coordinates()[healthy], plain.joint_coordinates()[healthy])
        np.testing.assert_array_equal(retried.newton_iterations()[healthy], plain.newton_iterations()[healthy])
        ok = retried.world_status() == WorldStatus.OK
        assert retried.converged()[ok].all()
    assert len(plain.failed_worlds()) >= 5 and len(retried.failed_worlds()) == 0
    assert counts[2] > 0 and counts[4] > 0  # both retries happen
    assert not healthy.all()


@pytest.mark.parametrize("n", [2, 4])
def test_a_retried_step_is_the_substeps_step(n):
    """Implicit Euler: a world retried as n substeps ends where a simulator of dt/n ends after n
    steps from the same state (get_state before the step), to Newton's stop ‖Δq‖∞ < tol·h = 1e-6 m
    (the retry starts each substep from its own guess), the simulator's joints at strength γ/n²:
    a substep keeps the joints' stiffness K/dt² of the step it replaces (constitutions/_joint_step.py)."""
    sim = _sim()
    for _ in range(5):
        saved = sim.get_state()
        sim.step()
        worlds = np.flatnonzero(sim.substeps() == n)
        if len(worlds):
            break
    assert len(worlds)
    ref = ag.Simulator(mechanisms.double_pendulum(), num_worlds=W, dt=DT / n, integrator="implicit_euler",
                       dtype="float64", retry=False)  # fmt: skip
    ref.set_joint_strength(np.tile(ref.scene.strength_ratios() / n**2, (W, 1)))
    ref.set_state(saved)
    ref.step(n)
    good = worlds[ref.world_status()[worlds] == WorldStatus.OK]
    assert len(good)
    np.testing.assert_allclose(sim.body_q()[good], ref.body_q()[good], rtol=0, atol=1e-5)
    assert not np.array_equal(sim.body_q()[worlds], saved["q"][worlds])  # they moved


def test_a_world_failing_at_four_substeps_is_rejected_with_its_state():
    sim = _sim(max_iterations=1)
    q0 = sim.body_q()
    sim.step()
    bad = sim.failed_worlds()
    assert len(bad) and (sim.substeps()[bad] == 4).all()
    assert (sim.world_status()[bad] == WorldStatus.UNCONVERGED).all()
    np.testing.assert_array_equal(sim.body_q()[bad], q0[bad])
    before = sim.body_q()
    sim.step()  # a rejected world is not stepped (nor retried) again
    np.testing.assert_array_equal(sim.body_q()[bad], before[bad])


def test_the_staged_step_is_retried_too():
    fused, staged = _sim(), _sim(plan=dict(fused=False))
    fused.step()
    staged.step()
    np.testing.assert_array_equal(staged.substeps(), fused.substeps())
    np.testing.assert_allclose(staged.body_q(), fused.body_q(), rtol=0, atol=1e-9)


def test_the_vector_env_reports_substeps():
    from abd_gym.envs.cartpole import CartPoleVectorEnv

    env = CartPoleVectorEnv(num_envs=2)
    env.reset(seed=0)
    info = env.step(np.zeros((2, 1), dtype=np.float32))[4]
    np.testing.assert_array_equal(info["sim_substeps"], [1, 1])


def test_the_vector_envs_step_retries_too():
    """A budget of 2 Newton iterations, which CartPoleSwingUp-v0's steps outrun: the env's step (on
    the device, with autoresets) retries world-steps as 2 and 4 substeps, and a world it reports
    failed had failed at 4 too."""
    from abd_gym.envs.cartpole_swingup import CartPoleSwingUpVectorEnv

    env = CartPoleSwingUpVectorEnv(num_envs=4, dtype="float64", simulator_options=dict(max_iterations=2))
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    counts = np.zeros(5, dtype=int)
    for _ in range(10):
        info = env.step(rng.uniform(-1, 1, (4, 1)).astype(np.float32))[4]
        n = info["sim_substeps"]
        counts += np.bincount(n, minlength=5)
        assert (n[info["sim_failed"]] == 4).all()
    assert counts[2] > 0 and counts[4] > 0


@pytest.mark.parametrize("name", ["large_dt", "fourbar"])
def test_rejections_at_dt_0_2_fall_tenfold(name):
    """The robustness report's double pendulums and four-bar at dt 0.2 s (16 worlds, 1 s): the
    worlds rejected with the retry are at most a tenth of those without."""
    from abd_gym.bench import robustness as rb

    case = rb.case(name)
    scene = case.scene()
    rows = {retry: rb.run_case(case, 0.2, "bdf2", "float32", worlds=16, steps=5, scene=scene, retry=retry)
            for retry in (True, False)}  # fmt: skip
    assert rows[False]["reported"] >= 5
    assert 10 * rows[True]["reported"] <= rows[False]["reported"]
    assert rows[True]["substeps"][2] + rows[True]["substeps"][4] >= rows[False]["reported"]


def test_substeps_return_to_one_after_a_retried_step():
    """The count is the last step's: after a retried step, a step every world takes whole reads 1
    (on the CPU the check launches nothing while every world is OK and the last step took 1)."""
    sim = _sim()
    for _ in range(5):
        sim.step()
        if (sim.substeps() > 1).any():
            break
    assert (sim.substeps() > 1).any()
    sim.set_joint_state(np.zeros((W, 2)))  # at rest, hanging: every world's step converges
    sim.step()
    np.testing.assert_array_equal(sim.substeps(), np.ones(W))
    sim.step()
    np.testing.assert_array_equal(sim.substeps(), np.ones(W))
    state = sim.get_state()
    state["substeps"][:] = 2  # a restored count: the next step's check sets it again
    sim.set_state(state)
    sim.step()
    np.testing.assert_array_equal(sim.substeps(), np.ones(W))
