"""Seeds and hyperparameter sweeps of ``train()`` on Ray Tune, locally or on a Ray cluster.

    abd-gym-sweep CONFIG --out DIR [--seeds 0,1,2] [--grid key=v1,v2 ...]
        [--samples N --search optuna --space key=loguniform:1e-4:1e-2 ...]
        [--gpus-per-trial G] [--cpus-per-trial C] [--address auto|ray://HOST:PORT] [--num-cpus N]
        [--total-timesteps N] [--num-envs N] [--device D] [--eval-episodes E] [key=value ...]

(also ``python -m abd_gym.agents.sweep``).  Each trial is ``abd_gym.agents.train.train()`` on the
config after the ``key=value`` overrides, its grid point (or sampled point) and its seed, all
applied as abd-gym-train's dotted-key overrides; it writes its own run directory
``DIR/runs/<point>-seed<k>/``.  With ``--gpus-per-trial`` Ray gives each trial its share of a GPU
and sets ``CUDA_VISIBLE_DEVICES``, so the trial trains on ``cuda:0``.  Without ``--address`` Ray
starts on this machine; with one it joins a running cluster.

Tune's experiment lives in ``DIR/tune/`` (its TensorBoard logs included); the same command on the
same ``DIR`` restores it and runs only the trials that have not finished.  At the end the trials
are aggregated per point over seeds (mean ± std of the final return, solved count, training wall
time) into ``DIR/sweep.md`` and ``DIR/sweep.json``, printed, and written as TensorBoard hparams
to ``DIR/tensorboard/``.
"""
from __future__ import annotations

import argparse
import itertools
import json
import math
import re
import sys
from pathlib import Path
from typing import Any

from abd_gym.agents.config import ConfigError, apply_overrides, validate_config, yaml_load

__all__ = ["main", "parse_args", "parse_grid", "parse_space", "parse_seeds", "aggregate", "sweep"]

EXPERIMENT = "tune"  # Tune's experiment folder under --out
SEED_KEY = "seed"
DISTRIBUTIONS = ("uniform", "loguniform", "randint", "lograndint", "choice")


# ---------------------------------------------------------------------------------------------
# arguments


def _split_values(text: str) -> list[str]:
    """Split at commas outside brackets, so ``[64,64],[128,128]`` is two values."""
    parts, depth, cur = [], 0, ""
    for ch in text:
        if ch in "[{":
            depth += 1
        elif ch in "]}":
            depth -= 1
        if ch == "," and depth == 0:
            parts.append(cur)
            cur = ""
        else:
            cur += ch
    parts.append(cur)
    return parts


def _key(text: str, flag: str, key: str) -> str:
    if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*", key):
        raise ConfigError(f"{flag} {text!r}: bad key {key!r} (expected a dotted config key)")
    return key


def parse_seeds(text: str) -> list[int]:
    """``0,1,2`` -> [0, 1, 2]."""
    try:
        seeds = [int(s) for s in text.split(",")]
    except ValueError:
        raise ConfigError(f"--seeds {text!r}: expected comma-separated integers like 0,1,2") from None
    if len(set(seeds)) != len(seeds):
        raise ConfigError(f"--seeds {text!r}: a seed is repeated")
    return seeds


def parse_grid(text: str) -> tuple[str, list[Any]]:
    """``key=v1,v2`` -> (key, [v1, v2]) with YAML values (commas inside brackets stay)."""
    if "=" not in text:
        raise ConfigError(f"--grid {text!r}: expected key=v1,v2,...")
    key, values = text.split("=", 1)
    key = _key(text, "--grid", key.strip())
    raw = _split_values(values)
    if not values.strip() or any(not v.strip() for v in raw):
        raise ConfigError(f"--grid {text!r}: expected non-empty values key=v1,v2,...")
    try:
        parsed = [yaml_load(v) for v in raw]
    except Exception as exc:  # noqa: BLE001 -- yaml's errors are several types
        raise ConfigError(f"--grid {text!r}: a value is not YAML ({exc})") from None
    if key == SEED_KEY:
        raise ConfigError(f"--grid {text!r}: give seeds with --seeds")
    return key, parsed


