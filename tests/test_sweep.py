"""abd-gym-sweep: a real two-seed sweep on a local Ray instance (2 CPUs, 1 per trial), its
aggregate, its resume, and the argument errors."""
from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

pytest.importorskip("stable_baselines3")
ray = pytest.importorskip("ray")
pytest.importorskip("ray.tune")

from abd_gym.agents import sweep  # noqa: E402
from abd_gym.agents.config import ConfigError  # noqa: E402

TINY = [
    "--total-timesteps", "256", "--num-envs", "4", "--eval-episodes", "2",
    "hyperparams.n_steps=32", "hyperparams.batch_size=64", "hyperparams.n_epochs=2",
    "policy_kwargs.net_arch=[16]",
]  # fmt: skip


@pytest.fixture(scope="module")
def local_ray():
    """A local Ray instance of 2 CPUs (the CI machine's cores) whose worker processes build Warp
    kernels at this test run's optimisation level (tests/conftest.py), as the test processes do:
    the trials' kernels are then the ones other tests have built, not a second build of them."""
    import warp as wp

    level = wp.config.optimization_level

    def build_level():
        import warp as wp

        wp.config.optimization_level = level

    ray.init(num_cpus=2, include_dashboard=False, runtime_env={"worker_process_setup_hook": build_level})
    yield
    ray.shutdown()


def _mtimes(out: Path) -> dict[str, int]:
    return {p.parent.name: p.stat().st_mtime_ns for p in (out / "runs").glob("*/summary.json")}


def test_two_seeds_run_aggregate_and_resume(local_ray, tmp_path, capsys):
    out = tmp_path / "sweep"
    argv = ["cartpole_ppo", "--seeds", "0,1", "--cpus-per-trial", "1", "--out", str(out), *TINY]
    assert sweep.main(argv) == 0

    runs = sorted(p.name for p in (out / "runs").iterdir())
    assert runs == ["cartpole_ppo-seed0", "cartpole_ppo-seed1"]
    for name in runs:
        summary = json.loads((out / "runs" / name / "summary.json").read_text())
        assert (out / "runs" / name / "model.zip").is_file()
        assert summary["timesteps"] >= 256 and summary["seed"] == int(name[-1])
        assert summary["config"]["hyperparams"]["n_steps"] == 32  # the overrides reached the trial

    data = json.loads((out / "sweep.json").read_text())
    (point,) = data["points"]
    assert point["point"] == "cartpole_ppo" and point["seeds"] == [0, 1] and point["failed"] == point["not_run"] == 0
    returns = [json.loads((out / "runs" / n / "summary.json").read_text())["mean_return"] for n in runs]
    assert point["mean_return"] == pytest.approx(sum(returns) / 2)
    assert point["std_return"] == pytest.approx(abs(returns[0] - returns[1]) / 2)
    table = (out / "sweep.md").read_text()
    assert re.search(r"^\| cartpole_ppo \| 0,1 \| [0-9.]+ ± [0-9.]+ \| [0-2]/2 \|", table, re.M), table
    assert list((out / "tune").glob("*/events.out.tfevents.*")), "Tune's TensorBoard logs"
    if sweep.write_tensorboard(tmp_path / "tb_probe", []):  # tensorboard installed: the aggregate as hparams
        assert list((out / "tensorboard" / "cartpole_ppo").glob("events.out.tfevents.*"))

    before = _mtimes(out)
    capsys.readouterr()
    assert sweep.main(argv) == 0  # the same command again: restored, nothing retrained
    assert "resuming" in capsys.readouterr().err
    assert _mtimes(out) == before
    assert json.loads((out / "sweep.json").read_text())["points"][0]["seeds"] == [0, 1]


