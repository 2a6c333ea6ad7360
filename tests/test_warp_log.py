"""Warp stays quiet while abd_gym is used as a library, and can be turned up again."""
import os
import subprocess
import sys

SCRIPT = """
import gymnasium as gym
import abd_gym
env = gym.make("abd_gym/Pendulum-v0")
env.reset(seed=0)
env.step(env.action_space.sample())
env.close()
"""
# Warp's native library prints this on a machine without a CUDA driver, whatever its log level
NO_DRIVER = "Warp CUDA warning: Could not find or load the NVIDIA CUDA driver"


def _run(tmp_path, **env):
    environ = {k: v for k, v in os.environ.items() if k != "ABD_GYM_VERBOSE"}
    environ.update(env)
    out = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, cwd=tmp_path, env=environ,
                         check=True, timeout=600)  # fmt: skip
    return [line for line in (out.stdout + out.stderr).splitlines() if line.strip() and NO_DRIVER not in line]


def test_library_use_prints_nothing_from_warp(tmp_path):
    assert _run(tmp_path) == []


def test_abd_gym_verbose_turns_warp_up(tmp_path):
    lines = _run(tmp_path, ABD_GYM_VERBOSE="1")
    assert any(line.startswith("Warp ") and "initialized" in line for line in lines), lines
    assert any("load on device" in line for line in lines), lines
