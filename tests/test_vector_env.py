"""The native batched VectorEnv contract (abd_gym.vector.vector_env), on CartPole-v0 and Pendulum-v0.

Few worlds and short rollouts: every scene here shares its compiled kernels with test_envs.py.
"""
import math
import subprocess
import sys
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode

import abd_gym  # noqa: F401 -- registers the ids
from abd_gym import WorldStatus
from abd_gym.vector.registration import TASKS, env_ids
from abd_gym.vector.vector_env import ABDVectorEnv
from abd_gym.envs.cartpole import CartPoleVectorEnv
from abd_gym.envs.pendulum import PendulumVectorEnv

N = 4


def make(mode=AutoresetMode.NEXT_STEP, cls=CartPoleVectorEnv, **kw):
    return cls(N, autoreset_mode=mode, max_episode_steps=kw.pop("max_episode_steps", 500), **kw)


@pytest.fixture(scope="module")
def envs():
    """One CartPole vector env per autoreset mode (each test resets the one it uses)."""
    out = {mode: make(mode) for mode in AutoresetMode}
    yield out
    for e in out.values():
        e.close()


def rollout(env, actions, seed):
    obs, _ = env.reset(seed=seed)
    out = [obs.copy()]
    for a in actions:
        obs, r, te, tr, _ = env.step(a)
        out.append(np.concatenate([obs, r[:, None], te[:, None], tr[:, None]], axis=1))
    return out


def push(value=1.0):
    return np.full((N, 1), value, dtype=np.float32)


# ----------------------------------------------------------------------------- API surface
def test_spaces_and_metadata(envs):
    env = envs[AutoresetMode.NEXT_STEP]
    assert isinstance(env, gym.vector.VectorEnv) and isinstance(env, ABDVectorEnv)
    assert env.num_envs == N
    assert env.single_observation_space.shape == (4,) and env.single_observation_space.dtype == np.float32
    assert env.observation_space.shape == (N, 4) and env.observation_space.dtype == np.float32
    assert env.single_action_space.shape == (1,) and env.action_space.shape == (N, 1)
    np.testing.assert_array_equal(env.single_action_space.low, -1.0)
    np.testing.assert_array_equal(env.single_action_space.high, 1.0)
    assert np.all(np.isfinite(env.single_observation_space.high))
    for mode, e in envs.items():
        assert e.metadata["autoreset_mode"] is mode
    assert env.metadata["render_modes"] == ["rgb_array"] and env.metadata["render_fps"] == 50
    with pytest.raises(RuntimeError):
        make().step(push())  # step before reset


def test_reset_and_step_match_the_spaces(envs):
    env = envs[AutoresetMode.NEXT_STEP]
    obs, info = env.reset(seed=3)
    assert isinstance(info, dict)
    assert obs.shape == (N, 4) and obs.dtype == np.float32 and env.observation_space.contains(obs)
    env.action_space.seed(0)
    for _ in range(40):
        obs, r, te, tr, info = env.step(env.action_space.sample())
        assert obs.dtype == np.float32 and env.observation_space.contains(obs)
        assert r.shape == (N,) and r.dtype == np.float32
        assert te.shape == (N,) and te.dtype == np.bool_ and tr.shape == (N,) and tr.dtype == np.bool_
        assert isinstance(info, dict)


# ----------------------------------------------------------------------------- seeding
def test_same_seed_same_trajectories_autoresets_included(envs):
    env = envs[AutoresetMode.NEXT_STEP]
    rng = np.random.default_rng(1)
    actions = rng.uniform(-1, 1, size=(60, N, 1)).astype(np.float32)  # ~60 steps: several autoresets
    a, b = rollout(env, actions, seed=11), rollout(env, actions, seed=11)
    assert sum(int(x[:, 5].sum()) for x in a[1:]) >= N  # episodes did end and restart
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    c = rollout(env, actions, seed=12)
    assert not np.array_equal(a[0], c[0])
    other = make(AutoresetMode.NEXT_STEP)  # a fresh env: the same seed reproduces the trajectories too
    for x, y in zip(a, rollout(other, actions, seed=11)):
        np.testing.assert_array_equal(x, y)


# ----------------------------------------------------------------------------- autoreset modes
def first_done(env, action=1.0, limit=100):
    for t in range(limit):
        obs, r, te, tr, info = env.step(push(action))
        if (te | tr).any():
            return t, obs, r, te, tr, info
    raise AssertionError("no episode ended")


def test_next_step_autoreset(envs):
    env = envs[AutoresetMode.NEXT_STEP]
    env.reset(seed=0)
    _, obs, r, te, tr, info = first_done(env)
    done = te | tr
    assert np.all(r == 1.0) and "final_obs" not in info
    assert np.all((np.abs(obs[done, 2]) > 0.2) | (np.abs(obs[done, 0]) > 2.4))  # the terminal observation
    obs2, r2, te2, tr2, _ = env.step(push())
    # the finished worlds were reset (their action ignored): reward 0, flags False, a fresh state
    np.testing.assert_array_equal(r2[done], 0.0)
    assert not te2[done].any() and not tr2[done].any()
    assert np.all(np.abs(obs2[done]) <= 0.05 + 1e-5)
    assert np.all(r2[~done] == 1.0)
    np.testing.assert_array_equal(env.episodes.elapsed[done], 0)


def test_same_step_autoreset(envs):
    env = envs[AutoresetMode.SAME_STEP]
    env.reset(seed=0)
    _, obs, r, te, tr, info = first_done(env)
    done = te | tr
    assert np.all(r == 1.0)  # a real transition, not a reset step
    np.testing.assert_array_equal(info["_final_obs"], done)
    np.testing.assert_array_equal(info["_final_info"], done)
    final = info["final_obs"]
    assert final.shape == obs.shape and final.dtype == np.float32
    assert np.all((np.abs(final[done, 2]) > 0.2) | (np.abs(final[done, 0]) > 2.4))  # last obs of the episode
    assert np.all(np.abs(obs[done]) <= 0.05 + 1e-5)  # first obs of the next one
    np.testing.assert_array_equal(final[~done], obs[~done])
    np.testing.assert_array_equal(env.episodes.elapsed[done], 0)
    _, r2, te2, _, _ = env.step(push(0.0))
    assert np.all(r2 == 1.0) and not te2[done].any()


