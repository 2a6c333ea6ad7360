"""The device-resident PPO rollout learns exactly as SB3's own NumPy rollout does, on a SAME_STEP env,
and on a NEXT_STEP env trains on exactly the transitions SB3's rollout collects (CPU)."""
from __future__ import annotations

from unittest import mock

import numpy as np
import pytest
import torch as th

pytest.importorskip("stable_baselines3")
from stable_baselines3 import PPO  # noqa: E402
from stable_baselines3.common.vec_env import VecMonitor  # noqa: E402

from abd_gym.agents import graphed_update  # noqa: E402

from abd_gym.agents.common import build_model  # noqa: E402
from abd_gym.agents.config import load_config  # noqa: E402
from abd_gym.agents.device_rollout import DevicePPO, TensorRolloutBuffer, rollout_path  # noqa: E402
from abd_gym.agents.graphed_update import GraphedMinibatchStep, GraphedPPO  # noqa: E402
from abd_gym.agents.sb3_vec_env import TensorStep, make_vec_env  # noqa: E402

N_ENVS, N_STEPS, ITERATIONS = 8, 16, 2
CUT_STEPS = 12  # a time limit shorter than a rollout: every world is cut at least once
LONG_STEPS = 1000  # no world reaches it: episodes end only by termination


def _config(episode_steps=CUT_STEPS, **extra):
    overrides = [
        f"n_envs={N_ENVS}",
        f"n_timesteps={N_ENVS * N_STEPS * ITERATIONS}",
        f"hyperparams.n_steps={N_STEPS}",
        "hyperparams.batch_size=32",
        "hyperparams.n_epochs=2",
        f"env_kwargs={{max_episode_steps: {episode_steps}}}",
    ]
    overrides += [f"{k}={v}" for k, v in extra.items()]
    return load_config("cartpole_ppo", overrides)


def _train(cfg, rollout, step=None):
    """A model trained on ``cfg``: ``rollout`` "sb3" is SB3's own PPO (the reference), "graphed"
    :class:`GraphedPPO` (SB3's rollout), "device" :class:`DevicePPO`; ``step``: the update's
    minibatch step (a :class:`GraphedMinibatchStep` class) where it is not the default."""
    # every path steps the same env (Torch backend)
    th.set_num_threads(1)  # the orthogonal initialisation's QR rounds differently with more threads
    env = VecMonitor(make_vec_env(cfg["env_id"], cfg["n_envs"], seed=cfg["seed"], env_kwargs=cfg["env_kwargs"],
                                  backend="torch"))  # fmt: skip
    if rollout == "sb3":
        with mock.patch.object(graphed_update, "GraphedPPO", PPO):
            model = build_model(cfg, env, rollout="sb3")
        assert type(model) is PPO
    else:
        model = build_model(cfg, env, rollout="sb3" if rollout == "graphed" else rollout)
        assert type(model) is (GraphedPPO if rollout == "graphed" else DevicePPO)
    if step is not None:
        model._minibatch_step = step(model, capture=False)
    model.learn(total_timesteps=cfg["n_timesteps"])
    return model


@pytest.fixture(scope="module")
def both_paths():
    cfg = _config()
    return _train(cfg, "sb3"), _train(cfg, "device")


_FIELDS = ("observations", "actions", "rewards", "episode_starts", "values", "log_probs", "advantages", "returns")


_LOGGED = ("train/entropy_loss", "train/policy_gradient_loss", "train/value_loss", "train/clip_fraction",
           "train/approx_kl", "train/loss", "train/explained_variance", "train/n_updates")


def _assert_same(a, b):
    """The same parameters bit for bit and the same logged means (to their float64 summation)."""
    for (name, p), q in zip(a.policy.state_dict().items(), b.policy.state_dict().values()):
        np.testing.assert_array_equal(p.numpy(), q.numpy(), err_msg=name)
    for key in _LOGGED:
        assert b.logger.name_to_value[key] == pytest.approx(a.logger.name_to_value[key], rel=1e-6, abs=1e-9), key


