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
    # not stopped: the last rollout's update followed every evaluation, so best_model.zip is scored
    # on the final evaluation's episodes even where it was saved at the last step
    best = on_disk["best_model"]
    assert on_disk["stopped_step"] is None and not best["same_as_final"] and best["eval_episodes"] == 3
    assert best["periodic_return"] == pytest.approx(on_disk["best_periodic_return"])

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


def test_stop_when_solved_validated():
    base = {"env_id": CARTPOLE, "algo": "ppo", "n_timesteps": 100}
    assert validate_config(base)["stop_when_solved"] == 0
    assert validate_config({**base, "eval_freq": 10, "stop_when_solved": 3})["stop_when_solved"] == 3
    with pytest.raises(ConfigError, match="stop_when_solved: must be 0"):
        validate_config({**base, "eval_freq": 10, "stop_when_solved": -1})
    with pytest.raises(ConfigError, match="stop_when_solved: 2 needs periodic evaluations; set eval_freq"):
        validate_config({**base, "stop_when_solved": 2})


def test_stop_lines_name_the_solved_evaluations():
    from abd_gym.agents.progress import evaluations_in_a_row

    assert evaluations_in_a_row(1) == "1 evaluation"
    assert evaluations_in_a_row(3) == "3 evaluations in a row"


def test_stop_when_solved_ends_training_after_solved_evaluations_in_a_row(tmp_path, capsys, monkeypatch):
    # Every CartPole episode pays at least 1, so every evaluation is solved with a margin against a
    # threshold of 1: two evaluations (at 128 and 256 env steps) end the 512-step run at 256.
    monkeypatch.setattr(agent_train, "reward_threshold", lambda env_id: 1.0)
    _, summary = _train(tmp_path, "stop", "--eval-freq", "128", "stop_when_solved=2")
    ev = np.load(tmp_path / "stop" / "evaluations.npz")
    np.testing.assert_array_equal(ev["timesteps"], [128, 256])
    assert summary["stopped_step"] == 256 and summary["timesteps"] == 256
    assert summary["stop_when_solved"] == 2 and summary["solved"]
    assert "stopping at 256 steps: solved in 2 evaluations in a row" in capsys.readouterr().out
    # the best model was saved at 128 or 256: scored on the final evaluation's episodes unless final
    best = summary["best_model"]
    assert best["file"] == "best_model.zip" and best["step"] in (128, 256)
    assert best["same_as_final"] == (best["step"] == 256)
    if not best["same_as_final"]:
        assert best["eval_episodes"] == summary["eval_episodes"] == 3
    assert summary["use_model"] == ("best_model.zip" if summary["final_below_best"] else "model.zip")

    # abd-gym-evaluate says which model it evaluates: the one use_model names, or --final's
    from abd_gym.agents import evaluate

    run = tmp_path / "stop"
    capsys.readouterr()
    assert evaluate.main([str(run), "--episodes", "2", "--json", str(tmp_path / "e.json")]) == 0
    assert f"model: {run / summary['use_model']}" in capsys.readouterr().out
    on_disk = json.loads((run / "summary.json").read_text())
    on_disk.update(use_model="best_model.zip", best_model={**best, "mean_return": 1e6})
    (run / "summary.json").write_text(json.dumps(on_disk))
    assert evaluate.main([str(run), "--episodes", "2", "--json", str(tmp_path / "e.json")]) == 0
    out = capsys.readouterr().out
    assert f"model: {run / 'best_model.zip'} (the final model.zip scored" in out and "(ppo, best_model.zip)" in out
    assert json.loads((tmp_path / "e.json").read_text())["model"] == str(run / "best_model.zip")
    assert evaluate.main([str(run), "--episodes", "2", "--final"]) == 0
    assert f"model: {run / 'model.zip'} (--final)" in capsys.readouterr().out


def test_threshold_eval_streak_needs_a_standard_error_to_spare():
    from abd_gym.agents.progress import ThresholdEval

    check = ThresholdEval.solved_with_margin
    probe = type("Probe", (), {"threshold": 10.0})()
    assert check(probe, [12.0, 12.0, 12.0, 12.0])  # std 0: the mean alone decides
    # mean 11, std 2, 4 episodes: standard error 1, so 11 - 1 = 10 reaches 10; 10.5 would not
    assert check(probe, [9.0, 13.0, 9.0, 13.0])
    assert not check(probe, [8.5, 12.5, 8.5, 12.5])
    probe.threshold = None
    assert not check(probe, [12.0])