def test_same_step_final_info_layout():
    from abd_gym.envs.reacher import ReacherVectorEnv

    env = ReacherVectorEnv(N, autoreset_mode=AutoresetMode.SAME_STEP, max_episode_steps=3)
    env.reset(seed=0)
    for t in range(3):
        obs, r, te, tr, info = env.step(np.zeros((N, 2)))
        assert tr.all() == (t == 2)
        if t < 2:
            assert info["_distance"].all() and "final_info" not in info
            np.testing.assert_allclose(info["distance"], np.hypot(obs[:, 8], obs[:, 9]), atol=1e-6)
    final, final_info = info["final_obs"], info["final_info"]
    assert info["_final_info"].all() and final_info["_distance"].all() and not info["_distance"].any()
    np.testing.assert_allclose(final_info["distance"], np.hypot(final[:, 8], final[:, 9]), atol=1e-6)
    np.testing.assert_array_equal(env.episodes.elapsed, 0)
    assert not np.allclose(obs[:, 4:6], final[:, 4:6])  # new targets for the new episodes


def test_disabled_autoreset_and_reset_mask(envs):
    env = envs[AutoresetMode.DISABLED]
    env.reset(seed=0)
    _, obs, r, te, tr, info = first_done(env)
    done = te | tr
    assert "final_obs" not in info
    obs2, r2, te2, _, _ = env.step(push())  # nothing resets by itself: the pole keeps falling
    assert te2[done].all() and np.all(np.abs(obs2[done, 2]) >= np.abs(obs[done, 2]))
    q_before = env.sim.body_q()
    obs3, _ = env.reset(options={"reset_mask": done})
    np.testing.assert_array_equal(obs3[~done], obs2[~done])
    np.testing.assert_array_equal(env.sim.body_q()[~done], q_before[~done])
    assert np.all(np.abs(obs3[done]) <= 0.05 + 1e-5)
    _, r4, te4, _, _ = env.step(push(0.0))
    assert not te4[done].any()


@pytest.mark.parametrize("mask", [np.ones(N, dtype=int), np.ones(N + 1, dtype=bool), np.ones((N, 1), dtype=bool)])
def test_reset_mask_is_validated(envs, mask):
    env = envs[AutoresetMode.DISABLED]
    env.reset(seed=0)
    with pytest.raises(ValueError, match="reset_mask"):
        env.reset(options={"reset_mask": mask})


def test_unknown_reset_option_raises(envs):
    with pytest.raises(ValueError, match="unknown reset options"):
        envs[AutoresetMode.DISABLED].reset(options={"lowww": 0.1})


def test_per_world_reset_leaves_other_worlds_untouched():
    """Worlds outside the mask continue exactly as in an env where nothing was reset."""
    a, b = make(AutoresetMode.DISABLED, PendulumVectorEnv), make(AutoresetMode.DISABLED, PendulumVectorEnv)
    actions = np.random.default_rng(2).uniform(-1, 1, size=(20, N, 1)).astype(np.float32)
    a.reset(seed=5)
    b.reset(seed=5)
    mask = np.array([False, True, False, True])
    for t in range(20):
        if t == 8:
            q_before, steps_before = b.sim.body_q(), b.episodes.elapsed.copy()
            b.reset(options={"reset_mask": mask})
            np.testing.assert_array_equal(b.sim.body_q()[~mask], q_before[~mask])
            np.testing.assert_array_equal(b.episodes.elapsed[~mask], steps_before[~mask])
            np.testing.assert_array_equal(b.episodes.elapsed[mask], 0)
            assert not np.allclose(b.sim.body_q()[mask], q_before[mask])
        oa, ra, *_ = a.step(actions[t])
        ob, rb, *_ = b.step(actions[t])
        np.testing.assert_array_equal(ob[~mask], oa[~mask])
        np.testing.assert_array_equal(rb[~mask], ra[~mask])
    assert not np.allclose(ob[mask], oa[mask])


@pytest.mark.parametrize("backend", ["numpy", "torch"])
def test_a_failed_world_is_reported_and_autoreset(backend):
    """A world whose state goes non-finite: terminated with zero observation and reward, flagged in
    info["sim_failed"] with its cause in info["sim_status"] (NONFINITE; False and OK for the others,
    which step on as in an untouched env), and reset by
    the NEXT_STEP autoreset."""
    if backend == "torch":
        pytest.importorskip("torch")
    env = make(AutoresetMode.NEXT_STEP, PendulumVectorEnv, backend=backend)
    ref = make(AutoresetMode.NEXT_STEP, PendulumVectorEnv)
    env.reset(seed=4)
    ref.reset(seed=4)
    a = np.full((N, 1), 0.3, dtype=np.float32)
    for _ in range(3):
        env.step(a)
        ref.step(a)
    q = env.sim.state.q.numpy()
    q[2, 1, 0] = np.nan
    env.sim.state.q.assign(q)
    obs, r, te, tr, info = (np.asarray(x.cpu()) if hasattr(x, "cpu") else x for x in env.step(a))
    robs, rr, *_ = ref.step(a)
    failed = np.asarray(info["sim_failed"].cpu() if hasattr(info["sim_failed"], "cpu") else info["sim_failed"])
    assert failed.tolist() == [False, False, True, False]
    status = np.asarray(info["sim_status"].cpu() if hasattr(info["sim_status"], "cpu") else info["sim_status"])
    assert status.tolist() == [WorldStatus.OK, WorldStatus.OK, WorldStatus.NONFINITE, WorldStatus.OK]
    assert te[2] and not te[[0, 1, 3]].any()
    assert not obs[2].any() and r[2] == 0.0
    np.testing.assert_allclose(obs[[0, 1, 3]], robs[[0, 1, 3]], atol=1e-6)
    obs, r, te, tr, info = env.step(a)  # the autoreset brings world 2 back
    assert env.sim.failed_worlds().size == 0
    assert np.isfinite(np.asarray(obs.cpu() if hasattr(obs, "cpu") else obs)).all()
    assert not bool(te[2])


def test_time_limit_truncates_inside_the_vector_env():
    env = make(AutoresetMode.NEXT_STEP, PendulumVectorEnv, max_episode_steps=5)
    env.reset(seed=0)
    for t in range(1, 6):
        _, r, te, tr, _ = env.step(np.zeros((N, 1)))
        assert not te.any()
        assert tr.all() == (t == 5) and tr.any() == (t == 5)
    _, r, te, tr, _ = env.step(np.zeros((N, 1)))  # the autoreset step
    assert not tr.any() and np.all(r == 0.0)
    _, r, te, tr, _ = env.step(np.zeros((N, 1)))
    assert not tr.any() and np.all(r < 0.0)