def _assert_close(a, b, start):
    """Parameters that moved from ``start`` the same way to 1e-4 of the move, and logged means to 1e-4."""
    for p, q, p0 in zip(a.policy.parameters(), b.policy.parameters(), start):
        moved = (p.detach() - p0).abs().max()
        assert moved > 0
        assert (p.detach() - q.detach()).abs().max() <= 1e-4 * moved
    for key in _LOGGED:
        assert b.logger.name_to_value[key] == pytest.approx(a.logger.name_to_value[key], rel=1e-4, abs=1e-7), key


def _initial_parameters(cfg):
    model = _train(dict(cfg, n_timesteps=0), "sb3")
    return [p.detach().clone() for p in model.policy.parameters()]


@pytest.mark.parametrize("target_kl", [None, 1e-6])
def test_bit_identical_without_time_limit_cuts(target_kl):
    # the device path's update is SB3's (GraphedPPO._train off a GPU): the same parameters, the
    # same logged means, and with a target KL small enough to stop epochs early, the same early stops
    cfg = _config(LONG_STEPS, **({} if target_kl is None else {"hyperparams.target_kl": target_kl}))
    sb3, dev = _train(cfg, "sb3"), _train(cfg, "device")
    assert len(sb3.ep_info_buffer) > 0  # some episodes terminated (reset inside a rollout)
    a, b = sb3.rollout_buffer, dev.rollout_buffer
    for name in _FIELDS:
        np.testing.assert_array_equal(getattr(a, name).astype(np.float32), getattr(b, name), err_msg=name)
    _assert_same(sb3, dev)
    full = ITERATIONS * cfg["hyperparams"]["n_epochs"]
    assert (dev._n_updates < full) == (target_kl is not None)  # the small target stops epochs early
    # SB3's rollout with GraphedPPO's update off a GPU: SB3's learning bit for bit
    _assert_same(sb3, _train(cfg, "graphed"))


# 48 leaves a padded last minibatch on purpose; SB3 warns that it does
@pytest.mark.filterwarnings("ignore:You have specified a mini-batch size of 48")
@pytest.mark.parametrize("batch_size", [32, 48])
@pytest.mark.parametrize("rollout", ["device", "graphed"])
def test_graphed_update_is_sb3s_to_rounding(batch_size, rollout):
    # the CUDA-graph minibatch step's arithmetic (weighted means, padded last minibatch at 48:
    # 128 = 2 x 48 + 32), run eagerly on the CPU, moves the parameters as SB3's update does, on the
    # device rollout and on SB3's (whose buffer goes to the update's tensors once an update)
    cfg = _config(LONG_STEPS, **{"hyperparams.batch_size": batch_size})
    _assert_close(_train(cfg, "sb3"), _train(cfg, rollout, GraphedMinibatchStep), _initial_parameters(cfg))


def test_update_refuses_a_non_finite_loss():
    dev = _train(_config(LONG_STEPS), "device")
    with th.no_grad():
        next(dev.policy.parameters()).fill_(float("nan"))
    with pytest.raises(FloatingPointError, match="loss is nan"):
        dev.train()


def test_paths_choose_as_documented():
    on_gpu = {**_config(), "device": "cuda:0"}  # the choice reads the name only
    assert rollout_path(on_gpu)[0] == "device"
    assert rollout_path({**_config(normalize="true"), "device": "cuda:0"})[0] == "device"  # VecNormalize on the device
    path, reason = rollout_path(_config())  # auto on the CPU: SB3's NumPy rollout, the faster there
    assert path == "sb3" and "CPU" in reason
    assert rollout_path(_config(rollout="device"))[0] == "device"
    assert rollout_path({**on_gpu, "rollout": "sb3"})[0] == "sb3"
    assert rollout_path(load_config("cartpole_sac"))[0] == "sb3"
    with pytest.raises(ValueError, match="not PPO"):
        rollout_path({**load_config("cartpole_sac"), "rollout": "device"})


def test_same_rollout_buffer_and_policy(both_paths):
    sb3, dev = both_paths
    assert type(dev) is DevicePPO and isinstance(dev.rollout_buffer, TensorRolloutBuffer)
    assert sb3.num_timesteps == dev.num_timesteps == N_ENVS * N_STEPS * ITERATIONS
    a, b = sb3.rollout_buffer, dev.rollout_buffer
    # the last rollout (taken with the policy after one update), flattened world-major by get().
    # SB3 evaluates V(final_obs) one world at a time, the device path for all cut worlds at once:
    # the batched matmul may round the last bit differently, and that bit reaches the update
    np.testing.assert_array_equal(a.episode_starts, b.episode_starts)
    for name in _FIELDS:
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=1e-6, atol=1e-6, err_msg=name)
    for (name, p), q in zip(sb3.policy.state_dict().items(), dev.policy.state_dict().values()):
        np.testing.assert_allclose(p.numpy(), q.numpy(), rtol=1e-5, atol=1e-6, err_msg=name)


