"""Gymnasium's MuJoCo classics on abd_gym against Gymnasium's own envs (MuJoCo C).

For the same simulator state, the observation, reward and termination agree with what
Gymnasium's env computes from it (``_get_obs`` and its reward terms after ``set_state``); from
the same initial state with the same actions, a short rollout stays close to Gymnasium's (the
engines differ: abd_gym's BDF2 on affine bodies against MuJoCo's RK4, at the file's timestep).
One env of each task (few worlds) is shared by the module's tests.
"""
import math

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode

import abd_gym  # noqa: F401 -- registers the ids
from abd_gym.vector.registration import TASKS

pytest.importorskip("mujoco")

CLASSICS = {"InvertedPendulum-v5": "InvertedPendulumVectorEnv",
            "InvertedDoublePendulum-v5": "InvertedDoublePendulumVectorEnv",
            "Reacher-v5": "ReacherV5VectorEnv"}  # fmt: skip
N = 3
_ENVS = {}


def ours(name):
    """The shared abd_gym env of task ``name`` (N worlds, no autoreset: the tests set states)."""
    if name not in _ENVS:
        import importlib

        module = importlib.import_module(TASKS[name][0])
        _ENVS[name] = getattr(module, CLASSICS[name])(N, autoreset_mode=AutoresetMode.DISABLED)
        _ENVS[name].reset(seed=0)
    return _ENVS[name]


def theirs(name):
    return gym.make(name).unwrapped


def gym_state(env, q, v, target=None):
    """Gymnasium's env ``env`` put at joint coordinates q and rates v (and a Reacher's target)."""
    qpos, qvel = np.array(q, dtype=np.float64), np.array(v, dtype=np.float64)
    if target is not None:
        qpos, qvel = np.r_[qpos, target], np.r_[qvel, 0.0, 0.0]
    env.set_state(qpos, qvel)


def random_states(env, rng, scale):
    """(N, joints) coordinates and rates drawn around the zero pose, inside every joint limit."""
    nj = env.scene.num_joints
    q = rng.uniform(-scale[0], scale[0], (N, nj))
    v = rng.uniform(-scale[1], scale[1], (N, nj))
    for j, joint in enumerate(env.scene.joints):
        if joint.has_limit:
            q[:, j] = np.clip(q[:, j], joint.attributes["limit/lower"], joint.attributes["limit/upper"])
    return q, v


# ----------------------------------------------------------------------------- spaces and registration
@pytest.mark.parametrize("name", CLASSICS)
def test_spaces_timing_and_limits_are_gymnasiums(name):
    env, ref = ours(name), theirs(name)
    spec, ref_spec = gym.spec(f"abd_gym/{name}"), gym.spec(name)
    assert (spec.max_episode_steps, spec.reward_threshold) == (ref_spec.max_episode_steps, ref_spec.reward_threshold)
    assert env.dt == ref.model.opt.timestep == env.imported.timestep
    assert env.frame_skip == ref.frame_skip and math.isclose(env.step_dt, ref.dt)
    a, b = env.single_action_space, ref.action_space
    assert a.shape == b.shape and np.array_equal(a.low, b.low) and np.array_equal(a.high, b.high)
    assert env.single_observation_space.shape == ref.observation_space.shape
    assert env.single_observation_space.dtype == np.float32
    # the action's drive input is gear · ctrl
    ctrl = (np.linspace(-1.0, 1.0, N)[:, None] * b.high[None, :]).astype(np.float32)
    np.testing.assert_allclose(env.controls(ctrl), ctrl * ref.model.actuator_gear[:, 0], rtol=1e-6)


# ----------------------------------------------------------------------------- observation, reward, termination
def _agree(name, q, v, actions, target=None):
    """Our observation, reward and termination at (q, v) against Gymnasium's at the same state."""
    env, ref = ours(name), theirs(name)
    env.sim.set_joint_state(q, v)
    obs = env.observation()
    rew = env.reward(obs, actions)
    term = env.terminated(obs)
    for w in range(N):
        gym_state(ref, q[w], v[w], None if target is None else target[w])
        yield w, obs[w], rew[w], bool(term[w]), ref, ref._get_obs()