# ----------------------------------------------------------------------------- bad actions
def test_nan_actions_raise_and_change_nothing(envs):
    env, ref = envs[AutoresetMode.DISABLED], make(AutoresetMode.DISABLED)
    env.reset(seed=4)
    ref.reset(seed=4)
    for _ in range(3):
        env.step(push(0.3))
        ref.step(push(0.3))
    q = env.sim.body_q()
    bad = push(0.3)
    bad[2, 0] = np.nan
    with pytest.raises(ValueError, match=r"NaN in worlds \[2\]"):
        env.step(bad)
    np.testing.assert_array_equal(env.sim.body_q(), q)
    np.testing.assert_array_equal(env.sim.body_q(), ref.sim.body_q())
    o1, *_ = env.step(push(-0.2))
    o2, *_ = ref.step(push(-0.2))
    np.testing.assert_array_equal(o1, o2)


def test_out_of_range_actions_are_clipped(envs):
    env, ref = envs[AutoresetMode.DISABLED], make(AutoresetMode.DISABLED)
    big = np.array([[50.0], [-7.0], [np.inf], [-np.inf]], dtype=np.float32)
    env.reset(seed=9)
    ref.reset(seed=9)
    for _ in range(3):
        o1, *_ = env.step(big)
        o2, *_ = ref.step(np.clip(big, -1.0, 1.0))
        np.testing.assert_array_equal(o1, o2)
        np.testing.assert_array_equal(env.sim.state.control.numpy()[:, 0], [10.0, -10.0, 10.0, -10.0])


def test_action_shape_is_validated(envs):
    env = envs[AutoresetMode.DISABLED]
    env.reset(seed=0)
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros((N, 2)))
    obs, *_ = env.step(np.zeros(N))  # (N,) is accepted for a 1-D action
    assert obs.shape == (N, 4)


# ----------------------------------------------------------------------------- torch backend
def _cuda_or_skip(device):
    import warp as wp

    if device.startswith("cuda") and not wp.is_cuda_available():
        pytest.skip("no CUDA device")


@pytest.mark.parametrize("device", ["cpu", "cuda:0"])
def test_fixed_outputs_are_written_in_place(device):
    """fixed_outputs: every later NEXT_STEP step writes its outputs into the same tensors and hands
    them back, with the values of an env that returns fresh ones (autoresets included); a NumPy or
    SAME_STEP env has none."""
    torch = pytest.importorskip("torch")
    _cuda_or_skip(device)
    env = make(backend="torch", device=device)
    ref = make(backend="torch", device=device)
    env.reset(seed=8)
    ref.reset(seed=8)
    fixed = env.fixed_outputs()
    ptrs = [x.data_ptr() for x in fixed]
    actions = torch.as_tensor(np.random.default_rng(1).uniform(-1, 1, size=(60, N, 1)), dtype=torch.float32,
                              device=fixed[0].device)  # fmt: skip
    ended = False
    for a in actions:
        out = env.step(a)[:4]
        expected = ref.step(a)[:4]
        assert [x.data_ptr() for x in out] == ptrs
        for x, fx, y in zip(out, fixed, expected):
            assert torch.equal(x, fx) and torch.equal(x, y)
        ended |= bool(out[2].any())
    assert ended
    assert make().fixed_outputs() is None
    assert make(AutoresetMode.SAME_STEP, backend="torch", device=device).fixed_outputs() is None


@pytest.mark.parametrize("device", ["cpu", "cuda:0"])
@pytest.mark.parametrize("mode", [AutoresetMode.SAME_STEP, AutoresetMode.NEXT_STEP])
def test_torch_backend_matches_numpy_and_stays_on_device(mode, device):
    """The torch backend against the numpy one on the same device and seed, autoresets included
    (on a GPU, NEXT_STEP's done mask travels by an asynchronous copy read one step later)."""
    torch = pytest.importorskip("torch")
    import warp as wp

    _cuda_or_skip(device)
    tenv = make(mode, backend="torch", device=device)
    nenv = make(mode, device=device)
    to, _ = tenv.reset(seed=6)
    no, _ = nenv.reset(seed=6)
    assert isinstance(to, torch.Tensor) and to.dtype == torch.float32
    assert to.device == torch.device(wp.device_to_torch(tenv.device))
    np.testing.assert_allclose(to.cpu().numpy(), no, atol=1e-6)
    # observations come from zero-copy views of the simulator state
    assert tenv.coords().data_ptr() == wp.to_torch(tenv.sim.state.coord).data_ptr()
    actions = np.random.default_rng(3).uniform(-1, 1, size=(40, N, 1)).astype(np.float32)
    ended = False
    for a in actions:
        to, tr_, tt, ttr, tinfo = tenv.step(torch.as_tensor(a, device=to.device))
        no, nr, nt, ntr, ninfo = nenv.step(a)
        assert isinstance(tr_, torch.Tensor) and tr_.dtype == torch.float32 and tt.dtype == torch.bool
        assert tr_.device == to.device and tt.device == to.device
        np.testing.assert_allclose(to.cpu().numpy(), no, atol=1e-5)
        np.testing.assert_allclose(tr_.cpu().numpy(), nr, atol=1e-5)
        np.testing.assert_array_equal(tt.cpu().numpy(), nt)
        np.testing.assert_array_equal(tinfo["sim_failed"].cpu().numpy(), ninfo["sim_failed"])
        ended |= bool(nt.any())
        if "final_obs" in tinfo:
            assert isinstance(tinfo["final_obs"], torch.Tensor)
            np.testing.assert_allclose(tinfo["final_obs"].cpu().numpy(), ninfo["final_obs"], atol=1e-5)
    assert ended
    bad = torch.zeros(N, 1, device=to.device)
    bad[0, 0] = float("nan")
    if tenv.device_step.check_on_device:  # the GPU's step graph: refused on the device, raised by the next call
        tenv.step(bad)
        bad = torch.zeros_like(bad)
    with pytest.raises(ValueError, match=r"NaN in worlds \[0\]"):
        tenv.step(bad)
    tenv.close()
    nenv.close()


class _FixedStartCartPole(CartPoleVectorEnv):
    """Every episode starts from the same state (pole at 0.15 rad, falling): the host and device
    autoreset paths then give the same stream, whatever generator each draws from."""

    def initial_state(self, n, rng, options):
        return np.tile([0.0, 0.15], (n, 1)), np.tile([0.0, 0.5], (n, 1))


