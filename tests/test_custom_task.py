"""docs/custom_task.md's and docs/mjcf_task.md's examples, as the pages show them: a new task
registered, passed through Gymnasium's and Stable-Baselines3's checkers, and trained on the CPU
until its deterministic policy balances the pendulum far longer than a policy that learned nothing.

The learning check, measured on two CPU cores (64 envs, 3 resets each): the random policy holds
the Furuta pendulum 8.8 steps on average (the MJCF one 9.2), zero torque 18.7 (19.7); PPO's
deterministic policy after 4,096 steps (8 envs) returns 101-200 over seeds 0-4 (the MJCF one
114-139 over seeds 0-2), at ~9 s a run.  The check asks for 3x the better of the random and
zero-torque policies' returns over the same evaluation's resets: ~57, which a learner that
does not learn (no update, a policy stuck at a constant action) cannot reach."""
import importlib.util
import re
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

REPO = Path(__file__).resolve().parent.parent
EXAMPLE = REPO / "docs" / "examples" / "furuta.py"


def _load(path, name):
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _example():
    return _load(EXAMPLE, "furuta_example")


TRAIN = dict(n_envs=8, n_timesteps=4096, eval_episodes=8, seed=0, hyperparams={"n_steps": 64, "batch_size": 64})


def _untrained_return(env_id, episodes=16, max_steps=200):
    """The better of a uniformly random policy's and a zero-action policy's mean return over one
    episode in each of ``episodes`` worlds."""
    env = gym.make_vec(env_id, num_envs=episodes, vectorization_mode="vector_entry_point")
    rng = np.random.default_rng(0)
    best = -np.inf
    for policy in (lambda: rng.uniform(-1.0, 1.0, (episodes, 1)), lambda: np.zeros((episodes, 1))):
        env.reset(seed=0)
        total, done = np.zeros(episodes), np.zeros(episodes, dtype=bool)
        for _ in range(max_steps):
            _, reward, terminated, truncated, _ = env.step(policy().astype(np.float32))
            total += np.where(done, 0.0, reward)
            done |= terminated | truncated
            if done.all():
                break
        best = max(best, float(total.mean()))
    env.close()
    return best


def _assert_learned(summary, env_id):
    untrained = _untrained_return(env_id)
    assert 3.0 < untrained < 40.0  # the pendulum falls within a few dozen steps without control
    assert summary["mean_return"] > 3.0 * untrained, (summary["mean_return"], untrained)


def test_the_page_shows_the_example_file():
    page = (REPO / "docs" / "custom_task.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", page, flags=re.S)
    assert blocks == [EXAMPLE.read_text()]


def test_example_checks_and_trains(tmp_path):
    pytest.importorskip("stable_baselines3")
    furuta = _example()
    furuta.register()
    furuta.register()  # idempotent
    furuta.check()
    env = gym.make_vec(furuta.ENV_ID, num_envs=2, vectorization_mode="vector_entry_point")
    assert isinstance(env.unwrapped, furuta.FurutaVectorEnv)
    env.close()
    summary = furuta.train(run_dir=tmp_path / "run", **TRAIN)
    assert summary["timesteps"] == TRAIN["n_timesteps"]
    _assert_learned(summary, furuta.ENV_ID)
    assert (tmp_path / "run" / "model.zip").is_file()


MJCF_PAGE = REPO / "docs" / "mjcf_task.md"
MJCF_EXAMPLE = REPO / "docs" / "examples" / "furuta_mjcf.py"


def _mjcf_example():
    return _load(MJCF_EXAMPLE, "furuta_mjcf_example")


def test_the_mjcf_page_shows_the_example_files():
    page = MJCF_PAGE.read_text()
    assert re.findall(r"```xml\n(.*?)```", page, flags=re.S) == [(REPO / "docs" / "examples" / "furuta.xml").read_text()]
    assert re.findall(r"```python\n(.*?)```", page, flags=re.S)[-1] == MJCF_EXAMPLE.read_text()


def test_mjcf_example_matches_mujoco_checks_and_trains(tmp_path):
    pytest.importorskip("mujoco")
    pytest.importorskip("stable_baselines3")
    furuta = _mjcf_example()
    # the page's claim: 5e-3 rad over 1 s at dt 0.002 (float64; the pendulum falls and swings
    # through several radians, so this is the two engines' integration error, not a state that sat still)
    assert furuta.compare_with_mujoco() < 0.01
    furuta.register()
    furuta.check()
    summary = furuta.train(run_dir=tmp_path / "run", **TRAIN)
    assert summary["timesteps"] == TRAIN["n_timesteps"]
    _assert_learned(summary, furuta.ENV_ID)