def test_same_episode_statistics(both_paths):
    sb3, dev = both_paths
    episodes = [[(round(e["r"], 4), e["l"]) for e in m.ep_info_buffer] for m in (sb3, dev)]
    assert episodes[0] == episodes[1]
    assert len(episodes[0]) >= N_ENVS * ITERATIONS  # every world finished at least one episode per rollout


def test_many_finished_episodes_keep_the_last(both_paths):
    _, dev = both_paths
    saved = dev.ep_info_buffer.copy()
    try:
        returns, lengths = np.arange(250, dtype=np.float32), np.arange(250) + 1
        dev._add_episodes(returns, lengths)  # only the last maxlen are kept, as extending with all would
        assert [(e["r"], e["l"]) for e in dev.ep_info_buffer] == list(zip(range(150, 250), range(151, 251)))
    finally:
        dev.ep_info_buffer = saved


def test_truncated_episode_bootstrapped(both_paths):
    _, dev = both_paths
    # world 0 terminated, world 1 cut by its time limit, world 2 both (terminal: no bootstrap), world 3 runs on
    terminated = th.tensor([True, False, True, False])
    truncated = th.tensor([False, True, True, False])
    done = (terminated | truncated).numpy()
    final_obs = th.randn(4, 4, generator=th.Generator().manual_seed(3))
    rewards = th.ones(4)
    step = TensorStep(final_obs + 1.0, rewards, terminated, truncated, done, final_obs)
    out = dev._bootstrap_timeouts(step, rewards)
    with th.no_grad():
        v = dev.policy.predict_values(final_obs[1:2]).item()
    assert abs(v) > 1e-3  # a bootstrap that can be seen
    assert out[1].item() == pytest.approx(1.0 + dev.gamma * v, rel=1e-6)
    assert out[[0, 2, 3]].tolist() == [1.0, 1.0, 1.0]
    assert rewards.tolist() == [1.0, 1.0, 1.0, 1.0]  # the env's reward tensor is left as it was


def test_rollout_bootstraps_cut_episodes(both_paths):
    _, dev = both_paths
    t = dev.rollout_buffer.tensors  # rewards and episode_starts stay (n_steps, n_envs)
    ended = t["episode_starts"][1:] > 0  # the step before a new episode ended one
    rewards = t["rewards"][:-1]
    assert (rewards[~ended] == 1.0).all()  # CartPole: 1 per step
    assert (rewards[ended] != 1.0).sum() >= N_ENVS // 2  # most worlds were cut at step 12, not terminated


def test_train_takes_and_records_the_device_path(tmp_path, capsys):
    from stable_baselines3 import PPO

    from abd_gym.agents import train as agent_train

    cfg = _config(rollout="device", **{"hyperparams.n_steps": 8, "hyperparams.batch_size": 32, "hyperparams.n_epochs": 1})
    cfg["n_timesteps"], cfg["eval_episodes"] = 2 * N_ENVS * 8, 2
    summary = agent_train.train(cfg, config_name="dev", run_dir=tmp_path / "run", progress_bar=False)
    assert summary["rollout"] == "device" and summary["timesteps"] == 2 * N_ENVS * 8
    assert summary["autoreset_mode"] == "NEXT_STEP"
    assert summary["mean_episode_length"] > 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[1].startswith("rollout: device (") and lines[1].endswith("; autoreset: NEXT_STEP")
    # the saved model is a plain PPO with SB3's own buffer, and trains on in SB3's rollout
    model = PPO.load(tmp_path / "run" / "model.zip", device="cpu")
    assert model.rollout_buffer_class is None or model.rollout_buffer_class.__name__ == "RolloutBuffer"
    env = VecMonitor(make_vec_env(cfg["env_id"], N_ENVS, seed=1, env_kwargs=cfg["env_kwargs"]))
    model.set_env(env)
    model.learn(total_timesteps=N_ENVS * 8, reset_num_timesteps=False)
    assert model.num_timesteps == 3 * N_ENVS * 8