@pytest.mark.parametrize("backend", ["numpy", "torch", "torch-checked"])
def test_device_autoreset_matches_the_host_reset(backend):
    """NEXT_STEP autoresets on the device (autoreset.py: next episodes drawn ahead, applied by the
    device mask of last step's ended worlds) against the same env resetting on the host: same
    observations, rewards, flags, info masks and clocks through terminations and truncations.
    torch-checked: with the GPU graph's checks and conditional launches (run directly on the CPU)."""
    if backend != "numpy":
        pytest.importorskip("torch")
    dev, host = (_FixedStartCartPole(N, max_episode_steps=9, backend=backend.split("-")[0], device="cpu")
                 for _ in range(2))  # fmt: skip
    host.next_episodes = None  # the host path: _reset_worlds in the step
    assert dev.next_episodes is not None and not dev.device_step.use_graph  # on the CPU: the same launches, no graph
    dev.device_step.check_on_device = backend == "torch-checked"
    for env in (dev, host):
        env.reset(seed=2)
    actions = np.random.default_rng(4).uniform(-1, 1, size=(40, N, 1)).astype(np.float32)
    ends = truncs = 0
    for a in actions:
        out_d, out_h = dev.step(a), host.step(a)
        for x, y in zip(out_d[:4], out_h[:4]):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
        assert out_d[4].keys() == out_h[4].keys()
        for k in out_d[4]:
            np.testing.assert_array_equal(np.asarray(out_d[4][k]), np.asarray(out_h[4][k]))
        np.testing.assert_array_equal(dev.sim.state.time, host.sim.state.time)
        ends += int(np.asarray(out_h[2]).sum())
        truncs += int(np.asarray(out_h[3]).sum())
    assert ends > 0 and truncs > 0


@pytest.mark.parametrize("backend", ["numpy", "torch", "torch-checked"])
def test_device_autoreset_draws_the_task_state(backend):
    """A task with per-episode task values (TwoLinkReacher-v0's target, ``task_state``) autoresets on the
    device: the queues hold each next episode's target with its initial state, the worlds that
    ended take both in the next step (the Torch backend by the take kernel, NumPy's by the host
    copy of the rows: the same episodes from the same seed), and the env's clock, observations and
    flags follow as for a task without task values.  A task with a ``reset_task`` of its own keeps
    its resets on the host."""
    from abd_gym.envs.reacher import ReacherVectorEnv

    if backend != "numpy":
        pytest.importorskip("torch")
    env, ref = (ReacherVectorEnv(N, max_episode_steps=4, backend=b) for b in (backend.split("-")[0], "numpy"))
    env.device_step.check_on_device = backend == "torch-checked"
    assert env.next_episodes is not None and env.next_episodes.task_width == 2
    env.reset(seed=7)
    ref.reset(seed=7)
    rng = np.random.default_rng(1)
    targets = [np.asarray(ref.target).copy()]
    for t in range(13):
        a = rng.uniform(-1, 1, size=(N, 2)).astype(np.float32)
        out, want = env.step(a), ref.step(a)
        for x, y in zip(out[:4], want[:4]):
            np.testing.assert_allclose(np.asarray(x.cpu() if hasattr(x, "cpu") else x), y, atol=1e-6)
        target = np.asarray(env.target.cpu() if hasattr(env.target, "cpu") else env.target)
        np.testing.assert_array_equal(target, ref.target)
        np.testing.assert_allclose(want[0][:, 4:6], ref.target, atol=1e-7)  # observed as it is held
        if t % 5 == 4:  # the step after a truncation (every 4 steps, then 1 autoreset step): new targets
            assert not np.any(np.all(target == targets[-1], axis=1))
            r = np.hypot(target[:, 0], target[:, 1])
            assert np.all((r >= 0.03 - 1e-6) & (r <= 0.2 + 1e-6))
            targets.append(target.copy())
        else:
            np.testing.assert_array_equal(target, targets[-1])
    assert len(targets) == 3
    env.close()
    ref.close()

    class OwnReset(ReacherVectorEnv):
        def reset_task(self, idx, rng, options):
            self.put(self.target, idx, np.full((len(idx), 2), 0.1))

    own = OwnReset(N, max_episode_steps=4)
    assert own.next_episodes is None  # resets on the host
    own.reset(seed=0)
    np.testing.assert_array_equal(own.target, np.float32(0.1))
    own.close()

    class BadDraw(ReacherVectorEnv):
        def draw_task(self, n, rng, options):
            return {"goal": np.zeros((n, 2))}

    with pytest.raises(ValueError, match=r"task_state values \['target'\], got \['goal'\]"):
        BadDraw(N).reset(seed=0)

    class BadWidth(ReacherVectorEnv):
        task_state = (("target", 0),)

    with pytest.raises(ValueError, match=r"positive int width\), got \('target', 0\)"):
        BadWidth(N)


def test_autoreset_launches_wait_for_the_go_flag():
    """NextEpisodes.apply(go=): with go[0] = 0 (a batch the device refused, in the GPU step graph
    where the autoreset runs beside the physics, with no conditional node) no world takes a row or
    restarts and no clock ticks; with go[0] = 1 the pending worlds do, the others only tick."""
    import warp as wp

    pytest.importorskip("torch")
    env = make(backend="torch", device="cpu")
    env.reset(seed=2)
    for _ in range(3):
        env.step(np.zeros((N, 1), np.float32))
    nxt, sim, clock = env.next_episodes, env.sim, env.device_step.arrays["elapsed"]
    nxt.set_pending(np.array([False, True, False, True]))

    def snap():
        return [np.array(x) for x in (sim.joint_coordinates(), sim.joint_velocities(), clock.numpy(), nxt.taken.numpy())]

    before = snap()
    nxt.apply(clock, env.device_step.arrays["task"], go=wp.zeros(1, dtype=wp.int32, device="cpu"))
    for x, y in zip(snap(), before):
        np.testing.assert_array_equal(x, y)
    nxt.apply(clock, env.device_step.arrays["task"], go=wp.ones(1, dtype=wp.int32, device="cpu"))
    x, v, c, taken = snap()
    np.testing.assert_array_equal(taken - before[3], [0, 1, 0, 1])
    np.testing.assert_array_equal(c, np.where([0, 1, 0, 1], 0, before[2] + 1))
    np.testing.assert_array_equal(x[[0, 2]], before[0][[0, 2]])
    rows = nxt.queue.numpy()[N * (before[3][[1, 3]] % nxt.depth) + [1, 3]]
    np.testing.assert_allclose(x[[1, 3]], rows[:, 0, : x.shape[1]], atol=1e-6)
    np.testing.assert_allclose(v[[1, 3]], rows[:, 1, : v.shape[1]], atol=1e-6)
    env.close()


