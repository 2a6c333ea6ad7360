"""The package's layout as installed: the tasks, the training code and the configs inside the
abd_gym namespace (nothing generic at the top level), found through the package's own modules
wherever the working directory is."""
import importlib
import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent


def test_subpackages_under_abd_gym():
    for name in ("abd_gym.envs", "abd_gym.agents", "abd_gym.configs"):
        assert importlib.util.find_spec(name) is not None, name
    import abd_gym.envs.cartpole

    assert Path(abd_gym.envs.cartpole.__file__).resolve().parent.name == "envs"


def test_configs_ship_with_the_package(tmp_path, monkeypatch):
    pytest.importorskip("yaml")
    from importlib import resources

    from abd_gym.agents.config import find_config

    shipped = sorted(p.name for p in resources.files("abd_gym.configs").iterdir() if p.name.endswith(".yaml"))
    assert "cartpole_ppo.yaml" in shipped
    assert shipped == sorted(p.name for p in (REPO / "configs").glob("*.yaml"))
    monkeypatch.chdir(tmp_path)  # no ./configs here: the shipped ones
    assert find_config("cartpole_ppo").read_text() == (REPO / "configs" / "cartpole_ppo.yaml").read_text()
    monkeypatch.chdir(REPO)
    assert find_config("configs/cartpole_ppo.yaml").is_file()  # a repository path still works
    with pytest.raises(FileNotFoundError, match="no config 'nope'"):
        find_config("nope")


def test_registered_entry_points_name_the_namespace():
    import gymnasium as gym

    import abd_gym  # noqa: F401
    from abd_gym.registration import env_ids

    for env_id in env_ids():
        spec = gym.spec(env_id)
        assert spec.entry_point.startswith("abd_gym.envs."), spec.entry_point
        assert spec.vector_entry_point.startswith("abd_gym.envs."), spec.vector_entry_point


def test_import_abd_gym_imports_no_task_or_training_module(tmp_path):
    """The library does not import the tasks or the training code (the ids name them by string)."""
    prefixes = ("abd_gym.envs", "abd_gym.agents", "envs", "agents")
    code = f"import sys, abd_gym; print(sorted(m for m in sys.modules if m.startswith({prefixes!r})))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, check=True)
    assert out.stdout.strip() == "[]"
