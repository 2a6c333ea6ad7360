"""docs/custom_task.md's example, as the page shows it: a new task registered, passed through
Gymnasium's and Stable-Baselines3's checkers, and trained for a few hundred steps on the CPU."""
import importlib.util
import re
from pathlib import Path

import gymnasium as gym
import pytest

REPO = Path(__file__).resolve().parent.parent
EXAMPLE = REPO / "docs" / "examples" / "furuta.py"


def _example():
    spec = importlib.util.spec_from_file_location("furuta_example", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


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
    summary = furuta.train(run_dir=tmp_path / "run", n_envs=4, n_timesteps=512, eval_episodes=2,
                           hyperparams={"n_steps": 64, "batch_size": 64})  # fmt: skip
    assert summary["timesteps"] == 512
    assert 0 < summary["mean_return"] <= 200
    assert (tmp_path / "run" / "model.zip").is_file()
