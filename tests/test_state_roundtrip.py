"""States round-trip: what the getters return after a step is accepted by the matching setter, and
get_state / set_state restore worlds bit for bit (the next steps identical to never having saved),
in both integrators and dtypes, for the simulator and for a vector env's task state."""
import numpy as np
import pytest

import abd_gym as ag
from abd_gym.envs.reacher import ReacherVectorEnv
from abd_gym.sim import mechanisms

W = 4
CASES = [(i, d) for i in ("implicit_euler", "bdf2") for d in ("float32", "float64")]


def _scene():
    """A cart-pole whose slider (±0.5 m) and pole (±0.3 rad) are limited, the slider driven."""
    scene = mechanisms.cartpole(track=0.5)
    scene.add_revolute_limit(1, -0.3, 0.3, 1e3)
    return scene


def _driven_into_limits(integrator, dtype):
    """W worlds pushed into both limits, with the drive on: states a step produced past the bounds."""
    sim = ag.Simulator(_scene(), num_worlds=W, dt=0.01, integrator=integrator, dtype=dtype)
    sim.set_joint_state([[0.4, 0.25], [-0.45, -0.28], [0.0, 0.29], [0.3, -0.1]],
                        [[3.0, 4.0], [-3.0, -5.0], [1.0, 6.0], [2.0, -2.0]])  # fmt: skip
    sim.set_controls([[10.0], [-10.0], [5.0], [8.0]])
    past = np.zeros((W, 2), dtype=bool)
    for _ in range(8):
        sim.step()
        x = sim.joint_coordinates()
        past |= (np.abs(x) > [0.5, 0.3])
    assert past[:, 1].any() and past[:, 0].any()  # the limits were penetrated, as a penalty is
    return sim


@pytest.fixture(scope="module", params=CASES, ids=lambda c: "-".join(c))
def case(request):
    return request.param


def _trajectory(sim, steps=6):
    out = []
    for k in range(steps):
        sim.set_controls(np.full((W, 1), 3.0 * (-1) ** k))
        sim.step()
        out.append((sim.body_q(), sim.joint_coordinates(), sim.joint_velocities(), sim.joint_angles_unwrapped(),
                    sim.world_status(), sim.newton_iterations()))  # fmt: skip
    return out


def _same(a, b):
    for x, y in zip(a, b):
        for u, v in zip(x, y):
            np.testing.assert_array_equal(u, v)


def test_produced_states_are_accepted_by_the_setters(case):
    sim = _driven_into_limits(*case)
    x, xd = sim.joint_coordinates(), sim.joint_velocities()
    sim.set_joint_state(x, xd)
    sim.step()
    sim.set_body_states(sim.body_positions(), sim.body_rotations(), sim.body_velocities()[..., :3],
                        sim.body_angular_velocities())  # fmt: skip
    sim.set_state(sim.get_state())


def test_get_state_set_state_restores_bit_for_bit(case):
    sim = _driven_into_limits(*case)
    saved = sim.get_state()
    want = _trajectory(sim)
    sim.set_state(saved)
    _same(_trajectory(sim), want)
    # into a fresh simulator, and into one world of a batch that went elsewhere
    other = ag.Simulator(_scene(), num_worlds=W, dt=0.01, integrator=case[0], dtype=case[1])
    other.set_state(saved)
    _same(_trajectory(other), want)
    other.reset()
    other.step(3)
    other.set_state({k: v[[2]] for k, v in saved.items()}, worlds=[2])
    got = _trajectory(other)
    for step, ref in zip(got, want):
        for u, v in zip(step, ref):
            np.testing.assert_array_equal(u[2], v[2])


def test_vector_env_state_restores_task_state():
    """A Reacher's target (task state), clocks, autoreset queues and generators come back: the env
    steps, truncates and resets as it did from the saved point."""
    env = ReacherVectorEnv(num_envs=3, max_episode_steps=5)
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, (12,) + env.action_space.shape).astype(np.float32)
    env.reset(seed=1)
    for a in actions[:3]:
        env.step(a)
    saved = env.get_state()

    def run():
        out = []
        for a in actions[3:]:
            obs, rew, term, trunc, _ = env.step(a)
            out.append((np.array(obs), np.array(rew), np.array(term), np.array(trunc)))
        return out

    want = run()
    env.set_state(saved)
    _same(run(), want)
    env.set_state(saved)  # a state restores more than once
    _same(run(), want)
    with pytest.raises(ValueError, match="state must be a dict"):
        env.set_state({"sim": saved["sim"]})
