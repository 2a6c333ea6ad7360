"""Evaluation on the device plays the episodes SB3's ``evaluate_policy`` plays (CPU: the same code
runs eagerly there)."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("stable_baselines3")
from gymnasium.vector import AutoresetMode  # noqa: E402
from stable_baselines3 import PPO, SAC  # noqa: E402
from stable_baselines3.common.evaluation import evaluate_policy  # noqa: E402
from stable_baselines3.common.vec_env import VecMonitor, VecNormalize  # noqa: E402

from abd_gym.agents.common import build_eval_env, episode_evaluator  # noqa: E402
from abd_gym.agents.config import load_config  # noqa: E402
from abd_gym.agents.device_eval import DeviceEvaluator  # noqa: E402
from abd_gym.agents.progress import ThresholdEval  # noqa: E402
from abd_gym.agents.sb3_vec_env import make_vec_env  # noqa: E402

N = 8
SEED = 7


def _env(env_id: str, on_device: bool, **kwargs):
    return VecMonitor(make_vec_env(
        env_id, N, device="cpu", seed=SEED, backend="torch" if on_device else None,
        autoreset_mode=AutoresetMode.NEXT_STEP if on_device else AutoresetMode.SAME_STEP, env_kwargs=kwargs,
    ))  # fmt: skip


def _frozen_normalize(venv, mean, var):
    venv = VecNormalize(venv, norm_reward=False, clip_obs=2.0)
    venv.obs_rms.mean, venv.obs_rms.var = mean.copy(), var.copy()
    venv.training = False
    return venv


def _episodes(returns, lengths):
    return sorted(zip(lengths, returns))


@pytest.mark.parametrize(
    "env_id, algo, normalize",
    [("abd_gym/CartPole-v0", PPO, True),  # a Box policy clipped to the bounds, observations normalised
     ("abd_gym/Pendulum-v0", SAC, False)],  # a squashed policy, unscaled to the bounds
)  # fmt: skip
def test_device_evaluator_plays_evaluate_policys_episodes(env_id, algo, normalize):
    kwargs = {"max_episode_steps": 40}
    model = algo("MlpPolicy", _env(env_id, False, **kwargs), seed=0, device="cpu")
    sb3_env, dev_env = _env(env_id, False, **kwargs), _env(env_id, True, **kwargs)
    if normalize:
        rng = np.random.default_rng(0)
        shape = sb3_env.observation_space.shape
        mean, var = rng.normal(0, 0.1, shape), rng.uniform(0.05, 2.0, shape)
        sb3_env, dev_env = _frozen_normalize(sb3_env, mean, var), _frozen_normalize(dev_env, mean, var)
    sb3 = evaluate_policy(model, sb3_env, n_eval_episodes=N, deterministic=True, return_episode_rewards=True)
    ours = DeviceEvaluator(dev_env)(model, N)
    # one episode a world from the same seeded reset: the same episodes (evaluate_policy lists them
    # in the order they ended, the device world by world)
    got, want = _episodes(*ours), _episodes(*sb3)
    assert [l for l, _ in got] == [l for l, _ in want]
    np.testing.assert_allclose([r for _, r in got], [r for _, r in want], rtol=1e-5)
    lengths = {l for l, _ in want}
    if env_id.endswith("CartPole-v0"):
        assert min(lengths) < 40  # some episode terminated before the time limit
    assert max(lengths) <= 40


def test_device_evaluator_counts_episodes_as_evaluate_policy():
    env = _env("abd_gym/CartPole-v0", True, max_episode_steps=12)
    model = PPO("MlpPolicy", env, seed=0, device="cpu")
    evaluator = DeviceEvaluator(env)
    episodes = 2 * N + 3  # worlds 5, 6, 7 play a third episode (evaluate_policy's targets)
    returns, lengths = evaluator(model, episodes)
    assert len(returns) == len(lengths) == episodes
    assert all(1 <= l <= 12 for l in lengths)
    # CartPole-v0 pays 1 a step: a return is its episode's length
    np.testing.assert_allclose(returns, lengths)
    again = evaluator(model, episodes)  # the captured state is reused
    assert len(again[0]) == episodes


def test_device_evaluator_refuses_an_env_that_is_not_next_step():
    env = _env("abd_gym/CartPole-v0", False)
    with pytest.raises(ValueError, match="SAME_STEP mode, not NEXT_STEP"):
        DeviceEvaluator(env)
    assert not isinstance(episode_evaluator(env), DeviceEvaluator)  # SB3's evaluate_policy serves it
    from stable_baselines3.common.vec_env import VecFrameStack

    stacked = VecFrameStack(_env("abd_gym/CartPole-v0", True), n_stack=2)  # its observations are not the env's
    with pytest.raises(ValueError, match="wrapped in VecFrameStack"):
        DeviceEvaluator(stacked)


def test_threshold_eval_evaluates_on_the_device(tmp_path):
    cfg = load_config("cartpole_ppo", ["hyperparams.n_steps=16", "hyperparams.batch_size=32", "hyperparams.n_epochs=1"])
    eval_env = build_eval_env(cfg, num_envs=N, seed=SEED, device="cpu", on_device=True)
    lines = []
    callback = ThresholdEval(eval_env, threshold=1.0, write=lines.append, eval_freq=16, n_eval_episodes=N,
                             best_model_save_path=str(tmp_path), log_path=str(tmp_path), verbose=0)  # fmt: skip
    assert isinstance(callback.evaluate, DeviceEvaluator)
    model = PPO("MlpPolicy", _env("abd_gym/CartPole-v0", False), n_steps=16, batch_size=32, n_epochs=1, seed=0,
                device="cpu")  # fmt: skip
    model.learn(total_timesteps=2 * 16 * N, callback=callback)
    assert callback.n_evaluations == 2 and callback.eval_time_s > 0
    assert callback.threshold_step == 16 * N  # every return is at least 1
    log = np.load(tmp_path / "evaluations.npz")
    assert log["results"].shape == (2, N) and (log["results"] == log["ep_lengths"]).all()
    assert (tmp_path / "best_model.zip").is_file()
    assert len(lines) == 2 and f"over {N} episodes (threshold 1: reached)" in lines[0]


def test_eval_times_script_times_both_paths(tmp_path, capsys, script):
    import json

    from abd_gym.agents.train import train

    cfg = load_config("cartpole_ppo", ["n_timesteps=256", "eval_freq=0", "stop_when_solved=0", f"eval_episodes={N}"])
    train(cfg, config_name="cartpole_ppo", run_dir=tmp_path / "run", progress_bar=False)
    script = script("eval_times")
    out = tmp_path / "t.json"
    assert script.main([str(tmp_path / "run"), "--repeat", "1", "--json", str(out)]) == 0
    (row,) = json.loads(out.read_text())
    assert row["episodes"] == N and row["sb3_s"] > 0 and row["device_s"] > 0
    # one episode a world from the seeded reset: both paths play the same episodes
    assert row["device_mean_return"] == pytest.approx(row["sb3_mean_return"], rel=1e-6)
    assert row["device_mean_length"] == row["sb3_mean_length"]
    assert "| abd_gym/CartPole-v0 | 8 |" in capsys.readouterr().out
    # the CPU run evaluated with SB3's evaluate_policy, and says so
    assert json.loads((tmp_path / "run" / "summary.json").read_text())["evaluator"] == "sb3"