def _snapshot(env):
    sim = env.unwrapped.sim
    return [np.array(x) for x in (sim.body_q(), sim.joint_velocities(), sim.joint_coordinates(), sim.state.time,
                                  env.episodes.elapsed.cpu().numpy(), env.next_episodes.pending.numpy(),
                                  env.next_episodes.taken.numpy(), env.next_episodes.bookmark())]  # fmt: skip


@pytest.mark.parametrize("device", ["cpu", "cuda:0"])
def test_nan_actions_checked_on_the_device_are_taken_back(device):
    """The check on the device (the GPU step graph's; forced here on the CPU): a batch with NaN steps
    no world, the next call raises naming the worlds and steps nothing either, and afterwards the
    env goes on as one that never saw the batch (autoresets, queues and clocks included); a reset
    after such a batch raises once, then resets."""
    torch = pytest.importorskip("torch")
    _cuda_or_skip(device)
    env, ref = (make(max_episode_steps=9, backend="torch", device=device) for _ in range(2))
    if device == "cpu":
        env.device_step.check_on_device = True  # ref keeps the host check: checked on the device, the same stream
    assert env.device_step.check_on_device
    actions = torch.as_tensor(np.random.default_rng(5).uniform(-1, 1, size=(30, N, 1)).astype(np.float32),
                              device=env.arrays.torch_device)  # fmt: skip
    env.reset(seed=3)
    ref.reset(seed=3)
    for a in actions[:9]:  # the 9th step truncates every world: the next one resets them all
        env.step(a)
        ref.step(a)
    before = _snapshot(env)
    bad = actions[9].clone()
    bad[2, 0] = float("nan")
    env.step(bad)
    after = _snapshot(env)
    for k in (0, 1, 2, 4, 5, 6):  # the device's state (the host's clocks and counts wait for the verdict)
        np.testing.assert_array_equal(after[k], before[k])
    with pytest.raises(ValueError, match=r"NaN in worlds \[2\]; no world was stepped"):
        env.step(actions[9])
    for x, y in zip(_snapshot(env), before):
        np.testing.assert_array_equal(x, y)
    for a in actions[9:]:
        out, want = env.step(a), ref.step(a)
        for x, y in zip(out[:4], want[:4]):
            np.testing.assert_array_equal(x.cpu().numpy(), y.cpu().numpy())
        for k in want[4]:
            np.testing.assert_array_equal(np.asarray(out[4][k].cpu() if torch.is_tensor(out[4][k]) else out[4][k]),
                                          np.asarray(want[4][k].cpu() if torch.is_tensor(want[4][k]) else want[4][k]))
        np.testing.assert_array_equal(env.sim.state.time, ref.sim.state.time)
    env.step(bad)
    with pytest.raises(ValueError, match=r"NaN in worlds \[2\]"):
        env.reset(seed=1)
    o1, _ = env.reset(seed=1)
    o2, _ = ref.reset(seed=1)
    np.testing.assert_array_equal(o1.cpu().numpy(), o2.cpu().numpy())
    env.close()
    ref.close()


def test_mailed_env_kernels_match_plain_ones():
    """The step graph's mailed kernels (env_kernels, run here on the CPU with host pointers): the
    check reads the caller's batch by the pointer in its mail slot (left unchanged), clips it
    into the graph's buffer and copies the slot to device memory, and the finish writes the
    outputs packed into the buffer mailed in its slot and the rows done and bad into its slot of
    the host flags: the same values the plain kernels write to their own arrays."""
    import warp as wp

    from abd_gym.vector import kernels as env_kernels

    if not wp.is_cpu_available():
        pytest.skip("device 'cpu' is not available: Warp has no CPU compiler here")
    n, d, na, slot = 5, 3, 2, 1
    rng = np.random.default_rng(0)
    user = rng.uniform(-2, 2, size=(n, na)).astype(np.float32)
    user[3, 1] = np.nan
    kept = user.copy()
    mail = wp.zeros((2, 2), dtype=wp.uint64, device="cpu")
    effort = wp.array([3.0, 0.5], dtype=wp.float32, device="cpu")

    def check(mailed):
        a = wp.zeros((n, na), dtype=wp.float32, device="cpu") if mailed else wp.array(user, device="cpu")
        bad, go = wp.zeros(n, dtype=wp.bool, device="cpu"), wp.ones(1, dtype=wp.int32, device="cpu")
        controls = wp.zeros((n, na), dtype=wp.float32, device="cpu")
        if mailed:
            mail.numpy()[slot, 0] = user.ctypes.data
        wp.launch(env_kernels.check_actions(wp.float32, True, mailed), dim=n,
                  inputs=[a, effort, 1.0, bad, go, controls, mail if mailed else None, slot,
                          copy if mailed else None], device="cpu")  # fmt: skip
        return [x.numpy().copy() for x in (a, bad, go, controls)]

    copy = wp.zeros((2, 2), dtype=wp.uint64, device="cpu")
    mail.numpy()[slot, 1] = 12345
    for x, y in zip(check(True), check(False)):
        np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(user, kept)
    np.testing.assert_array_equal(copy.numpy()[slot], mail.numpy()[slot])  # the mailbox copied for finish_step
    assert not copy.numpy()[1 - slot].any()

    obs = rng.normal(size=(n, d)).astype(np.float32)
    obs[2, 0] = np.inf
    ins = dict(obs=obs, reward=rng.normal(size=n).astype(np.float32), term=np.array([1, 0, 0, 1, 0], bool),
               status=np.array([0, 0, 0, 0, 1], np.int32), go=np.ones(1, np.int32),
               pending=np.array([1, 0, 0, 0, 0], np.int32), elapsed=np.array([1, 9, 3, 9, 2], np.int64))
    out = np.zeros(4 * n * (d + 2) + 3 * n, dtype=np.uint8)

    def finish(mailed):
        packed = np.concatenate([ins["obs"], ins["reward"][:, None], ins["term"][:, None].astype(np.float32)], 1)
        arrays = {"outcome": wp.array(packed, device="cpu")}
        arrays |= {k: wp.array(v, device="cpu") for k, v in ins.items() if k not in ("obs", "reward", "term")}
        o, r = wp.zeros((n, d), dtype=wp.float32, device="cpu"), wp.zeros(n, dtype=wp.float32, device="cpu")
        status = wp.full(n, -1, dtype=wp.int32, device="cpu")
        flags = wp.array(np.eye(5, n, dtype=bool), device="cpu")  # row 4 (bad): the check's
        host = wp.zeros((3, 2, n), dtype=wp.bool, device="cpu")
        if mailed:
            mail.numpy()[slot, 1] = out.ctypes.data
        wp.launch(env_kernels.finish_step(mailed), dim=n,
                  inputs=[*arrays.values(), wp.int64(8), o, r, status, flags, mail if mailed else None, slot,
                          host if mailed else None], device="cpu")  # fmt: skip
        if mailed:
            f = out[: 4 * n * (d + 1)].view(np.float32)
            codes = out[4 * n * (d + 1) : 4 * n * (d + 2)].view(np.int32)
            rows = out[4 * n * (d + 2):].view(bool).reshape(3, n)
            assert not host.numpy()[[0, 2]].any()
            return (f[: n * d].reshape(n, d), f[n * d:], codes, rows, host.numpy()[slot],
                    arrays["pending"].numpy())  # fmt: skip
        fl = flags.numpy()
        return o.numpy(), r.numpy(), status.numpy(), fl[:3], fl[3:5], arrays["pending"].numpy()

    mailed, plain = finish(True), finish(False)
    for x, y in zip(mailed, plain):
        np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(plain[2], ins["status"])  # the status copied out
    assert plain[3][2, 2] and plain[3][2, 4] and plain[4][0].any()  # failures seen; some world done