def test_final_below_best_by_more_than_the_standard_error():
    from abd_gym.agents.common import compare_to_best

    final = {"mean_return": 243.0, "std_return": 17.0, "eval_episodes": 1024}
    best = {"file": "best_model.zip", "mean_return": 480.0, "std_return": 20.0, "eval_episodes": 1024}
    assert compare_to_best(final, best) == (True, "best_model.zip")
    # standard error 16 / sqrt(4) = 8: a best model 7.9 higher is within it, 8.1 higher is not
    final = {"mean_return": 100.0, "std_return": 16.0, "eval_episodes": 4}
    assert compare_to_best(final, {**best, "mean_return": 107.9}) == (False, "model.zip")
    assert compare_to_best(final, {**best, "mean_return": 108.1}) == (True, "best_model.zip")
    assert compare_to_best(final, None) == (False, "model.zip")
    assert compare_to_best(final, {"file": "best_model.zip", "same_as_final": True}) == (False, "model.zip")


def _fake_run(folder: Path, **summary) -> Path:
    folder.mkdir(parents=True)
    (folder / "config.yaml").write_text(yaml.safe_dump({"env_id": CARTPOLE, "algo": "ppo", "n_timesteps": 100}))
    for name in ("model.zip", "best_model.zip"):
        (folder / name).write_bytes(b"")
    (folder / "summary.json").write_text(json.dumps(summary))
    return folder


def test_evaluate_defaults_to_the_best_model_where_the_final_one_is_worse(tmp_path):
    from abd_gym.agents.evaluate import default_model

    worse = _fake_run(tmp_path / "worse", mean_return=243.0, use_model="best_model.zip",
                      best_model={"file": "best_model.zip", "mean_return": 480.0})  # fmt: skip
    path, why = default_model(worse)
    assert path == worse / "best_model.zip" and "243.00, below best_model.zip's 480.00" in why and "--final" in why
    fine = _fake_run(tmp_path / "fine", mean_return=480.0, use_model="model.zip")
    assert default_model(fine)[0] == fine / "model.zip"
    (worse / "best_model.zip").unlink()  # named but gone: the final model, not a missing file
    assert default_model(worse)[0] == worse / "model.zip"


@pytest.mark.parametrize("flags, message", [
    (["--episodes", "0"], "--episodes 0: must be at least 1"),
    (["--episodes", "-3"], "--episodes -3: must be at least 1"),
    (["--video-episodes", "0"], "--video-episodes 0: must be at least 1"),
    (["--video", "x.avi"], "unsupported video format '.avi'; use .gif or .mp4"),
    (["--model", "nowhere.zip"], "--model nowhere.zip: no such file"),
])  # fmt: skip
def test_evaluate_refuses_bad_arguments_before_it_runs(tmp_path, capsys, flags, message):
    from abd_gym.agents import evaluate

    run = _fake_run(tmp_path / "run", mean_return=1.0, use_model="model.zip")
    assert evaluate.main([str(run), *flags]) == 2
    out = capsys.readouterr()
    assert message in out.err and out.out == ""  # nothing loaded, nothing evaluated


def test_evaluate_checks_the_mp4_writer_before_it_runs(tmp_path, capsys, monkeypatch):
    import importlib.util
    import sys

    from abd_gym.agents import evaluate

    find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "av" else find_spec(name, *a))
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)  # importing it raises ImportError
    run = _fake_run(tmp_path / "run", mean_return=1.0, use_model="model.zip")
    assert evaluate.main([str(run), "--video", str(tmp_path / "x.mp4")]) == 2
    out = capsys.readouterr()
    assert "writing MP4 needs" in out.err and "pip install 'imageio[ffmpeg]', or write a .gif" in out.err
    assert out.out == "" and not (tmp_path / "x.mp4").exists()


def test_a_misspelt_config_name_lists_the_configs_and_the_closest(capsys):
    assert agent_train.main(["cartpol_ppo"]) == 2
    err = capsys.readouterr().err
    assert "no config 'cartpol_ppo' (did you mean cartpole_ppo" in err
    assert "gpu/inverted_double_pendulum_ppo" in err and "reacher_v5_sac" in err  # the list of what exists


def test_a_final_policy_below_its_best_is_named_in_the_last_line(tmp_path, capsys, monkeypatch):
    # what the comparison decides is compare_to_best's (tested above); here: what the run says then
    monkeypatch.setattr(agent_train, "reward_threshold", lambda env_id: 1.0)
    monkeypatch.setattr(agent_train, "compare_to_best", lambda final, best: (True, "best_model.zip"))
    run = tmp_path / "below"
    assert agent_train.main([str(_config(tmp_path)), "--run-dir", str(run), "--eval-freq", "128", "--no-progress"]) == 0
    last = capsys.readouterr().out.splitlines()[-1]
    assert last.startswith("final policy worse than its best: model.zip ")
    assert "best_model.zip (saved at " in last and last.endswith("use best_model.zip (abd-gym-evaluate evaluates it by default)")
    summary = json.loads((run / "summary.json").read_text())
    assert summary["final_below_best"] and summary["use_model"] == "best_model.zip"
