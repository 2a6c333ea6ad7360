import os

import pytest

os.environ.setdefault("WARP_CACHE_PATH", os.path.join(os.path.expanduser("~"), ".cache", "warp"))


def pytest_configure(config):
    config.addinivalue_line("markers", "slow: a longer check (learning, long trajectories); runs by default")
