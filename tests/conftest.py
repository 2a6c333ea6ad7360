import importlib.util
import os
from pathlib import Path

import pytest

os.environ.setdefault("WARP_CACHE_PATH", os.path.join(os.path.expanduser("~"), ".cache", "warp"))

import warp as wp  # noqa: E402

# The tests build a few hundred CPU kernel modules and run most of them for a handful of steps
# on a handful of worlds, so on the CPU the suite's time goes to LLVM optimising kernels rather
# than to running them.  The CPU test run therefore builds its kernels at optimisation level 0.
# The library's own default (Warp's, for users' kernels) is untouched.  CPU results stay the
# same bits as at the default level: tests/test_golden.py compares stored trajectories.  Warp's
# module hash includes the level, so these builds sit beside the default-level ones in a shared
# kernel cache instead of replacing them.  A GPU test run (ABD_GYM_DEVICE=cuda:N) keeps the
# default level, for its CUDA kernels are built at it.  pytest-xdist workers import this file
# before collecting tests, so the level is set in each worker before any kernel is built.
if os.environ.get("ABD_GYM_DEVICE", "cpu") == "cpu":
    wp.config.optimization_level = 0


def pytest_configure(config):
    config.addinivalue_line("markers", "slow: a longer check (learning, long trajectories); runs by default")


NO_CPU = "device 'cpu' is not available"


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    """A test that builds a CPU simulator or env on a machine where Warp lists no CPU device (a GPU
    image without Warp's CPU compiler) is reported as skipped, naming why: the machine, not the
    code, stopped it.  Every other failure stands."""
    outcome = yield
    report = outcome.get_result()
    if report.failed and call.excinfo is not None and call.excinfo.errisinstance(ValueError) \
            and str(call.excinfo.value).startswith(NO_CPU):  # fmt: skip
        report.outcome = "skipped"
        report.longrepr = (str(item.path), item.location[1] or 0, f"Skipped: {call.excinfo.value}")


@pytest.fixture
def script():
    """``script(name)``: the module ``scripts/<name>.py`` of the repository, loaded from its file
    (scripts/ is no package), so that a test can call its ``main``."""

    def load(name: str):
        path = Path(__file__).resolve().parents[1] / "scripts" / f"{name}.py"
        spec = importlib.util.spec_from_file_location(name, path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module

    return load