def test_device_autoreset_draws_fresh_episodes():
    """Autoreset episodes come from the task's reset distribution, each world its own draw: the
    reset step's observation is the drawn state itself (its physics step is discarded)."""
    env = make()
    env.reset(seed=5)
    starts = []
    for _ in range(60):
        obs, _, te, tr, info = env.step(push(1.0))
        reset = ~info["_sim_failed"]  # worlds whose info is a reset's
        starts += list(obs[reset])
    starts = np.array(starts)
    assert len(starts) >= 2 * N
    assert np.all(np.abs(starts) <= 0.05 + 1e-6)  # U(-0.05, 0.05) each, to float32 rounding
    assert len(np.unique(starts[:, 2])) == len(starts)
    env.close()


@pytest.mark.parametrize("task", ["CartPole-v0", "Pendulum-v0", "TwoLinkReacher-v0", "FourBar-v0"])
def test_graph_step_matches_launched_step(task):
    """On a GPU with Torch: the env step replayed as one CUDA graph (graph=True, the default there)
    gives the stream of the same step launched op by op (graph=False): the same physics, and the
    task's outcome to float32 rounding (the graph's is compiled by torch.compile where Triton is
    installed, whose sin and cos may differ from Torch's by an ulp).  In the graph the step holds
    the worlds that the autoreset restarts beside it; FourBar-v0 (episodes cut to 25 steps so that
    worlds end and are held): a closed loop of 36 unknowns on the lane-split step."""
    torch = pytest.importorskip("torch")
    _cuda_or_skip("cuda:0")
    kw = dict(num_envs=64, vectorization_mode="vector_entry_point", device="cuda:0", backend="torch")
    if task == "FourBar-v0":
        kw["max_episode_steps"] = 25
    g, plain = gym.make_vec(f"abd_gym/{task}", **kw), gym.make_vec(f"abd_gym/{task}", graph=False, **kw)
    assert g.unwrapped.device_step.use_graph and not plain.unwrapped.device_step.use_graph
    g.reset(seed=8)
    plain.reset(seed=8)
    d = g.unwrapped.action_dim
    actions = torch.rand((80, 64, d), device="cuda:0", generator=torch.Generator("cuda:0").manual_seed(0)) * 2 - 1
    ends = 0
    returned, copies = [], []
    for a in actions:
        mine = a.clone()
        out_g, out_p = g.step(mine), plain.step(a)
        # the graph reads the caller's batch in stream order: a later write to it (here NaN, which
        # the graph would refuse) is not seen by the step it was given to
        mine.fill_(float("nan"))
        for x, y in zip(out_g[:4], out_p[:4]):
            torch.testing.assert_close(x, y, rtol=1e-6, atol=1e-6)
        for key in ("sim_failed", "sim_status"):
            torch.testing.assert_close(out_g[4][key], out_p[4][key])
        ends += int((out_g[2] | out_g[3]).sum())
        returned.append((*out_g[:4], out_g[4]["sim_status"]))
        copies.append([x.clone() for x in returned[-1]])
    assert g.unwrapped.device_step.graph is not None
    for out, kept in zip(returned, copies):  # each step's outputs are the caller's (no later step writes them)
        for x, y in zip(out, kept):
            torch.testing.assert_close(x, y, rtol=0, atol=0)
    assert ends > 0 or task == "Pendulum-v0"
    g.close()
    plain.close()


def test_each_env_compiles_its_own_outcome():
    """Envs of several sizes in one process each keep a compiled outcome: torch.compile keeps its
    versions of a function on its code object, at most recompile_limit of them (8; here 1), after
    which it runs the function uncompiled; each env compiles a copy of its own."""
    torch = pytest.importorskip("torch")
    import logging
    import shutil

    if shutil.which("g++") is None and shutil.which("c++") is None:
        pytest.skip("torch.compile on the CPU needs a C++ compiler")
    if not hasattr(torch._dynamo.config, "recompile_limit"):
        pytest.skip("this Torch names the limit otherwise")
    fallbacks = []

    class Catch(logging.Handler):
        def emit(self, record):
            if "recompile_limit" in record.getMessage():
                fallbacks.append(record.getMessage())

    handler, log = Catch(), logging.getLogger("torch._dynamo")
    log.addHandler(handler)
    try:
        with torch._dynamo.config.patch(recompile_limit=1):
            for n in (4, 8):
                env = gym.make_vec("abd_gym/CartPole-v0", num_envs=n, vectorization_mode="vector_entry_point",
                                   device="cpu", backend="torch", compile_outcome=True)  # fmt: skip
                env.reset(seed=0)
                for _ in range(2):
                    env.step(torch.zeros(n, 1))
                assert hasattr(env.unwrapped.device_step.outcome_fn, "_torchdynamo_orig_callable")  # compiled
                env.close()
    finally:
        log.removeHandler(handler)
    assert not fallbacks