def parse_space(text: str) -> tuple[str, tuple[str, list[Any]]]:
    """``key=loguniform:1e-4:1e-2`` -> (key, ("loguniform", [1e-4, 1e-2])).

    Distributions: ``uniform:LO:HI``, ``loguniform:LO:HI``, ``randint:LO:HI`` (HI excluded),
    ``lograndint:LO:HI``, ``choice:V1,V2,...``.
    """
    if "=" not in text:
        raise ConfigError(f"--space {text!r}: expected key=DIST:ARGS, e.g. lr=loguniform:1e-4:1e-2")
    key, spec = text.split("=", 1)
    key = _key(text, "--space", key.strip())
    dist, _, rest = spec.partition(":")
    if dist not in DISTRIBUTIONS:
        raise ConfigError(f"--space {text!r}: unknown distribution {dist!r}; known: {', '.join(DISTRIBUTIONS)}")
    if dist == "choice":
        values = [yaml_load(v) for v in _split_values(rest)] if rest.strip() else []
        if not values:
            raise ConfigError(f"--space {text!r}: choice needs values, e.g. choice:32,64")
        return key, (dist, values)
    bounds = rest.split(":")
    try:
        lo, hi = (float(b) for b in bounds) if len(bounds) == 2 else (None, None)
    except ValueError:
        lo = hi = None
    if lo is None or not lo < hi or (dist.startswith("log") and lo <= 0):
        raise ConfigError(f"--space {text!r}: {dist} needs LO:HI with LO < HI" + (" and LO > 0" if "log" in dist else ""))
    if dist.endswith("randint"):
        if not (lo.is_integer() and hi.is_integer()):
            raise ConfigError(f"--space {text!r}: {dist} needs integer bounds")
        lo, hi = int(lo), int(hi)
    return key, (dist, [lo, hi])


def _tune_domain(dist: str, args: list[Any]):
    from ray import tune

    return tune.choice(args) if dist == "choice" else getattr(tune, dist)(*args)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="abd-gym-sweep", description=__doc__.split("\n\n")[0])
    p.add_argument("config", help="config file, or a name in configs/ (cartpole_ppo)")
    p.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides for every trial")
    p.add_argument("--out", required=True, help="sweep folder (run directories, Tune's experiment, sweep.md/json)")
    p.add_argument("--seeds", help="comma-separated seeds, each trained at every point (default: the config's seed)")
    p.add_argument("--grid", action="append", default=[], metavar="KEY=V1,V2", help="a grid axis (repeatable)")
    p.add_argument("--search", choices=("grid", "optuna"), default="grid", help="grid (default) or optuna")
    p.add_argument("--samples", type=int, default=1, help="points sampled from --space (optuna)")
    p.add_argument("--space", action="append", default=[], metavar="KEY=DIST:ARGS", help="a search dimension (optuna)")
    p.add_argument("--metric", default="mean_return", help="what optuna maximises (default mean_return)")
    p.add_argument("--gpus-per-trial", type=float, default=0.0, help="GPUs per trial (a fraction shares one)")
    p.add_argument("--cpus-per-trial", type=float, default=1.0, help="CPUs per trial")
    p.add_argument("--max-concurrent", type=int, default=0, help="trials at once (0: as many as resources allow)")
    p.add_argument("--address", help="Ray cluster to join: auto, or ray://HOST:PORT (default: start Ray here)")
    p.add_argument("--num-cpus", type=int, help="CPUs of the local Ray instance (default: all)")
    p.add_argument("--device", help="cpu or cuda:N when Ray assigns no GPU (default: the config's)")
    p.add_argument("--num-envs", type=int, help="worlds in the training env (n_envs)")
    p.add_argument("--total-timesteps", type=float, help="environment steps per trial (n_timesteps)")
    p.add_argument("--eval-episodes", type=int)
    return p.parse_intermixed_args(argv)


# ---------------------------------------------------------------------------------------------
# the plan: base config, points and their names


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, list) and all(isinstance(v, (int, float, str)) for v in value):
        return "x".join(_fmt(v) for v in value)  # net_arch [64, 64] -> 64x64
    return json.dumps(value, separators=(",", ":")) if isinstance(value, dict) else str(value)


