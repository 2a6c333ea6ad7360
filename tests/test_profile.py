"""The training profiler times every piece of a PPO iteration on both rollout paths (CPU, tiny):
each timer on the function an iteration runs, entered as often as the iteration runs it."""
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
    n_steps = 8
    for path in report["paths"].values():
        sections = path["sections"]
        assert all(s["s_per_iteration"] > 0 for s in sections.values())
        # the timers sit on the functions an iteration runs, as often as it runs them: the env's
        # step and the buffer's record once a step, one rollout and one update an iteration
        calls = {name: s["calls_per_iteration"] for name, s in sections.items()}
        assert calls["env step"] == calls["buffer add"] == n_steps
        assert calls["rollout other"] == calls["update"] == 1
        assert calls["policy"] >= n_steps and calls["GAE"] >= 1
        # exclusive times: the pieces of the instrumented iterations add up to no more than their
        # wall time (a piece counted inside another as well would exceed it)
        wall = path["steps_per_iteration"] / path["instrumented_steps_per_s"]
        assert sum(s["s_per_iteration"] for s in sections.values()) <= wall
        assert path["steps_per_iteration"] == 4 * n_steps
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
    # each bracket sits on what the rollout runs, as often as it runs it: the env's step and a
    # record every step, the policy every step (the first step's act, then record-and-act)
    calls = r["calls"]
    assert calls["env step"] == 8
    assert calls["act"] == 1 and calls["record and act"] == 7 and calls["record"] == 1
    assert calls["start"] == calls["end"] == calls["finish"] == calls["buffer reset"] == 1
    assert "env step" in capsys.readouterr().out