# ---------------------------------------------------------------------------------------------
# the NEXT_STEP env (what training builds for the device path): reset steps masked out

NS_ENVS, NS_STEPS, NS_ROLLOUTS = 4, 9, 3
NS_LIMIT = 9  # worlds 1 and 3 are cut at their 9th step, the last position of the first rollout
NS_START = (0.0, 0.12)  # (x [m], theta [rad]) every episode after the first starts from: 5 steps to fall
_GAIN = th.tensor([0.0, 0.0, -20.0, -2.0])  # pushes the cart away from the lean: the pole falls
_VALUE = th.tensor([0.5, -0.3, 4.0, 0.7])


def _scripted(model):
    """A state-feedback policy and value function (no sampling): both paths act alike in alike states."""

    def forward(obs, deterministic=False):
        obs = obs.float()
        return th.tanh(obs @ _GAIN)[:, None], predict_values(obs), th.zeros(len(obs))

    def predict_values(obs):
        return (obs.float() @ _VALUE)[:, None] + 1.0

    model.policy.forward, model.policy.predict_values = forward, predict_values


def _fixed_restarts(venv):
    """Episodes after the first start from NS_START (the two modes draw restarts from different
    generators); the full reset draws as the task does."""
    from abd_gym.agents.device_rollout import find_adapter

    env = find_adapter(venv).env.unwrapped
    draw, reset = env.initial_state, env.reset
    full = [False]

    def initial_state(n, rng, options):
        if full[0]:
            full[0] = False
            return draw(n, rng, options)
        return np.tile([NS_START], (n, 1)), np.zeros((n, 2))

    def full_reset(*args, **kwargs):
        full[0] = True
        return reset(*args, **kwargs)

    env.initial_state, env.reset = initial_state, full_reset


def _rollouts(model, count):
    """``count`` rollouts of the scripted policy; each buffer's (n_steps, n_envs) tensors, copied."""
    _scripted(model)
    _, callback = model._setup_learn(count * model.n_steps * model.n_envs)
    out = []
    for _ in range(count):
        assert model.collect_rollouts(model.env, callback, model.rollout_buffer, model.n_steps)
        buf = model.rollout_buffer
        if isinstance(buf, TensorRolloutBuffer):
            out.append({k: v.clone() for k, v in buf.tensors.items()})
        else:
            out.append({k: th.as_tensor(getattr(buf, k)) for k in _FIELDS})
    return out


def _gae(rewards, values, dones_after, last_value, gamma, lam):
    """Reference GAE(lambda) of one world's run of transitions (float64)."""
    adv, last = np.zeros(len(rewards)), 0.0
    next_values = np.append(values[1:], last_value)
    for j in reversed(range(len(rewards))):
        nnt = 1.0 - dones_after[j]
        last = rewards[j] + gamma * next_values[j] * nnt - values[j] + gamma * lam * nnt * last
        adv[j] = last
    return adv


@pytest.fixture(scope="module")
def next_and_same_step():
    from abd_gym.agents.common import build_train_env

    cfg = _config(NS_LIMIT, n_envs=NS_ENVS, **{"hyperparams.n_steps": NS_STEPS, "hyperparams.batch_size": 4})
    th.set_num_threads(1)
    nxt = build_model(cfg, env := build_train_env(cfg, rollout="device"), rollout="device")
    _fixed_restarts(env)
    next_rollouts = _rollouts(nxt, NS_ROLLOUTS)
    cfg_same = dict(cfg, hyperparams=dict(cfg["hyperparams"], n_steps=NS_STEPS * NS_ROLLOUTS + 1))
    same_env = VecMonitor(make_vec_env(cfg["env_id"], NS_ENVS, seed=cfg["seed"], env_kwargs=cfg["env_kwargs"],
                                       backend="torch"))  # fmt: skip
    same = build_model(cfg_same, same_env, rollout="sb3")
    _fixed_restarts(same_env)
    (same_rollout,) = _rollouts(same, 1)
    return nxt, next_rollouts, same, same_rollout