def point_name(point: dict[str, Any], default: str) -> str:
    """A folder-safe name of a point: ``learning_rate=0.001,n_steps=64`` (last key part only)."""
    if not point:
        return default
    text = ",".join(f"{k.rsplit('.', 1)[-1]}={_fmt(v)}" for k, v in sorted(point.items()))
    return re.sub(r"[^A-Za-z0-9_.,=+-]", "_", text)


def plan(args: argparse.Namespace) -> dict[str, Any]:
    """Everything the sweep needs, checked before Ray starts: a bad value fails here, named."""
    from abd_gym.agents.train import raw_config_from_args  # the config as abd-gym-train reads it, before point and seed

    raw, name = raw_config_from_args(args)
    seeds = parse_seeds(args.seeds) if args.seeds else [int(validate_config(raw)["seed"])]
    grid = dict(parse_grid(g) for g in args.grid)
    space = dict(parse_space(s) for s in args.space)
    for flag, given, kept in (("--grid", args.grid, grid), ("--space", args.space, space)):
        if len(kept) < len(given):
            raise ConfigError(f"{flag}: a key is given twice ({', '.join(given)})")
    if args.search == "optuna":
        if not space:
            raise ConfigError("--search optuna: give the search space with --space key=DIST:ARGS")
        if args.samples < 1:
            raise ConfigError(f"--samples {args.samples}: must be at least 1")
        if grid:
            raise ConfigError("--grid: not with --search optuna (use --space key=choice:v1,v2)")
    elif space:
        raise ConfigError("--space: needs --search optuna")
    # every grid point and seed must make a valid config (the searched dimensions: their bounds)
    names = set()
    for values in itertools.product(*grid.values()):
        point = dict(zip(grid, values))
        validate_config(apply_overrides(raw, {**point, SEED_KEY: seeds[0]}))
        names.add(point_name(point, name))
    if len(names) < math.prod(len(v) for v in grid.values()):  # run folders are named by the last key part
        raise ConfigError(f"--grid: two points share a run folder name; keys end alike ({', '.join(grid)})")
    for key, (dist, vals) in space.items():
        for v in vals if dist == "choice" else vals[:1]:
            validate_config(apply_overrides(raw, {key: v}))
    device = validate_config(raw)["device"]
    if args.gpus_per_trial == 0 and device.startswith("cuda"):
        # Ray schedules GPUs only for trials that ask for them: without a share, trials would
        # all land on one GPU, or on none
        raise ConfigError(f"device {device!r}: give --gpus-per-trial (1, or a fraction such as 0.5), or --device cpu")
    if args.gpus_per_trial < 0 or args.cpus_per_trial <= 0:
        raise ConfigError("--gpus-per-trial must be >= 0 and --cpus-per-trial > 0")
    return {"raw": raw, "name": name, "seeds": seeds, "grid": grid, "space": space}


# ---------------------------------------------------------------------------------------------
# the trial


def run_trial(params: dict[str, Any], *, raw: dict[str, Any], name: str, out: str, gpus: float) -> None:
    """One training: the point's and the seed's overrides on ``raw``; reports the summary to Tune."""
    from ray import tune

    from abd_gym.agents.train import train

    point = {k: v for k, v in params.items() if k != SEED_KEY}
    seed = int(params[SEED_KEY])
    cfg = apply_overrides(raw, {**point, SEED_KEY: seed})
    if gpus > 0:
        cfg["device"] = "cuda:0"  # Ray set CUDA_VISIBLE_DEVICES to this trial's GPU
    label = point_name(point, name)
    run_dir = Path(out) / "runs" / f"{label}-seed{seed}"
    summary = train(cfg, config_name=name, run_dir=run_dir, progress_bar=False, command="abd-gym-sweep")
    tune.report(
        {
            "point": label,
            "seed": seed,
            "mean_return": summary["mean_return"],
            "std_return": summary["std_return"],
            "solved": int(summary["solved"]),
            "reward_threshold": summary["reward_threshold"],
            "wall_time_s": summary["wall_time_s"],
            "timesteps": summary["timesteps"],
            "run_dir": str(run_dir),
        }
    )