@pytest.mark.parametrize("task", ["CartPole-v0", "Pendulum-v0"])
def test_compiled_outcome_matches_eager(task):
    """compile_outcome=True (torch.compile of the task's observation, reward and termination; the
    default with the step graph on a GPU) gives the eager outcome: here on the CPU's Torch backend
    (Inductor's C++ kernels), to float32 rounding, the flags exactly; needs a C++ compiler."""
    torch = pytest.importorskip("torch")
    import shutil

    if shutil.which("g++") is None and shutil.which("c++") is None:
        pytest.skip("torch.compile on the CPU needs a C++ compiler")
    kw = dict(num_envs=8, vectorization_mode="vector_entry_point", device="cpu", backend="torch")
    envs = [gym.make_vec(f"abd_gym/{task}", compile_outcome=c, **kw) for c in (True, False)]
    assert envs[0].unwrapped.device_step.compile_outcome and not envs[1].unwrapped.device_step.compile_outcome
    for e in envs:
        e.reset(seed=4)
    actions = torch.rand((30, 8, envs[0].unwrapped.action_dim), generator=torch.Generator().manual_seed(1)) * 2 - 1
    ends = 0
    for a in actions:
        (oc, rc, tc, trc, _), (oe, re, te, tre, _) = (e.step(a) for e in envs)
        torch.testing.assert_close(oc, oe, rtol=1e-6, atol=1e-6)
        torch.testing.assert_close(rc, re, rtol=1e-6, atol=1e-6)
        assert torch.equal(tc, te) and torch.equal(trc, tre)
        ends += int(tc.sum())
    assert ends > 0 or task == "Pendulum-v0"
    assert hasattr(envs[0].unwrapped.device_step.outcome_fn, "_torchdynamo_orig_callable")  # the compiled one ran
    assert envs[1].unwrapped.device_step.outcome_fn == envs[1].unwrapped.device_step.task_outcome
    for e in envs:
        e.close()
    with pytest.raises(ValueError, match="compile_outcome=True needs the Torch backend"):
        CartPoleVectorEnv(2, compile_outcome=True)


# ----------------------------------------------------------------------------- registration
def test_every_task_is_registered():
    ids = env_ids()
    assert len(ids) == len(TASKS) == 12
    for env_id in ids:
        spec = gym.spec(env_id)
        assert spec.namespace == "abd_gym" and spec.vector_entry_point is not None and spec.entry_point is not None
        assert spec.max_episode_steps and spec.reward_threshold is not None
    assert gym.spec("abd_gym/CartPole-v0").max_episode_steps == 500
    assert gym.spec("abd_gym/CartPole-v0").reward_threshold == 475.0


def test_make_and_make_vec():
    env = gym.make("abd_gym/CartPole-v0")
    assert env.spec.max_episode_steps == 500 and env.unwrapped.sim.num_worlds == 1
    assert str(env.unwrapped.sim.device) == "cpu"
    obs, _ = env.reset(seed=0)
    obs, r, te, tr, info = env.step(env.action_space.sample())
    assert obs.shape == (4,) and isinstance(r, float) and isinstance(te, bool) and isinstance(tr, bool)
    venv = gym.make_vec("abd_gym/CartPole-v0", num_envs=3, vectorization_mode="vector_entry_point",
                        autoreset_mode=AutoresetMode.SAME_STEP)  # fmt: skip
    assert isinstance(venv.unwrapped, CartPoleVectorEnv) and venv.num_envs == 3
    assert venv.unwrapped.max_episode_steps == 500 and venv.metadata["autoreset_mode"] is AutoresetMode.SAME_STEP
    obs, _ = venv.reset(seed=0)
    assert obs.shape == (3, 4)
    venv.close()
    env.close()


def test_no_two_ids_read_as_versions_of_one_task():
    """Gymnasium reads ids of one namespace and name as versions of one env (and warns on making any
    but the newest): every task has a name of its own."""
    names = [gym.envs.registration.parse_env_id(env_id)[1] for env_id in env_ids()]
    assert len(set(names)) == len(names), names


def test_former_id_makes_the_task_with_one_warning():
    """abd_gym/Reacher-v0, now abd_gym/TwoLinkReacher-v0: still made, single and vector; a fresh
    process making it twice warns once (a FutureWarning naming the new id), without Gymnasium's
    "out of date" warning."""
    from abd_gym.envs.reacher import ReacherEnv, ReacherVectorEnv

    script = "import gymnasium as gym, abd_gym\nfor _ in range(2):\n    gym.make('abd_gym/Reacher-v0')\n"
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True, timeout=600)
    warned = [line for line in out.stderr.splitlines() if "Warning" in line or "WARN" in line]
    assert len(warned) == 1 and warned[0].endswith(
        "FutureWarning: abd_gym/Reacher-v0 is now abd_gym/TwoLinkReacher-v0; the former id goes in the next release"), out.stderr
    assert "out of date" not in out.stderr, out.stderr
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)
        warnings.simplefilter("ignore", DeprecationWarning)  # pytest shows Gymnasium's again
        env = gym.make("abd_gym/Reacher-v0")
        venv = gym.make_vec("abd_gym/Reacher-v0", num_envs=2, vectorization_mode="vector_entry_point")
    assert isinstance(env.unwrapped, ReacherEnv) and isinstance(venv.unwrapped, ReacherVectorEnv)
    assert env.spec.max_episode_steps == gym.spec("abd_gym/TwoLinkReacher-v0").max_episode_steps
    env.close()
    venv.close()