def test_next_step_env_for_the_device_path():
    from gymnasium.vector import AutoresetMode

    from abd_gym.agents.common import build_train_env
    from abd_gym.agents.device_rollout import find_adapter

    cfg = _config(n_envs=2)
    assert find_adapter(build_train_env(cfg, rollout="device")).autoreset_mode == AutoresetMode.NEXT_STEP
    assert find_adapter(build_train_env(cfg, rollout="sb3")).autoreset_mode == AutoresetMode.SAME_STEP


def test_valid_transitions_are_same_step_transitions(next_and_same_step):
    nxt, rollouts, same, ref = next_and_same_step
    cat = {k: th.cat([r[k] for r in rollouts]).numpy() for k in rollouts[0]}  # (steps, worlds)
    valid = cat["valid"] > 0
    assert (~valid).any(axis=0).all()  # every world was reset in the rollouts
    assert valid[0].all() and not valid[NS_STEPS, 1:].any()  # worlds 1-3 ended at the first rollout's last step
    cuts = cat["cuts"][NS_STEPS - 1]
    assert cuts[[1, 3]].all() and not cuts[[0, 2]].any()
    assert (cat["dones"] * (1 - cat["cuts"])).sum() > 0  # terminations too
    for w in range(NS_ENVS):
        v = valid[:, w]
        m = int(v.sum())
        for name in ("observations", "actions"):
            np.testing.assert_array_equal(cat[name][v, w], ref[name][:m, w], err_msg=f"{name} world {w}")
        # rewards carry the time-limit bootstrap (NEXT_STEP: from the next position's value)
        np.testing.assert_allclose(cat["rewards"][v, w], ref["rewards"][:m, w], rtol=1e-6, err_msg=f"world {w}")
        dones_after = ref["episode_starts"][1 : m + 1, w].numpy()
        np.testing.assert_array_equal(cat["dones"][v, w], dones_after, err_msg=f"dones world {w}")
        np.testing.assert_array_equal(cat["rewards"][~v, w], 0.0)  # a reset step's reward


def test_valid_advantages_are_gae_of_the_same_step_run(next_and_same_step):
    nxt, rollouts, same, ref = next_and_same_step
    gamma, lam = nxt.gamma, nxt.gae_lambda
    r_ref, v_ref, starts = (ref[k].numpy().astype(np.float64) for k in ("rewards", "values", "episode_starts"))
    offset = np.zeros(NS_ENVS, dtype=int)  # each world's transitions before this rollout
    for r in rollouts:
        valid = r["valid"].numpy() > 0
        for w in range(NS_ENVS):
            m = int(valid[:, w].sum())
            a, b = offset[w], offset[w] + m
            expected = _gae(r_ref[a:b, w], v_ref[a:b, w], starts[a + 1 : b + 1, w], v_ref[b, w], gamma, lam)
            np.testing.assert_allclose(r["advantages"].numpy()[valid[:, w], w], expected, rtol=1e-5, atol=1e-5,
                                       err_msg=f"world {w}")  # fmt: skip
            np.testing.assert_allclose(r["returns"].numpy()[valid[:, w], w], expected + v_ref[a:b, w], rtol=1e-5,
                                       atol=1e-5)  # fmt: skip
            offset[w] = b


@pytest.mark.parametrize("size", [1, 3, 1000])
def test_rollout_tail_is_the_last_finished_episodes(next_and_same_step, size):
    """The rollout step's tail (what ep_info_buffer takes from a rollout): the returns and lengths
    of the last ``size`` finished episodes in row-major order, and their count."""
    steps, t = next_and_same_step[0]._rollout_step, next_and_same_step[0].rollout_buffer.storage
    done = t["dones"].flatten() > 0
    expected = th.stack((t["ep_return"].flatten()[done], t["ep_length"].flatten()[done]))[:, -size:]
    saved = steps.tail_size, steps.tail
    try:
        steps.tail_size, steps.tail = size, th.full((2, size + 1), -1.0)
        steps._tail()
        k = int(steps.tail[0, size])
        assert k == expected.shape[1] > 1 or size == 1
        np.testing.assert_array_equal(steps.tail[:, :k].numpy(), expected.numpy())
    finally:
        steps.tail_size, steps.tail = saved