def test_inverted_pendulum_observation_reward_termination_agree():
    rng = np.random.default_rng(0)
    env = ours("InvertedPendulum-v5")
    for scale in ((0.1, 0.5), (0.4, 2.0)):  # upright, and past the 0.2 rad threshold
        q, v = random_states(env, rng, scale)
        for w, obs, rew, term, ref, ref_obs in _agree("InvertedPendulum-v5", q, v, np.zeros((N, 1), np.float32)):
            np.testing.assert_allclose(obs, ref_obs, rtol=1e-6, atol=1e-6)
            ref_term = bool(np.abs(ref_obs[1]) > 0.2)  # InvertedPendulumEnv.step
            assert term == ref_term and rew == float(not ref_term)


def test_inverted_double_pendulum_observation_reward_termination_agree():
    """Site ``tip`` from the abd bodies' poses against MuJoCo's kinematics: within 1e-5 m (float32
    poses); the limit-force entry is 0 in both away from the slider's ends."""
    rng = np.random.default_rng(1)
    env = ours("InvertedDoublePendulum-v5")
    terms = []
    for scale in ((0.1, 1.0), (1.2, 3.0)):
        q, v = random_states(env, rng, scale)
        q[:, 0] = np.clip(q[:, 0], -0.9, 0.9)
        for w, obs, rew, term, ref, ref_obs in _agree("InvertedDoublePendulum-v5", q, v, np.zeros((N, 1), np.float32)):
            np.testing.assert_allclose(obs, ref_obs, rtol=1e-5, atol=2e-5)
            x, _, y = ref.data.site_xpos[0]
            ref_term = bool(y <= 1)
            ref_rew, _ = ref._get_rew(x, y, ref_term)
            assert term == ref_term
            np.testing.assert_allclose(rew, ref_rew, rtol=1e-5, atol=1e-4)  # (y − 2)² with y to 1e-5 m
            terms.append(term)
    assert any(terms) and not all(terms)


def test_reacher_observation_and_reward_agree():
    rng = np.random.default_rng(2)
    env = ours("Reacher-v5")
    target = np.array([[0.1, -0.05], [-0.15, 0.08], [0.0, 0.19]])
    env.reset(seed=0, options={"target": (0.0, 0.0)})
    env.put(env.episodes.task, np.arange(N), target)
    q, v = random_states(env, rng, (3.0, 5.0))
    actions = rng.uniform(-1, 1, (N, 2)).astype(np.float32)
    for w, obs, rew, _, ref, ref_obs in _agree("Reacher-v5", q, v, actions, target):
        np.testing.assert_allclose(obs, ref_obs, rtol=1e-5, atol=2e-5)
        ref_rew, _ = ref._get_rew(actions[w].astype(np.float64))
        np.testing.assert_allclose(rew, ref_rew, rtol=1e-5, atol=2e-5)


def test_inverted_double_pendulum_limit_force_pushes_back_as_mujocos():
    """Pushed into the slider's upper end: the observed limit force is negative, as MuJoCo's
    qfrc_constraint[0] is there, and clipped to −10 as Gymnasium clips it."""
    env, ref = ours("InvertedDoublePendulum-v5"), theirs("InvertedDoublePendulum-v5")
    env.sim.set_joint_state(np.zeros((N, 3)), np.zeros((N, 3)))
    gym_state(ref, np.zeros(3), np.zeros(3))
    push = np.ones((N, 1), np.float32)
    ours_f, theirs_f = [], []
    for _ in range(12):
        obs = env.step(push)[0]
        ref_obs = ref.step(push[0].astype(np.float64))[0]
        ours_f.append(obs[0, 8])
        theirs_f.append(ref_obs[8])
    ours_f, theirs_f = np.array(ours_f), np.array(theirs_f)
    assert ours_f.min() == -10.0 and theirs_f.min() == -10.0
    assert np.all(ours_f <= 0) and np.all(theirs_f <= 1e-9)
    assert ours_f[0] == 0.0 and theirs_f[0] == 0.0  # the cart starts mid-track