# ---------------------------------------------------------------------------------------------
# aggregation


def aggregate(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per point over its seeds: mean ± std (population) of the final return, solved count, wall time.

    A row without ``mean_return`` is a trial that raised (``error``) or has not run yet."""
    points: dict[str, list[dict[str, Any]]] = {}
    for row in rows:
        points.setdefault(row["point"], []).append(row)
    out = []
    for label, group in points.items():
        done = [r for r in group if r.get("mean_return") is not None]
        returns = [float(r["mean_return"]) for r in done]
        walls = [float(r["wall_time_s"]) for r in done]
        mean = sum(returns) / len(returns) if returns else None
        std = math.sqrt(sum((x - mean) ** 2 for x in returns) / len(returns)) if returns else None
        out.append(
            {
                "point": label,
                "params": group[0].get("params", {}),
                "seeds": sorted(int(r["seed"]) for r in done),
                "failed": sum(1 for r in group if r.get("mean_return") is None and r.get("error")),
                "not_run": sum(1 for r in group if r.get("mean_return") is None and not r.get("error")),
                "mean_return": mean,
                "std_return": std,
                "solved": sum(int(r["solved"]) for r in done),
                "reward_threshold": next((r.get("reward_threshold") for r in done), None),
                "wall_time_s_mean": sum(walls) / len(walls) if walls else None,
                "wall_time_s_max": max(walls) if walls else None,
                "returns": returns,
            }
        )
    return sorted(out, key=lambda p: -math.inf if p["mean_return"] is None else -p["mean_return"])


def markdown(points: list[dict[str, Any]], title: str) -> str:
    """The aggregate as a Markdown table (best point first)."""

    def num(x: float | None, fmt: str = ".2f") -> str:
        return "—" if x is None else format(x, fmt)

    lines = [
        f"# Sweep: {title}",
        "",
        "Final return: the deterministic policy's mean return after training, averaged over seeds "
        "(± population std over seeds). Wall time: training time to the end of the run, per trial "
        "(no periodic evaluation, so no time to the threshold).",
        "",
        "| point | seeds | return (mean ± std) | solved | wall time / trial (s) | failed | not run |",
        "|---|---|---|---|---|---|---|",
    ]
    for p in points:
        solved = f"{p['solved']}/{len(p['seeds'])}" if p["reward_threshold"] is not None else "no threshold"
        lines.append(
            f"| {p['point']} | {','.join(map(str, p['seeds']))} | {num(p['mean_return'])} ± {num(p['std_return'])} "
            f"| {solved} | {num(p['wall_time_s_mean'], '.1f')} | {p['failed']} | {p['not_run']} |"
        )
    return "\n".join(lines) + "\n"


def write_tensorboard(folder: Path, points: list[dict[str, Any]]) -> bool:
    """The aggregate as TensorBoard hparams: one run per point, its parameters against its
    ``sweep/mean_return``, ``sweep/std_return``, ``sweep/solved`` and ``sweep/wall_time_s``.
    False when tensorboard is not installed."""
    import importlib.util
    import shutil

    if importlib.util.find_spec("tensorboard") is None:
        return False
    from torch.utils.tensorboard import SummaryWriter

    shutil.rmtree(folder, ignore_errors=True)  # rewritten whole, as sweep.md is
    with SummaryWriter(str(folder)) as writer:
        for p in points:
            if p["mean_return"] is None:
                continue
            hparams = {k: v if isinstance(v, (int, float, str, bool)) else _fmt(v) for k, v in p["params"].items()}
            metrics = {
                "sweep/mean_return": p["mean_return"],
                "sweep/std_return": p["std_return"],
                "sweep/solved": p["solved"],
                "sweep/wall_time_s": p["wall_time_s_mean"],
            }
            writer.add_hparams(hparams or {"config": p["point"]}, metrics, run_name=p["point"])
    return True


def _rows(results) -> list[dict[str, Any]]:
    rows = []
    for result in results:
        params = dict(result.config or {})
        metrics = result.metrics or {}
        point = {k: v for k, v in params.items() if k != SEED_KEY}
        row = {"point": metrics.get("point"), "seed": params.get(SEED_KEY), "params": point}
        if result.error is None and "mean_return" in metrics:
            row.update({k: metrics[k] for k in ("mean_return", "solved", "reward_threshold", "wall_time_s")})
            row["run_dir"] = metrics.get("run_dir")
        else:
            row["mean_return"] = None
            if result.error is not None:
                row["error"] = str(result.error)[:500]
        rows.append(row)
    return rows


def write_outputs(out: Path, rows: list[dict[str, Any]], title: str, name: str) -> tuple[str, list[dict[str, Any]]]:
    for row in rows:
        if row["point"] is None:  # a trial that failed before reporting: name it from its params
            row["point"] = point_name(row["params"], name)
    points = aggregate(rows)
    table = markdown(points, title)
    (out / "sweep.md").write_text(table)
    (out / "sweep.json").write_text(json.dumps({"config": name, "points": points, "trials": rows}, indent=2) + "\n")
    write_tensorboard(out / "tensorboard", points)
    return table, points


# ---------------------------------------------------------------------------------------------
# the sweep


def _init_ray(args: argparse.Namespace) -> bool:
    """Start or join Ray; True when this call started it (and should shut it down)."""
    import ray

    if ray.is_initialized():
        return False
    if args.address:
        ray.init(address=args.address)
    else:
        ray.init(num_cpus=args.num_cpus, include_dashboard=False)
    return True


def sweep(args: argparse.Namespace, the_plan: dict[str, Any]) -> tuple[Any, Path]:
    """Run (or resume) the Tune experiment; return its ResultGrid and the experiment path."""
    from ray import tune

    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    trainable = tune.with_resources(
        tune.with_parameters(
            run_trial, raw=the_plan["raw"], name=the_plan["name"], out=str(out), gpus=args.gpus_per_trial
        ),
        {"cpu": args.cpus_per_trial, "gpu": args.gpus_per_trial},
    )
    path = out / EXPERIMENT
    if tune.Tuner.can_restore(str(path)):
        print(f"abd-gym-sweep: resuming {path}", file=sys.stderr)
        tuner = tune.Tuner.restore(str(path), trainable=trainable, resume_errored=True)
        return tuner.fit(), path

    seeds = the_plan["seeds"]
    if args.search == "optuna":
        from ray.tune.search.optuna import OptunaSearch

        space = {k: _tune_domain(d, v) for k, (d, v) in the_plan["space"].items()}
        space[SEED_KEY] = tune.choice(seeds) if len(seeds) > 1 else seeds[0]
        tune_config = tune.TuneConfig(
            search_alg=OptunaSearch(metric=args.metric, mode="max"),
            num_samples=args.samples,
            max_concurrent_trials=args.max_concurrent or None,
        )
    else:
        space = {k: tune.grid_search(v) for k, v in the_plan["grid"].items()}
        space[SEED_KEY] = tune.grid_search(seeds)
        tune_config = tune.TuneConfig(num_samples=1, max_concurrent_trials=args.max_concurrent or None)
    tuner = tune.Tuner(
        trainable,
        param_space=space,
        tune_config=tune_config,
        run_config=tune.RunConfig(name=EXPERIMENT, storage_path=str(out), verbose=1),
    )
    return tuner.fit(), path


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        the_plan = plan(args)
    except (ValueError, FileNotFoundError) as exc:
        print(f"abd-gym-sweep: error: {exc}", file=sys.stderr)
        return 2
    started = _init_ray(args)
    try:
        results, path = sweep(args, the_plan)
        rows = _rows(results)
    finally:
        if started:
            import ray

            ray.shutdown()
    out = Path(args.out).resolve()
    table, points = write_outputs(out, rows, the_plan["name"], the_plan["name"])
    print(table)
    print(f"sweep: {out / 'sweep.md'}, {out / 'sweep.json'}; TensorBoard: tensorboard --logdir {out}")
    if any(p["not_run"] for p in points):
        print("abd-gym-sweep: some trials did not run; the same command resumes the sweep", file=sys.stderr)
    return 0 if all(p["failed"] == 0 and p["not_run"] == 0 for p in points) else 1


if __name__ == "__main__":
    sys.exit(main())
