"""Per-world failure semantics: a step is converged, retried from a fresh factor, or rejected
and reported (abd_gym.WorldStatus); a rejected world keeps its state and the others step on."""
import numpy as np
import pytest

import abd_gym as ag
from abd_gym import WorldStatus
from abd_gym.sim import mechanisms

PLANS = {"default": None, "staged": dict(fused=False), "global": dict(scratch="global"), "lanes": dict(scratch="lanes")}


def _poses(sim):
    """(positions, rotations) of every body of every world."""
    return sim.body_positions().copy(), sim.body_rotations().copy()


def test_a_spin_of_pi_a_step_is_refused():
    """set_body_states refuses an angular velocity of π rad a step or more (1e6 rad/s at dt 0.01 is
    10⁴ rad a step), naming the body and the world, and writes nothing."""
    sim = ag.Simulator(mechanisms.double_pendulum(), num_worlds=3, dt=0.01)
    sim.set_joint_state([[0.5, 0.2], [0.3, -0.4], [-0.2, 0.1]])
    p, R = _poses(sim)
    q0 = sim.body_q().copy()
    spin = np.zeros((1, 3, 3))
    spin[0, 2] = (0.0, 1e6, 0.0)
    with pytest.raises(ValueError, match=r"body 'link1' in world 1 turns at 1000000.0 rad/s"):
        sim.set_body_states(p[1:2], R[1:2], angular_velocities=spin, worlds=[1])
    np.testing.assert_array_equal(sim.body_q(), q0)
    spin[0, 2, 1] = 0.99 * np.pi / 0.01  # just under π a step: accepted
    sim.set_body_states(p[1:2], R[1:2], angular_velocities=spin, worlds=[1])


@pytest.mark.parametrize("dtype,plan", [("float32", "default"), ("float32", "staged"), ("float32", "global"),
                                        ("float32", "lanes"), ("float64", "default"), ("float64", "staged")])
def test_a_world_flung_at_1e25_m_s_is_reported_and_the_others_step_on(dtype, plan):
    """A world whose second link is set moving at 1e25 m/s (finite, but 1e23 m a step;
    the setters refuse it, inputs.state_bound) is reported
    at its first step: the solve breaks down or does not converge.  The step that reports it leaves
    its state as it was, it is not stepped again, and the other worlds are bit-identical to a batch
    stepped without it."""
    scene = mechanisms.double_pendulum()

    def batch(fling):
        sim = ag.Simulator(scene, num_worlds=3, dt=0.01, dtype=dtype, plan=PLANS[plan])
        sim.set_joint_state([[0.5, 0.2], [0.3, -0.4], [-0.2, 0.1]], [[0.0, 1.0], [2.0, 0.0], [0.0, 0.0]])
        if fling:  # past the setters' checks, which refuse such a velocity, into the restart they write by
            q = sim.body_q()[1:2]
            qd = np.zeros_like(q)
            qd[:, 1:, :3] = 1e25
            sim._set_q(np.array([1]), q, qd)
        return sim

    ref, bad = batch(False), batch(True)
    q_set = bad.body_q()[1].copy()
    for k in range(3):
        ref.step()
        bad.step()
        status = bad.world_status()
        assert status[[0, 2]].tolist() == [WorldStatus.OK] * 2
        assert status[1] != WorldStatus.OK and not bad.converged()[1]
        assert bad.failed_worlds().tolist() == [1]
        np.testing.assert_array_equal(bad.body_q()[1], q_set)
        np.testing.assert_array_equal(bad.body_q()[[0, 2]], ref.body_q()[[0, 2]])
        np.testing.assert_array_equal(bad.joint_coordinates()[[0, 2]], ref.joint_coordinates()[[0, 2]])
    # set again, the world steps as the others do
    bad.set_joint_state([[0.3, -0.4]], [[2.0, 0.0]], worlds=[1])
    assert bad.world_status().tolist() == [WorldStatus.OK] * 3
    bad.step(2)
    assert bad.failed_worlds().size == 0 and bad.converged().all()


@pytest.mark.parametrize("plan", ["default", "staged", "lanes"])
def test_a_stalled_reused_factor_is_retried_as_a_fresh_factor_solve(plan):
    """A float32 link spinning at 10-50 rad/s into a revolute limit at ±3.1 rad (strength 1e5, BDF2,
    dt 0.002), with the factor reused and a budget of 5 iterations, which a reused factor runs out of at the limit on
    some world-steps where a fresh one converges: the step is solved again from q̃ with a fresh
    factor at every iteration.  A retried step either converges (and is committed) or is rejected
    (the world keeps qⁿ); the retries save most of the steps they take up, and no committed step
    is unconverged."""
    W = 64
    scene = mechanisms.pendulum(limit=(-3.1, 3.1, 1e5))
    sim = ag.Simulator(scene, num_worlds=W, dt=0.002, integrator="bdf2", dtype="float32", max_iterations=5,
                       reuse_factor=True, plan=PLANS[plan])  # fmt: skip
    rng = np.random.default_rng(0)
    rates = rng.uniform(10, 50, W) * rng.choice([-1, 1], W)
    sim.set_joint_state(2.0 * np.sign(rates)[:, None], rates[:, None])
    retried = rejected = 0
    for _ in range(120):
        ok = sim.world_status() == WorldStatus.OK
        q_before = sim.body_q()
        sim.step()
        status = sim.world_status()
        done = ok & (status == WorldStatus.OK)
        assert sim.converged()[done].all()
        again = ok & sim.newton_retried()
        dropped = ok & (status != WorldStatus.OK)
        assert (status[dropped] != WorldStatus.NONFINITE).all()
        np.testing.assert_array_equal(sim.body_q()[dropped], q_before[dropped])
        retried += int(again.sum())
        rejected += int(dropped.sum())
    assert retried >= 3  # the case exercises the retry
    assert rejected < retried / 2


def test_factor_reuse_off_rejects_without_a_retry():
    """Without factor reuse (the default) there is no retry: a step that does not converge in
    max_iterations is rejected at once, and newton_retried stays False."""
    sim = ag.Simulator(mechanisms.double_pendulum(), num_worlds=2, dt=0.01, dtype="float64", max_iterations=1,
                       retry=False)
    sim.set_joint_state([[1.0, -0.5], [0.5, 0.0]], [[5.0, -5.0], [0.0, 3.0]])
    q0 = sim.body_q().copy()
    sim.step()
    assert sim.world_status().tolist() == [WorldStatus.UNCONVERGED] * 2
    assert not sim.newton_retried().any() and sim.newton_iterations().tolist() == [1, 1]
    np.testing.assert_array_equal(sim.body_q(), q0)


def test_status_codes_are_named():
    """The codes are the documented IntEnum's; a non-finite state is NONFINITE."""
    assert [int(s) for s in WorldStatus] == [0, 1, 2, 3]
    sim = ag.Simulator(mechanisms.pendulum(), num_worlds=2, dt=0.01, dtype="float64")
    q = sim.state.q.numpy()
    q[0, 1, 0] = np.inf
    sim.state.q.assign(q)
    sim.step()
    assert [WorldStatus(c).name for c in sim.world_status()] == ["NONFINITE", "OK"]
