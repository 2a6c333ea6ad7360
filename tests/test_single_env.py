"""The single env's lean CPU step (abd_gym.vector.single_step) is its vector env's world's step.

``gym.make`` envs step one world on the CPU through HostStep, with the one-launch physics
(ExecutionPlan.one_launch) replayed from a captured graph; the vector env of the same task
steps its worlds through the batched path with the default plan (five launches a step).  Both
are compared here bit for bit: observations, rewards, flags and info, over random actions
(out-of-range ones included), past terminations, for a task with the default controls, one with
its own controls hook (TwoLinkReacher-v0), float64 physics and failed worlds.
"""
from unittest import mock

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode

import abd_gym  # noqa: F401 -- registers the ids
from abd_gym.vector.registration import TASKS
from abd_gym.vector.single_step import HostStep

STEPS = 30
LEAN = ("CartPole-v0", "InvertedPendulum-v5")  # the tasks with one-world hooks (Task.world_observation, ...)


def _pair(task, seed=3, **kwargs):
    """(the gym.make env unwrapped, a 1-world vector env of its task with autoreset off), both reset with ``seed``."""
    single = gym.make(f"abd_gym/{task}", **kwargs).unwrapped
    vector = single.vector_class(num_envs=1, autoreset_mode=AutoresetMode.DISABLED, **kwargs)
    obs_s, _ = single.reset(seed=seed)
    obs_v, _ = vector.reset(seed=seed)
    np.testing.assert_array_equal(obs_s, obs_v[0])
    return single, vector


def _compare(single, vector, steps=STEPS, seed=0):
    """Step both with the same random actions (up to 1.5× the bound); returns the single env's infos."""
    rng = np.random.default_rng(seed)
    bound = float(single.action_space.high[0])
    infos = []
    for t in range(steps):
        a = rng.uniform(-1.5, 1.5, size=single.action_space.shape).astype(np.float32) * bound
        obs, reward, terminated, truncated, info = single.step(a)
        v_obs, v_reward, v_term, v_trunc, v_info = vector.step(a[None])
        assert obs.dtype == np.float32 and obs.shape == single.observation_space.shape
        np.testing.assert_array_equal(obs, v_obs[0], err_msg=f"step {t}")
        assert type(reward) is float and reward == float(v_reward[0]), t
        assert (terminated, truncated) == (bool(v_term[0]), bool(v_trunc[0])), t
        assert info.keys() == {k for k in v_info if not k.startswith("_")}, t
        for key, value in info.items():
            assert np.asarray(value).tolist() == np.asarray(v_info[key])[0].tolist(), (t, key)
        infos.append(info)
    return infos


@pytest.mark.parametrize("task,kwargs", [(name, {}) for name in TASKS] + [("CartPole-v0", {"dtype": "float64"})])
def test_single_env_steps_as_the_vector_envs_world_bit_for_bit(task, kwargs):
    single, vector = _pair(task, **kwargs)
    assert isinstance(single._host_step, HostStep)
    assert single._host_step.lean == (task in LEAN and not kwargs)  # the Python-float step where a task has it
    single._host_step.numpy_step = mock.Mock(wraps=single._host_step.numpy_step)
    assert single.sim.plan.one_launch and not vector.sim.plan.one_launch  # two ways of launching one step
    infos = _compare(single, vector)
    assert type(infos[0]["sim_status"]) is int and type(infos[0]["sim_failed"]) is bool
    # every step of _compare's float32 actions takes the Python-float step where the task has it
    assert single._host_step.numpy_step.call_count == (0 if single._host_step.lean else STEPS)
    single.reset(seed=5)
    vector.reset(seed=5)
    _compare(single, vector, steps=10, seed=1)  # after a reset as well


def test_failed_world_is_reported_as_the_vector_env_does():
    """An iteration budget of 1 leaves some steps unconverged: a rejected step gives a zero
    observation and reward, terminated, sim_failed and the status code, in both envs alike."""
    options = {"simulator_options": {"max_iterations": 1}}
    single, vector = _pair("CartPole-v0", **options)
    infos = _compare(single, vector)
    failed = [info for info in infos if info["sim_failed"]]
    assert failed and all(info["sim_status"] == int(abd_gym.WorldStatus.UNCONVERGED) for info in failed)


def test_non_finite_observation_fails_the_world_as_the_vector_env_does():
    """A NaN in the task's observation (an infinite entry clips to the bound): zero observation and
    reward, terminated and sim_failed, with the world's status left OK."""
    single, vector = _pair("CartPole-v0")
    for env in (single.vector_env, vector):
        env.observe = lambda env=env: np.array([[np.nan, np.inf, 0.1, 0.2]])
    single.vector_env.world_observation = lambda q, v: [np.nan, np.inf, 0.1, 0.2]  # the single env's lean step
    infos = _compare(single, vector, steps=2)
    assert all(info["sim_failed"] and info["sim_status"] == 0 for info in infos)


