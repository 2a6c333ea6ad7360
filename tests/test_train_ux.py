"""Training UX: periodic evaluation (--eval-freq), plain progress lines, the run folder."""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

pytest.importorskip("stable_baselines3")

import abd_gym  # noqa: E402,F401 -- registers the abd_gym/ ids
from abd_gym.agents import train as agent_train  # noqa: E402
from abd_gym.agents.config import ConfigError, validate_config  # noqa: E402

CARTPOLE = "abd_gym/CartPole-v0"
N_ENVS, N_STEPS, TOTAL = 4, 64, 512  # two PPO rollouts of 256 env steps


def _config(tmp_path: Path) -> Path:
    cfg = {
        "env_id": CARTPOLE,
        "algo": "ppo",
        "n_envs": N_ENVS,
        "n_timesteps": TOTAL,
        "normalize": True,
        "seed": 1,
        "eval_episodes": 3,
        "hyperparams": {"n_steps": N_STEPS, "batch_size": 64, "n_epochs": 1},
        "policy_kwargs": {"net_arch": [16]},
    }
    path = tmp_path / "ux_ppo.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def _train(tmp_path: Path, run: str, *flags: str):
    args = agent_train.parse_args([str(_config(tmp_path)), "--run-dir", str(tmp_path / run), *flags])
    cfg, name = agent_train.config_from_args(args)
    return cfg, agent_train.train(cfg, config_name=name, run_dir=tmp_path / run, progress_bar=not args.no_progress)


def test_eval_freq_validated():
    base = {"env_id": CARTPOLE, "algo": "ppo", "n_timesteps": 100}
    assert validate_config(base)["eval_freq"] == 0
    assert validate_config({**base, "eval_freq": 1000})["eval_freq"] == 1000
    with pytest.raises(ConfigError, match="eval_freq"):
        validate_config({**base, "eval_freq": -1})
    with pytest.raises(ConfigError, match="eval_freq"):
        validate_config({**base, "eval_freq": "often"})


def test_periodic_evaluation_and_progress_lines(tmp_path, capsys, monkeypatch):
    # A threshold every episode reaches (CartPole pays 1 a step) makes the first evaluation the
    # first to reach it: threshold_step is that evaluation's env step.
    monkeypatch.setattr(agent_train, "reward_threshold", lambda env_id: 1.0)
    cfg, summary = _train(tmp_path, "eval", "--eval-freq", "128")
    run = tmp_path / "eval"
    out = capsys.readouterr().out

    assert cfg["eval_freq"] == 128
    for f in ("best_model.zip", "best_vecnormalize.pkl", "evaluations.npz", "model.zip", "summary.json"):
        assert (run / f).is_file(), f
    ev = np.load(run / "evaluations.npz")
    # every 128 env steps = every 32 vector steps of 4 worlds; 3 episodes each
    np.testing.assert_array_equal(ev["timesteps"], [128, 256, 384, 512])
    assert ev["results"].shape == (4, 3) and (ev["results"] >= 1).all()

    on_disk = json.loads((run / "summary.json").read_text())
    assert on_disk["periodic_evaluations"] == 4
    assert on_disk["threshold_step"] == 128
    assert 0 < on_disk["threshold_time_s"] <= on_disk["wall_time_s"]
    assert on_disk["best_periodic_return"] == pytest.approx(ev["results"].mean(axis=1).max())

    # no terminal under capsys: the run directory first, then plain lines, no progress bar
    lines = out.splitlines()
    assert lines[0] == f"run directory: {run}"
    progress = [ln for ln in lines if re.search(r"[\d,]+/512 steps \(\d+%\)\s+[\d,]+ steps/s\s+return ", ln)]
    assert progress and progress[-1].startswith("ux_ppo: 512/512 steps (100%)")
    evals = [ln for ln in lines if "eval at" in ln]
    assert len(evals) == 4 and "threshold 1: reached" in evals[0]


def test_eval_freq_zero_leaves_run_folder_as_before(tmp_path, capsys):
    _, summary = _train(tmp_path, "plain", "--no-progress")
    run = tmp_path / "plain"
    assert sorted(p.name for p in run.iterdir()) == [
        "checkpoints", "config.yaml", "model.zip", "summary.json", "tensorboard", "vecnormalize.pkl",
    ]
    assert summary["threshold_step"] is None and summary["threshold_time_s"] is None
    assert summary["periodic_evaluations"] == 0
    out = capsys.readouterr().out
    assert out.splitlines()[0] == f"run directory: {run}"
    assert "eval at" not in out and "512/512 steps (100%)" in out


def test_evaluate_pairs_each_model_with_its_statistics(tmp_path):
    from abd_gym.agents.evaluate import vecnormalize_for

    assert vecnormalize_for(tmp_path) is None  # a run that does not normalise
    for name in ("vecnormalize.pkl", "best_vecnormalize.pkl", "checkpoints/model_vecnormalize_512_steps.pkl"):
        (tmp_path / name).parent.mkdir(exist_ok=True)
        (tmp_path / name).write_bytes(b"")
    assert vecnormalize_for(tmp_path) == tmp_path / "vecnormalize.pkl"
    assert vecnormalize_for(tmp_path, tmp_path / "model.zip") == tmp_path / "vecnormalize.pkl"
    assert vecnormalize_for(tmp_path, tmp_path / "best_model.zip") == tmp_path / "best_vecnormalize.pkl"
    checkpoint = tmp_path / "checkpoints" / "model_512_steps.zip"
    assert vecnormalize_for(tmp_path, checkpoint) == tmp_path / "checkpoints" / "model_vecnormalize_512_steps.pkl"