def test_simulator_options_reach_the_simulator():
    """simulator_options passes more Simulator settings through gym.make_vec (here Newton's iteration
    budget, max_iterations 2, with the factor reused, where random forces take ~3.8 iterations a
    step: a solve that has not converged in 2 is retried from a fresh factor for 2 more, which the
    default budget never needs); the task's own settings cannot be overridden, and a bad value is
    the Simulator's error."""
    def retried(**kw):
        venv = gym.make_vec("abd_gym/CartPole-v0", num_envs=8, vectorization_mode="vector_entry_point", **kw)
        venv.reset(seed=0)
        venv.action_space.seed(0)
        sim = venv.unwrapped.sim
        count = 0
        for _ in range(20):
            venv.step(venv.action_space.sample())
            assert sim.newton_iterations().max() <= 2 * sim.solver.settings.max_iterations
            count += int(sim.newton_retried().sum())
        assert sim.solver.settings.max_iterations == kw["simulator_options"].get("max_iterations", 50)
        venv.close()
        return count

    assert retried(simulator_options={"max_iterations": 2, "reuse_factor": True}) > 0 == retried(
        simulator_options={"reuse_factor": True})
    with pytest.raises(ValueError, match="dt"):
        gym.make_vec("abd_gym/CartPole-v0", num_envs=2, vectorization_mode="vector_entry_point",
                     simulator_options={"dt": 0.5})  # fmt: skip
    with pytest.raises(ValueError, match="quadratic_stop"):
        gym.make_vec("abd_gym/CartPole-v0", num_envs=2, vectorization_mode="vector_entry_point",
                     simulator_options={"quadratic_stop": -1.0})  # fmt: skip


def test_single_env_seeding_is_reproducible():
    env = gym.make("abd_gym/Pendulum-v0")
    runs = []
    for _ in range(2):
        obs, _ = env.reset(seed=21)
        traj = [obs]
        for k in range(5):
            traj.append(env.step(np.array([0.5], dtype=np.float32))[0])
        runs.append(np.array(traj))
    np.testing.assert_array_equal(runs[0], runs[1])
    assert not np.array_equal(env.reset(seed=22)[0], runs[0][0])


# ----------------------------------------------------------------------------- parameters, render
def test_randomized_parameters_per_world():
    env = make(AutoresetMode.DISABLED)
    spec = {"mass_scale": (0.5, 2.0), "strength_ratio": (50.0, 200.0), "limit_scale": (0.8, 0.9),
            "limit_strength_scale": {"slider": (2.0, 3.0)}}  # fmt: skip
    env.reset(seed=0, options={"randomize": spec})
    free = [1, 2]  # cart, pole
    scale = env.body_mass[:, free] / env.parameters.nominal_mass[free]
    assert np.all((scale >= 0.5) & (scale <= 2.0)) and np.ptp(scale[:, 0]) > 0.05
    np.testing.assert_array_equal(env.body_mass[:, 0], env.parameters.nominal_mass[0])  # fixed rail untouched
    assert np.all((env.strength_ratio >= 50) & (env.strength_ratio <= 200))
    lo, up, st = env.limits[0].T
    assert np.all((up >= 2.4 * 0.8) & (up <= 2.4 * 0.9)) and np.allclose(lo, -up) and np.all((st >= 2e4) & (st <= 3e4))
    m = env.sim.model  # the simulator holds the same values
    np.testing.assert_allclose(m.mass.numpy()[:, free], env.body_mass[:, free], rtol=1e-6)
    K = env.strength_ratio * (env.body_mass[:, m.body_a.numpy()[:2]] + env.body_mass[:, m.body_b.numpy()[:2]])
    np.testing.assert_allclose(m.K.numpy()[:, :2], K, rtol=1e-5)
    np.testing.assert_allclose(m.limit_params["prismatic"][1].numpy()[:, 0], up, rtol=1e-6)
    # a masked reset draws new parameters for its worlds only (the spec is sticky)
    before = env.body_mass.copy()
    mask = np.array([True, False, False, False])
    env.reset(options={"reset_mask": mask})
    np.testing.assert_array_equal(env.body_mass[1:], before[1:])
    assert not np.array_equal(env.body_mass[0], before[0])
    # randomize=None restores the nominal values
    env.reset(options={"randomize": None})
    np.testing.assert_allclose(m.mass.numpy(), np.broadcast_to(env.parameters.nominal_mass, (N, 3)), rtol=1e-6)
    np.testing.assert_allclose(m.limit_params["prismatic"][1].numpy()[:, 0], 2.4, rtol=1e-6)
    with pytest.raises(ValueError, match="unknown randomize"):
        env.reset(options={"randomize": {"masses": (1, 2)}})


def test_heavier_pole_changes_the_dynamics():
    env = make(AutoresetMode.DISABLED)
    env.reset(seed=1)
    light = [env.step(push(0.5))[0] for _ in range(10)][-1]
    env.reset(seed=1, options={"randomize": {"mass_scale": {"pole0": (3.0, 3.0)}}})
    heavy = [env.step(push(0.5))[0] for _ in range(10)][-1]
    assert np.all(np.abs(heavy[:, 0] - light[:, 0]) > 1e-3)  # the cart accelerates less / differently


def test_vector_render_frames():
    env = make(AutoresetMode.NEXT_STEP, render_mode="rgb_array")
    env.reset(seed=0)
    for _ in range(5):
        env.step(np.array([[1.0], [-1.0], [0.0], [0.5]], dtype=np.float32))
    frames = env.render()
    assert isinstance(frames, tuple) and len(frames) == N
    for f in frames:
        assert f.dtype == np.uint8 and f.shape == (400, 600, 3)
        assert (f != 255).any(axis=2).mean() > 0.005  # something was drawn
    assert not np.array_equal(frames[0], frames[1])
    few = make(AutoresetMode.NEXT_STEP, render_mode="rgb_array", render_worlds=[2])
    few.reset(seed=0)
    assert len(few.render()) == 1
    with pytest.warns(UserWarning, match="render_mode"):
        assert make().render() is None  # no render mode


def test_single_env_render_shows_the_current_state():
    """A single env's frame is the same image until the env steps, and a different one after."""
    env = gym.make("abd_gym/CartPoleSwingUp-v0", render_mode="rgb_array")
    env.reset(seed=0)
    first = env.render()
    assert first.shape == (400, 600, 3) and first.dtype == np.uint8
    np.testing.assert_array_equal(env.render(), first)
    for _ in range(5):
        env.step(np.array([1.0], dtype=np.float32))
    assert not np.array_equal(env.render(), first)
    env.close()


def test_reset_option_angles_are_respected():
    env = make(AutoresetMode.DISABLED)
    obs, _ = env.reset(seed=0, options={"low": 0.1, "high": 0.15})
    assert np.all((obs >= 0.1 - 1e-5) & (obs <= 0.15 + 1e-5))
    assert math.isclose(float(env.sim.joint_coordinates()[0, 1]), float(obs[0, 2]), abs_tol=1e-6)
