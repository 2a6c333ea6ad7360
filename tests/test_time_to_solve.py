"""The time-to-solve table: its rows from the trials' summaries, its failures named, and the
shipped GPU configs it runs by default (the real sweeps behind it are tests/test_sweep.py's)."""
from __future__ import annotations

import json

import pytest

pytest.importorskip("stable_baselines3")

from abd_gym.agents import time_to_solve  # noqa: E402


def _summary(folder, seed, solved, threshold_time):
    folder.mkdir(parents=True)
    (folder / "summary.json").write_text(json.dumps(dict(
        env_id="abd_gym/CartPole-v0", algo="ppo", seed=seed, device_description="NVIDIA H100 80GB HBM3", n_envs=1024,
        timesteps=1_015_808, threshold_step=None if threshold_time is None else 524_288,
        threshold_time_s=threshold_time, wall_time_s=9.5, mean_return=500.0 if solved else 120.0, std_return=0.0,
        reward_threshold=475.0, solved=solved)))  # fmt: skip
    return str(folder)


def test_rows_and_solved_count(tmp_path):
    trials = [dict(seed=1, run_dir=_summary(tmp_path / "b", 1, False, None), error=None),
              dict(seed=0, run_dir=_summary(tmp_path / "a", 0, True, 4.25), error=None),
              dict(seed=2, run_dir=None, error="RayTaskError: CUDA out of memory")]  # fmt: skip
    rows = time_to_solve.collect("gpu/cartpole_ppo", trials)
    assert [(r["seed"], r["failed"]) for r in rows] == [(0, False), (1, False), (2, True)]
    assert rows[0]["threshold_time_s"] == 4.25 and rows[0]["solved"] and not rows[1]["solved"]
    table = time_to_solve.markdown(rows, "python -m abd_gym.agents.time_to_solve --out x", "2026-11-26")
    assert "| abd_gym/CartPole-v0 | gpu/cartpole_ppo (ppo) | 0 | NVIDIA H100 80GB HBM3 | 1,024 | 1,015,808 | 524,288 | 4.2 |" in table
    assert "failed: RayTaskError: CUDA out of memory" in table
    # a seed that never reached the threshold has no slowest time: the table says so, not a number
    assert "| gpu/cartpole_ppo | 1/3 | — |" in table


def test_defaults_to_every_gpu_config():
    configs = time_to_solve.gpu_configs()
    assert "gpu/cartpole_ppo" in configs and all(c.startswith("gpu/") for c in configs)


def test_a_bad_config_fails_before_ray_starts(tmp_path, capsys):
    assert time_to_solve.main(["no_such_config", "--out", str(tmp_path)]) == 2
    assert "no_such_config" in capsys.readouterr().err
    assert time_to_solve.main(["gpu/cartpole_ppo", "--out", str(tmp_path)]) == 2  # a GPU config needs a GPU share
    assert "--gpus-per-trial" in capsys.readouterr().err
