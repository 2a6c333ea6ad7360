"""The device-resident PPO rollout learns exactly as SB3's own NumPy rollout does (CPU)."""
from __future__ import annotations

import numpy as np
import pytest
import torch as th

pytest.importorskip("stable_baselines3")
from stable_baselines3.common.vec_env import VecMonitor  # noqa: E402

from abd_gym.agents.common import build_model  # noqa: E402
from abd_gym.agents.config import load_config  # noqa: E402
from abd_gym.agents.device_rollout import DevicePPO, TensorRolloutBuffer, rollout_path  # noqa: E402
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


def _train(cfg, rollout):
    # both paths step the same env (Torch backend); only the rollout differs
    th.set_num_threads(1)  # the orthogonal initialisation's QR rounds differently with more threads
    env = VecMonitor(make_vec_env(cfg["env_id"], cfg["n_envs"], seed=cfg["seed"], env_kwargs=cfg["env_kwargs"],
                                  backend="torch"))  # fmt: skip
    model = build_model(cfg, env, rollout=rollout)
    model.learn(total_timesteps=cfg["n_timesteps"])
    return model


@pytest.fixture(scope="module")
def both_paths():
    cfg = _config()
    return _train(cfg, "sb3"), _train(cfg, "device")


_FIELDS = ("observations", "actions", "rewards", "episode_starts", "values", "log_probs", "advantages", "returns")


def test_bit_identical_without_time_limit_cuts():
    cfg = _config(LONG_STEPS)
    sb3, dev = _train(cfg, "sb3"), _train(cfg, "device")
    assert len(sb3.ep_info_buffer) > 0  # some episodes terminated (reset inside a rollout)
    a, b = sb3.rollout_buffer, dev.rollout_buffer
    for name in _FIELDS:
        np.testing.assert_array_equal(getattr(a, name).astype(np.float32), getattr(b, name), err_msg=name)
    for (name, p), q in zip(sb3.policy.state_dict().items(), dev.policy.state_dict().values()):
        np.testing.assert_array_equal(p.numpy(), q.numpy(), err_msg=name)


def test_paths_choose_as_documented():
    assert rollout_path(_config())[0] == "device"
    assert rollout_path(_config(rollout="sb3"))[0] == "sb3"
    assert rollout_path(_config(normalize="true"))[0] == "sb3"
    with pytest.raises(ValueError, match="VecNormalize"):
        rollout_path(_config(normalize="true", rollout="device"))


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

    cfg = _config(**{"hyperparams.n_steps": 8, "hyperparams.batch_size": 32, "hyperparams.n_epochs": 1})
    cfg["n_timesteps"], cfg["eval_episodes"] = 2 * N_ENVS * 8, 2
    summary = agent_train.train(cfg, config_name="dev", run_dir=tmp_path / "run", progress_bar=False)
    assert summary["rollout"] == "device" and summary["timesteps"] == 2 * N_ENVS * 8
    assert summary["mean_episode_length"] > 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[1].startswith("rollout: device (")
    # the saved model is a plain PPO with SB3's own buffer, and trains on in SB3's rollout
    model = PPO.load(tmp_path / "run" / "model.zip", device="cpu")
    assert model.rollout_buffer_class is None or model.rollout_buffer_class.__name__ == "RolloutBuffer"
    env = VecMonitor(make_vec_env(cfg["env_id"], N_ENVS, seed=1, env_kwargs=cfg["env_kwargs"]))
    model.set_env(env)
    model.learn(total_timesteps=N_ENVS * 8, reset_num_timesteps=False)
    assert model.num_timesteps == 3 * N_ENVS * 8
