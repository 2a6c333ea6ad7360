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


def test_best_model_and_stop_columns(tmp_path):
    folder = tmp_path / "a"
    _summary(folder, 0, True, 4.25)
    s = json.loads((folder / "summary.json").read_text())
    s.update(stopped_step=786_432, eval_episodes=1024, final_below_best=True, std_return=17.0, mean_return=243.0,
             best_model=dict(file="best_model.zip", step=524_288, same_as_final=False, mean_return=480.0, std_return=20.0))
    (folder / "summary.json").write_text(json.dumps(s))
    row = time_to_solve.row_from_summary("gpu/cartpole_ppo", folder / "summary.json")
    assert (row["stopped_step"], row["best_return"], row["best_step"], row["final_below_best"]) == (786_432, 480.0, 524_288, True)
    table = time_to_solve.markdown([row], "cmd", "2026-12-07")
    assert "| 786,432 | 9.5 | 243.0 ± 17.0 | 480.0 ± 20.0 (final below) | 475 |" in table
    assert "| gpu/cartpole_ppo | 1/1 | 4.2 | 1/1 |" in table  # solved, slowest time, final below best
    # a best model that is the final policy scores what the final policy scores
    s.update(best_model=dict(file="best_model.zip", step=1_015_808, same_as_final=True), final_below_best=False)
    (folder / "summary.json").write_text(json.dumps(s))
    row = time_to_solve.row_from_summary("gpu/cartpole_ppo", folder / "summary.json")
    assert (row["best_return"], row["best_std"]) == (243.0, 17.0)


def test_serial_trials_without_ray(tmp_path, monkeypatch):
    import yaml

    from abd_gym.agents import train as agent_train

    # CartPole pays at least 1 an episode: a threshold of 1 is solved at every evaluation, so each
    # trial stops at its second evaluation (256 env steps of 4 worlds)
    monkeypatch.setattr(agent_train, "reward_threshold", lambda env_id: 1.0)
    cfg = {"env_id": "abd_gym/CartPole-v0", "algo": "ppo", "n_envs": 4, "n_timesteps": 1024, "normalize": True,
           "eval_episodes": 2, "eval_freq": 128, "stop_when_solved": 2,
           "hyperparams": {"n_steps": 32, "batch_size": 64, "n_epochs": 1}, "policy_kwargs": {"net_arch": [8]}}  # fmt: skip
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(cfg))
    out = tmp_path / "tts"
    code = time_to_solve.main([str(path), "--out", str(out), "--seeds", "5,6", "--serial", "--warmup"])
    assert code == 0
    rows = json.loads((out / "time_to_solve.json").read_text())["rows"]
    assert [(r["seed"], r["failed"], r["stopped_step"], r["timesteps"]) for r in rows] == [(5, False, 256, 256),
                                                                                            (6, False, 256, 256)]
    assert (out / "warmup" / "tiny" / "summary.json").is_file()  # one evaluation interval: 128 steps
    assert json.loads((out / "warmup" / "tiny" / "summary.json").read_text())["timesteps"] == 128
    table = (out / "time_to_solve.md").read_text()
    assert "| 5 | cpu" in table and f"| {path} | 2/2 |" in table


def test_warmup_needs_serial(tmp_path):
    with pytest.raises(SystemExit):
        time_to_solve.parse_args(["--out", str(tmp_path), "--warmup"])