def test_next_step_episode_statistics(next_and_same_step):
    from collections import Counter

    nxt, rollouts, _, ref = next_and_same_step
    got = [(e["r"], e["l"]) for e in nxt.ep_info_buffer]
    valid = th.cat([r["valid"] for r in rollouts]).numpy() > 0
    lengths = []  # the episodes the SAME_STEP run completed within each world's valid transitions
    for w in range(NS_ENVS):
        ends = np.flatnonzero(ref["episode_starts"][1 : int(valid[:, w].sum()) + 1, w].numpy()) + 1
        lengths += np.diff(ends, prepend=0).tolist()
    assert Counter(got) == Counter((float(n), n) for n in lengths)  # CartPole: 1 per step, no reset step counted
    assert {n for _, n in got} >= {5, NS_LIMIT}  # terminated from NS_START, cut by the limit


@pytest.mark.filterwarnings("ignore:You have specified a mini-batch size")  # the smaller last minibatch is the point
def test_next_step_training_masks_reset_steps():
    from stable_baselines3.common.callbacks import BaseCallback

    from abd_gym.agents.common import build_train_env

    n_envs, n_steps, batch, epochs, iterations = 4, 16, 20, 2, 3
    cfg = _config(8, n_envs=n_envs, **{"hyperparams.n_steps": n_steps, "hyperparams.batch_size": batch,
                                       "hyperparams.n_epochs": epochs})  # fmt: skip
    th.set_num_threads(1)
    model = build_model(cfg, build_train_env(cfg, rollout="device"), rollout="device")
    flags, draws = [], []  # per rollout: (valid, dones) (n_steps, n_envs); minibatch index tensors

    class Record(BaseCallback):
        def _on_step(self):
            return True

        def _on_rollout_end(self):
            t = self.model.rollout_buffer.tensors
            flags.append((t["valid"] > 0, t["dones"] > 0))
            draws.append([])

    buf = model.rollout_buffer
    get_samples = buf._get_samples
    buf._get_samples = lambda idx, env=None: draws[-1].append(idx) or get_samples(idx, env)
    model.learn(total_timesteps=n_envs * n_steps * iterations, callback=Record())
    assert model.num_timesteps == n_envs * n_steps * iterations  # every world at every step, reset steps too

    valid = th.cat([v for v, _ in flags])
    dones = th.cat([d for _, d in flags])
    # exactly the step after an episode's end is masked, across rollout boundaries too
    assert valid[0].all() and th.equal(valid[1:], ~dones[:-1])
    episodes = list(model.ep_info_buffer)
    assert len(episodes) == int(dones.sum()) and int((~valid).sum()) == int(dones[:-1].sum())
    # the valid positions are the episodes' own steps: finished ones plus the ones running on
    assert int(valid.sum()) == sum(e["l"] for e in episodes) + int(model._ep_length.sum())
    assert all(e["r"] == e["l"] for e in episodes) and max(e["l"] for e in episodes) <= 8

    for (v, _), idx in zip(flags, draws):
        allowed = th.nonzero(v.transpose(0, 1).reshape(-1)).flatten()  # world-major, as get() flattens
        m = len(allowed)
        sizes = [batch] * (m // batch) + ([m % batch] if m % batch else [])
        assert [len(i) for i in idx] == sizes * epochs
        for e in range(epochs):
            epoch = th.cat(idx[e * len(sizes) : (e + 1) * len(sizes)])
            assert th.equal(th.sort(epoch).values, allowed)  # each valid position once per epoch, nothing else
    # PPO's explained variance reads the last rollout's values and returns at its valid positions
    assert model.rollout_buffer.values.shape == (int(flags[-1][0].sum()), 1)


def test_masked_update_is_running_mean_std():
    # Chan's parallel update on the masked rows, an all-masked step included, is SB3's RunningMeanStd
    from stable_baselines3.common.running_mean_std import RunningMeanStd

    from abd_gym.agents.device_normalize import masked_update

    rng = np.random.default_rng(0)
    ref = RunningMeanStd(shape=(3,))
    mean, var, count = th.zeros(3, dtype=th.float64), th.ones(3, dtype=th.float64), th.tensor(1e-4, dtype=th.float64)
    for step in range(6):
        x = rng.normal(step, 1.0 + step, size=(10, 3))
        mask = rng.random(10) < (0.0 if step == 2 else 0.6)
        if mask.any():
            ref.update(x[mask])
        masked_update(mean, var, count, th.as_tensor(x), th.as_tensor(mask))
    np.testing.assert_allclose(mean.numpy(), ref.mean, rtol=1e-12)
    np.testing.assert_allclose(var.numpy(), ref.var, rtol=1e-12)
    assert float(count) == pytest.approx(ref.count, rel=1e-12)


def test_device_normalization_is_vecnormalize():
    # a VecNormalize config on the device path: the buffer holds VecNormalize's observations and
    # rewards, computed from the env's raw step outputs by SB3's own RunningMeanStd with the
    # NEXT_STEP masks (a step's last observation of an episode not counted, a reset step's reward
    # not accumulated), and the wrapper ends the rollout with the same statistics
    import copy

    from abd_gym.agents.common import build_train_env

    cfg = _config(LONG_STEPS, normalize="true", **{"hyperparams.n_epochs": 1})
    th.set_num_threads(1)
    env = build_train_env(cfg, rollout="device")
    model = build_model(cfg, env, rollout="device")
    from abd_gym.agents.device_rollout import find_adapter

    wrapper, adapter = env, find_adapter(env)
    steps, start = [], {}
    step_tensors = adapter.step_tensors

    def recording(actions):
        if not steps:
            start.update(obs=copy.deepcopy(wrapper.obs_rms), ret=copy.deepcopy(wrapper.ret_rms),
                         returns=wrapper.returns.copy(), first=model._last_obs.detach().clone().numpy())  # fmt: skip
        out = step_tensors(actions)
        steps.append([t.detach().clone().numpy() for t in (out.obs, out.rewards, out.terminated, out.truncated)])
        return out

    adapter.step_tensors = recording
    model.learn(total_timesteps=N_ENVS * N_STEPS)
    obs_rms, ret_rms, returns = start["obs"], start["ret"], start["returns"].copy()
    eps, clip_obs, clip_rew, gamma = wrapper.epsilon, wrapper.clip_obs, wrapper.clip_reward, wrapper.gamma
    ended = np.zeros(N_ENVS, dtype=bool)
    want_obs, want_rew = [start["first"]], []
    for obs, rew, term, trunc in steps:
        dones, valid = term | trunc, ~ended
        if (~dones).any():
            obs_rms.update(obs[~dones].astype(np.float64))
        returns = np.where(valid, returns * gamma + rew, returns)
        if valid.any():
            ret_rms.update(returns[valid])
        want_obs.append(np.clip((obs - obs_rms.mean) / np.sqrt(obs_rms.var + eps), -clip_obs, clip_obs))
        want_rew.append(np.clip(rew / np.sqrt(ret_rms.var + eps), -clip_rew, clip_rew))
        returns[dones] = 0.0
        ended = dones
    assert any(s[2].any() for s in steps)  # some episodes ended in the rollout
    assert ret_rms.count > N_ENVS * (N_STEPS - 2)  # the statistics took (nearly) every step
    t = model.rollout_buffer.storage
    np.testing.assert_allclose(t["observations"].numpy(), np.array(want_obs[:-1], dtype=np.float32), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(t["rewards"].numpy(), np.array(want_rew, dtype=np.float32), rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(wrapper.obs_rms.mean, obs_rms.mean, rtol=1e-10)
    np.testing.assert_allclose(wrapper.obs_rms.var, obs_rms.var, rtol=1e-10)
    np.testing.assert_allclose(wrapper.ret_rms.var, ret_rms.var, rtol=1e-10)
    assert wrapper.obs_rms.count == pytest.approx(obs_rms.count) and wrapper.ret_rms.count == pytest.approx(ret_rms.count)


def test_device_normalization_needs_a_next_step_env():
    from stable_baselines3.common.vec_env import VecNormalize

    cfg = _config(LONG_STEPS, normalize="true")
    env = VecNormalize(VecMonitor(make_vec_env(cfg["env_id"], cfg["n_envs"], seed=0, env_kwargs=cfg["env_kwargs"],
                                               backend="torch")))  # fmt: skip
    model = build_model(cfg, env, rollout="device")
    with pytest.raises(ValueError, match="NEXT_STEP env only: this env autoresets SAME_STEP"):
        model.learn(total_timesteps=N_ENVS * N_STEPS)
