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


def _run(tmp_path, script=SCRIPT, **env):
    environ = {k: v for k, v in os.environ.items() if k != "ABD_GYM_VERBOSE"}
    environ.update(env)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=tmp_path, env=environ,
                         check=True, timeout=600)  # fmt: skip
    return [line for line in (out.stdout + out.stderr).splitlines() if line.strip()]


def test_library_use_prints_nothing_from_warp(tmp_path):
    """Not even the native library's no-CUDA-driver line on a machine without a GPU."""
    assert _run(tmp_path) == []


def test_abd_gym_verbose_turns_warp_up(tmp_path):
    lines = _run(tmp_path, ABD_GYM_VERBOSE="1")
    assert any(line.startswith("Warp ") and "initialized" in line for line in lines), lines
    assert any("load on device" in line for line in lines), lines


def test_init_keeps_the_native_libraries_other_lines(tmp_path):
    """init_without_driver_line drops the no-driver line only: other lines written to file
    descriptor 2 while Warp initialises come back on standard error."""
    script = """
import os, warp as wp
from abd_gym.core import warp_log
real_init = wp.init
def init():
    os.write(2, (warp_log.NO_DRIVER + ". GPU execution will not be available.\\n").encode())
    os.write(2, b"another native line\\n")
    real_init()
wp.init = init
warp_log.init_without_driver_line()
"""
    assert _run(tmp_path, script) == ["another native line"]