def test_nan_action_raises_and_steps_nothing():
    env = gym.make("abd_gym/CartPole-v0")
    env.reset(seed=0)
    sim = env.unwrapped.sim
    q, time = sim.body_q(), sim.state.time.copy()
    with pytest.raises(ValueError, match="NaN"):
        env.step(np.array([np.nan], dtype=np.float32))
    with pytest.raises(ValueError, match="1 entries"):
        env.step(np.zeros(2, dtype=np.float32))
    np.testing.assert_array_equal(sim.body_q(), q)
    np.testing.assert_array_equal(sim.state.time, time)
    np.testing.assert_array_equal(sim.host_view(sim.state.control), 0.0)
    env.step(np.array([np.inf], dtype=np.float32))  # clipped to the bound, as the vector env does
    assert sim.host_view(sim.state.control)[0, 0] == 10.0


def test_plan_given_in_simulator_options_is_kept():
    env = gym.make("abd_gym/CartPole-v0", simulator_options={"plan": {"one_launch": False}})
    assert not env.unwrapped.sim.plan.one_launch


def test_lean_step_takes_other_actions_as_the_vector_env_does():
    """Actions that are not float32 arrays of the action space's shape (float64, a list, a (1, 1)
    array, float16) take the NumPy step; both give the vector env's world's steps."""
    single, vector = _pair("CartPole-v0")
    single._host_step.numpy_step = mock.Mock(wraps=single._host_step.numpy_step)
    for t, a in enumerate([np.array([0.3]), [0.7], np.array([[-2.0]], dtype=np.float32), np.array([0.1], np.float16)]):
        obs, reward, terminated, _, _ = single.step(a)
        v_obs, v_reward, v_term, _, _ = vector.step(np.asarray(a, dtype=np.float32).reshape(1, 1))
        np.testing.assert_array_equal(obs, v_obs[0], err_msg=f"action {t}")
        assert (reward, terminated) == (float(v_reward[0]), bool(v_term[0])), t
    assert single._host_step.numpy_step.call_count == 4


@pytest.fixture(scope="module")
def lean_envs():
    """{task: its 1-world vector env} of the tasks with one-world hooks."""
    return {task: gym.make(f"abd_gym/{task}").unwrapped.vector_env for task in LEAN}


@pytest.mark.parametrize("task", LEAN)
def test_world_hooks_give_the_batched_hooks_values(task, lean_envs):
    """world_observation / world_reward / world_terminated against observe / reward / terminated
    on random states and on observations at the float32 neighbours of every bound and threshold."""
    env = lean_envs[task]
    sim, rng = env.sim, np.random.default_rng(0)
    for _ in range(20):  # observation: random joint states within the limits
        x, xd = env.initial_state(1, rng, {"low": -0.3, "high": 0.3} if task == "CartPole-v0" else {})
        sim.set_joint_state(x * 5, xd * 50)
        q, v = sim.joint_coordinates(), sim.joint_velocities()
        world = np.array(env.world_observation(q[0].tolist(), v[0].tolist()), dtype=np.float32)
        np.testing.assert_array_equal(world, env.f32(env.observe())[0])
    high = env._obs_high
    values = [0.0, -0.0, 0.1, 0.2, 0.19999999, 0.2000001, 2.4, 1.0, 3.0, 4.8, 100.0, 1e-30]
    edges = {np.float32(s * v) for v in values for s in (1, -1)} | {np.nextafter(np.float32(v), np.float32(d))
                                                                   for v in values for d in (0, 10)}  # fmt: skip
    edges = np.array(sorted(edges), dtype=np.float32)
    obs = np.clip(rng.choice(edges, size=(400, high.size)), -high, high).astype(np.float32)
    actions = rng.uniform(-3, 3, size=(400, env.action_dim)).astype(np.float32)
    reward, terminated = env.f32(env.reward(obs, actions)), env.terminated(obs)
    for i in range(len(obs)):
        o, a = obs[i].tolist(), actions[i].tolist()
        assert env.world_reward(o, a) == float(reward[i]) and type(env.world_reward(o, a)) is float, obs[i]
        assert bool(env.world_terminated(o)) == bool(terminated[i]), obs[i]
    env.theta_threshold = 0.05  # a threshold set on the env is read at the next call, as the batched hooks read it
    try:
        terminated = env.terminated(obs)
        assert [bool(env.world_terminated(o)) for o in obs.tolist()] == terminated.tolist()
        assert terminated.any() and not terminated.all()
    finally:
        del env.theta_threshold


@pytest.mark.parametrize("name", TASKS)
def test_one_world_set_joint_state_as_the_checked_path_writes_it(name):
    """A one-world CPU simulator's set_joint_state from float64 arrays (its plain-Python path) writes
    the state that the same values as lists (the NumPy path) write, bit for bit, and the steps
    after it are the same."""
    sims = [gym.make(f"abd_gym/{name}").unwrapped.vector_env for _ in range(2)]
    rng = np.random.default_rng(1)
    x, xd = sims[0].initial_state(1, rng, {})
    assert x.dtype == np.float64 and x.shape == (1, sims[0].scene.num_joints)
    sims[0].sim.set_joint_state(x, xd)
    sims[1].sim.set_joint_state(x.tolist(), xd.tolist())
    assert sims[0].sim._world0_graph is not None and sims[1].sim._world0_graph is None  # the two paths
    for _ in range(2):
        a, b = (s.sim.get_state() for s in sims)
        assert a.keys() == b.keys()
        for key in a:
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)
        for s in sims:
            s.sim.step()