@pytest.mark.parametrize(
    "flag, value, message",
    [
        ("--grid", "hyperparams.learning_rate", "--grid 'hyperparams.learning_rate': expected key=v1,v2"),
        ("--grid", "hyperparams.learning_rate=1e-3,", "--grid 'hyperparams.learning_rate=1e-3,': expected non-empty"),
        ("--grid", "bad key=1,2", "--grid 'bad key=1,2': bad key 'bad key'"),
        ("--grid", "seed=1,2", "--grid 'seed=1,2': give seeds with --seeds"),
        ("--space", "hyperparams.learning_rate=lognormal:1:2", "unknown distribution 'lognormal'"),
        ("--space", "hyperparams.learning_rate=loguniform:0:1e-2", "loguniform needs LO:HI with LO < HI and LO > 0"),
        ("--space", "hyperparams.learning_rate=uniform:1e-2", "'hyperparams.learning_rate=uniform:1e-2': uniform"),
        ("--space", "hyperparams.n_epochs=randint:1.5:4", "randint needs integer bounds"),
        ("--space", "hyperparams.n_epochs=choice:", "choice needs values"),
        ("--seeds", "0,x", "--seeds '0,x': expected comma-separated integers"),
        ("--grid", "hyperparams.n_epochs=[1,2", "--grid 'hyperparams.n_epochs=[1,2': a value is not YAML"),
    ],
)
def test_bad_arguments_name_the_value(flag, value, message):
    with pytest.raises(ConfigError, match=re.escape(message)):
        args = sweep.parse_args(["cartpole_ppo", "--out", "unused", "--search", "optuna", flag, value])
        sweep.plan(args)


def test_grid_values_are_checked_against_the_config(tmp_path, capsys):
    """A grid value the config rejects stops the sweep before Ray starts, naming the key."""
    code = sweep.main(["cartpole_ppo", "--out", str(tmp_path), "--grid", "hyperparams.n_steps=32,many"])
    assert code == 2
    assert "hyperparams.n_steps" in capsys.readouterr().err
    assert not (tmp_path / "tune").exists()


def test_a_gpu_config_needs_a_gpu_share(tmp_path, capsys):
    """Ray schedules GPUs only for trials that ask: a cuda device without --gpus-per-trial is refused."""
    code = sweep.main(["cartpole_ppo", "--out", str(tmp_path), "--device", "cuda:0"])
    assert code == 2
    assert "device 'cuda:0': give --gpus-per-trial" in capsys.readouterr().err


def test_grid_parsing_keeps_lists_and_names_points():
    key, values = sweep.parse_grid("policy_kwargs.net_arch=[64,64],[128]")
    assert key == "policy_kwargs.net_arch" and values == [[64, 64], [128]]
    assert sweep.parse_grid("hyperparams.learning_rate=1e-3,3e-4")[1] == [1e-3, 3e-4]
    name = sweep.point_name({"policy_kwargs.net_arch": [64, 64], "hyperparams.learning_rate": 1e-3}, "x")
    assert name == "net_arch=64x64,learning_rate=0.001" or name == "learning_rate=0.001,net_arch=64x64"
    assert sweep.parse_space("hyperparams.n_epochs=randint:1:5") == ("hyperparams.n_epochs", ("randint", [1, 5]))


def test_aggregate_counts_solved_and_failed():
    rows = [
        {"point": "a", "seed": 0, "mean_return": 500.0, "solved": 1, "reward_threshold": 475.0, "wall_time_s": 2.0},
        {"point": "a", "seed": 1, "mean_return": 400.0, "solved": 0, "reward_threshold": 475.0, "wall_time_s": 4.0},
        {"point": "a", "seed": 2, "mean_return": None, "error": "RuntimeError('diverged')"},
        {"point": "a", "seed": 3, "mean_return": None},
    ]
    (p,) = sweep.aggregate(rows)
    assert p["seeds"] == [0, 1] and p["failed"] == 1 and p["not_run"] == 1 and p["solved"] == 1
    assert p["mean_return"] == 450.0 and p["std_return"] == 50.0 and p["wall_time_s_mean"] == 3.0
