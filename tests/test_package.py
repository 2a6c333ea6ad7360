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
    from abd_gym.vector.registration import env_ids

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


def _purelib(py: Path) -> str:
    """The site-packages folder of the environment whose interpreter is ``py``."""
    return subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                          capture_output=True, text=True, check=True).stdout.strip()  # fmt: skip


def _venv_seeing_these_packages(venv: Path) -> Path:
    """A virtual environment at ``venv`` that sees the packages this interpreter sees (its python).

    ``venv --system-site-packages`` sees the base interpreter's packages only: run from inside a
    virtual environment it would not see that environment's (warp, gymnasium, torch, ...).  So
    this interpreter's site-packages folders, its own virtual environment's among them, go after
    the new environment's own in a .pth file there; the repository (an editable install's path) is
    not among them, so ``import abd_gym`` finds what is installed in the new environment."""
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    py = venv / "bin" / "python"
    own = _purelib(py)
    seen = [p for p in sys.path if Path(p).name in ("site-packages", "dist-packages") and Path(p).is_dir()]
    (Path(own) / "parent_site_packages.pth").write_text("".join(f"{p}\n" for p in seen))
    return py


def _build_at_this_runs_level(py: Path) -> None:
    """Make the environment of ``py`` build Warp kernels at this test run's optimisation level
    (tests/conftest.py): a .pth line, run at each interpreter start there, sets it.  The training
    run's kernels are then the ones the other tests build, not a second build of them."""
    import warp as wp

    own = _purelib(py)
    level = wp.config.optimization_level
    (Path(own) / "test_build_level.pth").write_text(f"import warp; warp.config.optimization_level = {level!r}\n")


def test_venv_seeing_these_packages_finds_them(tmp_path):
    """The helper's environment imports what this interpreter imports from its site-packages (here
    Gymnasium, a dependency), from inside a virtual environment as well."""
    import gymnasium

    py = _venv_seeing_these_packages(tmp_path / "venv")
    where = subprocess.run([str(py), "-c", "import gymnasium; print(gymnasium.__file__)"], capture_output=True,
                           text=True, check=True, cwd=tmp_path).stdout.strip()  # fmt: skip
    assert Path(where).resolve() == Path(gymnasium.__file__).resolve()


@pytest.mark.slow
def test_the_wheel_holds_only_the_abd_gym_namespace_and_trains_from_any_directory(tmp_path):
    """``pip wheel .``: every file of the wheel under abd_gym/ (or its dist-info), the configs among
    them, the console scripts naming abd_gym.agents; installed (not editable) in a virtual
    environment, ``abd-gym-train cartpole_ppo`` runs from a folder that has no configs/."""
    import zipfile

    import shutil

    src = tmp_path / "src"  # a copy: setuptools builds in the source folder (build/, *.egg-info)
    shutil.copytree(REPO, src, ignore=shutil.ignore_patterns(".git", "build", "runs", "results", "*.egg-info", "__pycache__",
                                                             ".gpu", "ab_base", ".pytest_cache"))  # fmt: skip
    cmd = [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w", str(tmp_path), str(src)]
    out = subprocess.run(cmd, capture_output=True, text=True)
    if out.returncode:
        pytest.skip(f"pip wheel could not build here: {out.stderr.strip()[-300:]}")
    (wheel,) = tmp_path.glob("abd_gym-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    top = {n.split("/")[0] for n in names}
    assert top == {"abd_gym", next(t for t in top if t.endswith(".dist-info"))}, sorted(top)
    for must in ("abd_gym/configs/cartpole_ppo.yaml", "abd_gym/envs/cartpole.py", "abd_gym/agents/train.py",
                 "abd_gym/constitutions/revolute_limit.py"):
        assert must in names, must
    shipped = {n[len("abd_gym/configs/"):] for n in names if n.startswith("abd_gym/configs/") and n.endswith(".yaml")}
    assert shipped == {p.relative_to(REPO / "configs").as_posix() for p in (REPO / "configs").rglob("*.yaml")}
    # every package of the source tree is in the wheel (a new subpackage must be listed in pyproject.toml)
    for init in (REPO / "abd_gym").rglob("__init__.py"):
        assert str(init.relative_to(REPO)) in names, init
    entry = next(n for n in names if n.endswith("entry_points.txt"))
    text = zipfile.ZipFile(wheel).read(entry).decode()
    for script in ("train", "evaluate", "sweep"):
        assert f"abd-gym-{script} = abd_gym.agents.{script}:main" in text, script

    venv, work = tmp_path / "venv", tmp_path / "elsewhere"
    py = _venv_seeing_these_packages(venv)
    subprocess.run([str(py), "-m", "pip", "install", "-q", "--no-deps", str(wheel)], check=True)
    work.mkdir()
    where = subprocess.run([str(py), "-c", "import abd_gym.envs; print(abd_gym.envs.__file__)"], cwd=work,
                           capture_output=True, text=True, check=True).stdout
    assert str(venv) in where, where  # the installed copy, not the repository's
    _build_at_this_runs_level(py)
    run = subprocess.run([str(venv / "bin" / "abd-gym-train"), "cartpole_ppo", "--total-timesteps", "256", "--num-envs", "4",
                          "--eval-episodes", "1", "--no-progress", "--run-dir", str(work / "run")],
                         cwd=work, capture_output=True, text=True)  # fmt: skip
    assert run.returncode == 0, run.stderr[-2000:]
    assert (work / "run" / "summary.json").is_file() and not (work / "configs").exists()