def test_one_world_set_joint_state_refuses_what_the_checked_path_refuses():
    """Values the plain-Python path's checks do not pass go to the NumPy path, which refuses them
    naming the joint and writes nothing; values it passes are taken."""
    sim = gym.make("abd_gym/CartPole-v0").unwrapped.sim
    before = sim.get_state()
    # the slider's limit [-2.4, 2.4] m holds 4.8 m (its range) beyond either bound
    cases = [([[2.4 + 4.81, 0.0]], "slider"), ([[0.0, np.nan]], "hinge0"), ([[np.inf, 0.0]], "slider"),
             ([[0.0, 0.0]], "hinge0")]  # fmt: skip
    turn = 4 * np.pi  # the most |rate|·dt a step produces: the retry's quarter substeps (inputs.max_turn)
    rates = [[[0.0, 0.0]]] * 3 + [[[0.0, turn / sim.dt]]]  # the last turns the hinge by 4 pi in a step
    for (x, joint), xd in zip(cases, rates):
        with pytest.raises(ValueError, match=joint):
            sim.set_joint_state(np.array(x), np.array(xd))
        after = sim.get_state()
        for key in before:
            np.testing.assert_array_equal(after[key], before[key], err_msg=key)
    sim.set_joint_state(np.array([[2.4 + 4.79, 0.0]]), np.array([[0.0, turn / sim.dt * 0.99]]))  # within what holds
    assert sim.joint_coordinates()[0, 0] == pytest.approx(7.19, abs=1e-5)


def test_initial_states_are_the_draws_of_the_tasks_distribution(lean_envs):
    """CartPole-v0: x, ẋ, θ, θ̇ from one uniform draw (4,) a world; InvertedPendulum-v5: qpos
    (n, 2), then qvel (n, 2), each uniform in ±reset_noise_scale, from the same stream."""
    rng, ref = np.random.default_rng(5), np.random.default_rng(5)
    x, xd = lean_envs["CartPole-v0"].initial_state(3, rng, {})
    s = ref.uniform(-0.05, 0.05, size=(3, 4))
    np.testing.assert_array_equal(x, s[:, [0, 2]])
    np.testing.assert_array_equal(xd, s[:, [1, 3]])
    x, xd = lean_envs["InvertedPendulum-v5"].initial_state(3, rng, {})
    np.testing.assert_array_equal(x, ref.uniform(-0.01, 0.01, size=(3, 2)))
    np.testing.assert_array_equal(xd, ref.uniform(-0.01, 0.01, size=(3, 2)))


@pytest.mark.parametrize("num_envs", [1, 2])
def test_stepper_steps_as_step_bit_for_bit(num_envs):
    """Simulator.stepper(k) (the captured step's replay and the clock) against step(k): the whole
    state, the clock included, after each of a few steps with changing controls."""
    from abd_gym.envs.cartpole import CartPoleVectorEnv

    envs = [CartPoleVectorEnv(num_envs, autoreset_mode=AutoresetMode.DISABLED) for _ in range(2)]
    for env in envs:
        env.reset(seed=2)
    a, b = envs[0].sim, envs[1].sim
    assert a.stepper(2) is None  # before step(2) has captured it
    for t in range(5):
        controls = np.full((num_envs, 1), 3.0 * (t - 2))
        for sim in (a, b):
            sim.set_controls(controls)
        a.step(2)
        stepper = b.stepper(2)
        b.step(2) if stepper is None else stepper()
        sa, sb = a.get_state(), b.get_state()
        for key in sa:
            np.testing.assert_array_equal(sa[key], sb[key], err_msg=f"step {t}: {key}")
    assert b.stepper(2) is not None


def test_a_task_with_some_world_hooks_is_refused():
    """A task gives all three one-world hooks or none: HostStep refuses one with some, naming them."""
    from abd_gym.envs.cartpole import CartPoleVectorEnv

    partial = type("PartialHooks", (CartPoleVectorEnv,), {"world_reward": None})
    with pytest.raises(TypeError, match="world_observation, world_reward and world_terminated"):
        HostStep(partial(1, autoreset_mode=AutoresetMode.DISABLED))


def test_a_world_observation_of_another_length_is_refused():
    from abd_gym.envs.cartpole import CartPoleVectorEnv

    short = type("ShortObservation", (CartPoleVectorEnv,), {"world_observation": lambda self, q, v: q + v[:1]})
    with pytest.raises(ValueError, match="world_observation gives 3 values, the observation space has 4"):
        HostStep(short(1, autoreset_mode=AutoresetMode.DISABLED))
