"""The training profiler times every piece of a PPO iteration on both rollout paths (CPU, tiny)."""
from __future__ import annotations

import json

import pytest

pytest.importorskip("stable_baselines3")
from abd_gym.agents import profile as agent_profile  # noqa: E402


def test_profile_both_paths(tmp_path, capsys):
    out = tmp_path / "p.json"
    argv = ["cartpole_ppo", "--num-envs", "4", "--rollouts", "1", "hyperparams.n_steps=8",
            "hyperparams.batch_size=16", "hyperparams.n_epochs=1", "--json", str(out)]  # fmt: skip
    assert agent_profile.main(argv) == 0
    report = json.loads(out.read_text())
    assert set(report["paths"]) == {"sb3", "device"} and report["default_rollout"] == "sb3"  # on the CPU
    for path in report["paths"].values():
        shares = [s["share"] for s in path["sections"].values()]
        assert sum(shares) == pytest.approx(1.0)
        assert all(s["s_per_iteration"] > 0 for s in path["sections"].values())
        assert path["steps_per_iteration"] == 32
        # the rollout phase alone is faster than rollout plus update
        assert path["rollout_steps_per_s"] > path["train_steps_per_s"] > 0
    assert report["vector_env_steps_per_s"] > 0
    text = capsys.readouterr().out
    assert "env step" in text and "update" in text and "vector env alone" in text


def test_rollout_step_times_brackets_every_piece(tmp_path, capsys, script):
    script = script("rollout_step_times")
    out = tmp_path / "t.json"
    argv = ["cartpole_ppo", "--num-envs", "4", "--rollouts", "2", "hyperparams.n_steps=8",
            "hyperparams.batch_size=16", "hyperparams.n_epochs=1", "--json", str(out)]  # fmt: skip
    assert script.main(argv) == 0
    r = json.loads(out.read_text())
    assert r["n_steps"] == 8 and r["gpu_ms"] is None  # the CPU: host clocks only
    pieces = {name for _, _, name in script.PIECES} | {"callbacks", script.OTHER}
    assert set(r["host_ms"]) == pieces and all(v > 0 for v in r["host_ms"].values())
    # the pieces partition the rollout: their times add up to its wall time
    assert sum(r["host_ms"].values()) == pytest.approx(r["wall_ms"], rel=1e-6)
    assert "env step" in capsys.readouterr().out