# ----------------------------------------------------------------------------- short rollouts
ROLLOUT_SCALE = {  # initial coordinates and rates drawn in ±these [m or rad, per s]
    "InvertedPendulum-v5": (0.05, 0.2),
    "InvertedDoublePendulum-v5": (0.05, 0.2),
    "Reacher-v5": (0.5, 0.5),
}


def rollouts(name, steps, action_scale):
    """(largest |Δq| between the engines, largest |q − q0| in Gymnasium's) over ``steps`` env steps
    from the same initial states with the same random actions (``action_scale`` × the range)."""
    env, ref = ours(name), theirs(name)
    rng = np.random.default_rng(3)
    q0, v0 = random_states(env, rng, ROLLOUT_SCALE[name])
    env.sim.set_joint_state(q0, v0)
    high = env.single_action_space.high
    actions = (action_scale * rng.uniform(-high, high, (steps, N, len(high)))).astype(np.float32)
    mine = []
    for k in range(steps):
        env.step(actions[k])
        mine.append(env.sim.joint_coordinates())
    err = motion = 0.0
    nj = env.scene.num_joints
    for w in range(N):
        gym_state(ref, q0[w], v0[w], np.zeros(2) if name == "Reacher-v5" else None)
        for k in range(steps):
            ref.do_simulation(actions[k, w].astype(np.float64), ref.frame_skip)
            d = mine[k][w] - ref.data.qpos[:nj]
            err = max(err, np.abs(np.arctan2(np.sin(d), np.cos(d))).max())  # hinge angles wrap
            motion = max(motion, np.abs(ref.data.qpos[:nj] - q0[w]).max())
    return err, motion


@pytest.mark.parametrize("name", CLASSICS)
def test_short_passive_rollout_stays_close_to_gymnasiums(name):
    """No control, 10 env steps (0.2–0.5 s) from states near the start: the coordinates of the two
    engines stay within 3% of how far they moved (the upright pendulums fall away, the reacher
    coasts against its damping)."""
    err, motion = rollouts(name, 10, 0.0)
    assert motion > 0.05 and err < 0.03 * motion, (err, motion)


@pytest.mark.parametrize("name", CLASSICS)
def test_short_driven_rollout_stays_close_to_gymnasiums(name):
    """Random controls (±20% of the range, new each env step), 5 env steps: within 15% of the
    motion.  A control that jumps each step costs BDF2 (a two-step method, which starts from an
    implicit Euler step) about a·h² per jump, for the acceleration a it adds; MuJoCo's RK4
    restarts at every step."""
    err, motion = rollouts(name, 5, 0.2)
    assert motion > 0.1 and err < 0.15 * motion, (err, motion)


@pytest.mark.parametrize("name", CLASSICS)
def test_torch_backend_steps_as_numpy(name):
    """The Torch backend (here on the CPU) gives the NumPy backend's observations, rewards and flags,
    through terminations, truncations and their autoresets (NEXT_STEP, the queued episodes)."""
    import importlib

    torch = pytest.importorskip("torch")
    cls = getattr(importlib.import_module(TASKS[name][0]), CLASSICS[name])
    runs = []
    for backend in ("numpy", "torch"):
        env = cls(N, backend=backend, max_episode_steps=20)
        env.reset(seed=5)
        rng = np.random.default_rng(0)
        high = env.single_action_space.high
        run = []
        for _ in range(45):
            out = env.step(rng.uniform(-high, high, (N, len(high))).astype(np.float32))[:4]
            run.append([x.numpy() if isinstance(x, torch.Tensor) else x for x in out])
        runs.append(run)
        env.close()
    ends = 0
    for (o, r, te, tr), (o_t, r_t, te_t, tr_t) in zip(*runs):
        np.testing.assert_allclose(o_t, o, atol=1e-6)  # float32 rounding of the task's arithmetic
        np.testing.assert_allclose(r_t, r, rtol=1e-6, atol=2e-6)
        np.testing.assert_array_equal(te_t, te)
        np.testing.assert_array_equal(tr_t, tr)
        ends += int((te | tr).sum())
    assert ends >= N  # every task ended episodes here (Reacher: its 20-step limit)
