"""The time-to-solve table: each config trained for each seed, and how long it took to reach its
task's reward threshold.

    python -m abd_gym.agents.time_to_solve [CONFIG ...] --out DIR [--seeds 0,1,2]
        [--gpus-per-trial G] [--cpus-per-trial C] [--address auto|ray://HOST:PORT] [--num-cpus N] [--device D]
        [--set KEY=VALUE ...] [--serial [--warmup]] [--doc docs/time_to_solve.md]

CONFIG defaults to every shipped GPU config (``configs/gpu/*.yaml``).  Each config's seeds run as
an ``abd-gym-sweep`` (Ray Tune: trials in parallel where the resources allow, one GPU each with
``--gpus-per-trial 1``; an interrupted table resumes) in ``DIR/<config>/``.  The time to the
threshold is that of the first periodic evaluation (the config's ``eval_freq``) whose mean return
reaches it: wall time from the start of training to the end of that evaluation, the periodic
evaluations' own time included.  The table (task ×
seed: device, envs, steps, time to the threshold and in total, the step at which a
``stop_when_solved`` config stopped, final return, the best model's return on the same episodes,
solved) goes to ``DIR/time_to_solve.md`` and ``.json``, and with ``--doc`` to that file too.

``--serial`` runs the trials in this process one after another, without Ray: seed by seed, every
config for a seed before the next seed, the table rewritten after each trial (an interrupted
table keeps the trials that finished; it does not resume).  ``--warmup`` first trains each config
for one evaluation interval (its ``eval_freq``, else 20,000 steps) into ``DIR/warmup/``, so that
no trial's time includes compiling the env's kernels.
"""
from __future__ import annotations

import argparse
import gc
import json
import shlex
import sys
import time
from pathlib import Path
from typing import Any

from abd_gym.agents import sweep
from abd_gym.agents.config import CONFIG_DIR, ConfigError

__all__ = ["main", "gpu_configs", "collect", "markdown"]


def gpu_configs() -> list[str]:
    """The shipped GPU configs, as names abd-gym-train resolves (``gpu/cartpole_ppo``)."""
    return [f"gpu/{p.stem}" for p in sorted((CONFIG_DIR / "gpu").glob("*.yaml"))]


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m abd_gym.agents.time_to_solve", description=__doc__.split("\n\n")[0])
    p.add_argument("configs", nargs="*", help="configs (default: every configs/gpu/*.yaml)")
    p.add_argument("--out", required=True, help="folder of the sweeps and the table")
    p.add_argument("--seeds", default="0,1,2", help="comma-separated seeds (default 0,1,2)")
    p.add_argument("--gpus-per-trial", type=float, default=0.0, help="GPUs per trial (1: a GPU each)")
    p.add_argument("--cpus-per-trial", type=float, default=1.0)
    p.add_argument("--address", help="Ray cluster to join (default: start Ray here)")
    p.add_argument("--num-cpus", type=int, help="CPUs of the local Ray instance (default: all)")
    p.add_argument("--device", help="cpu, to run the GPU configs without a GPU")
    p.add_argument("--total-timesteps", type=float, help="environment steps per trial (default: each config's)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="overrides",
                   help="a config override for every config (abd-gym-train's key=value; repeatable)")
    p.add_argument("--serial", action="store_true", help="trials one after another in this process, without Ray")
    p.add_argument("--warmup", action="store_true", help="with --serial: a short run of each config first")
    p.add_argument("--doc", help="also write the table to this Markdown file")
    args = p.parse_args(argv)
    if args.warmup and not args.serial:
        p.error("--warmup needs --serial")
    return args


def _sweep_args(args: argparse.Namespace, config: str) -> argparse.Namespace:
    argv = [config, "--out", str(Path(args.out) / config.replace("/", "_")), "--seeds", args.seeds,
            "--gpus-per-trial", str(args.gpus_per_trial), "--cpus-per-trial", str(args.cpus_per_trial)]  # fmt: skip
    for flag, value in (("--address", args.address), ("--num-cpus", args.num_cpus), ("--device", args.device),
                        ("--total-timesteps", args.total_timesteps)):
        if value is not None:
            argv += [flag, str(value)]
    return sweep.parse_args(argv[:1] + list(args.overrides) + argv[1:])


def collect(config: str, rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One table row per trial, from the trial's ``summary.json`` (a trial without one: failed)."""
    out = []
    for row in sorted(rows, key=lambda r: r["seed"]):
        summary_path = Path(row.get("run_dir") or "") / "summary.json"
        if not row.get("run_dir") or not summary_path.is_file():
            out.append(dict(config=config, seed=row["seed"], failed=True, error=row.get("error")))
            continue
        out.append(row_from_summary(config, summary_path))
    return out


def row_from_summary(config: str, summary_path: Path) -> dict[str, Any]:
    """A trial's table row from its ``summary.json``.  ``best_return`` / ``best_std``: the best
    model's score on the final evaluation's episodes (the final return where the best model is
    the final policy; None where the run kept no best model)."""
    s = json.loads(Path(summary_path).read_text())
    best = s.get("best_model") or {}
    if best.get("same_as_final"):
        best_return, best_std = s["mean_return"], s["std_return"]
    else:
        best_return, best_std = best.get("mean_return"), best.get("std_return")
    return dict(config=config, env_id=s["env_id"], algo=s["algo"], seed=s["seed"], failed=False,
                device=s["device_description"], n_envs=s["n_envs"], timesteps=s["timesteps"],
                threshold_step=s.get("threshold_step"), threshold_time_s=s.get("threshold_time_s"),
                stopped_step=s.get("stopped_step"), wall_time_s=s["wall_time_s"], mean_return=s["mean_return"],
                std_return=s["std_return"], eval_episodes=s.get("eval_episodes"), best_return=best_return,
                best_std=best_std, best_step=best.get("step"), final_below_best=bool(s.get("final_below_best")),
                reward_threshold=s["reward_threshold"], solved=bool(s["solved"]),
                periodic_eval_time_s=s.get("periodic_eval_time_s"), run_dir=str(Path(summary_path).parent))  # fmt: skip


def markdown(rows: list[dict[str, Any]], command: str, date: str) -> str:
    """The table: one row per trial, then each config's solved count."""

    def num(x, fmt):
        return "—" if x is None else format(x, fmt)

    def best(r):
        if r.get("best_return") is None:
            return "—"
        flag = " (final below)" if r.get("final_below_best") else ""
        return f"{r['best_return']:.1f} ± {r['best_std']:.1f}{flag}"

    lines = ["# Time to solve", "",
             f"`{command}`, {date}. Time to the threshold: wall time from the start of training to the end "
             "of the first periodic evaluation whose mean return reaches the task's threshold (the periodic "
             "evaluations' own time included); total: the whole run. Stopped at: the step at which a "
             "`stop_when_solved` config ended training. Final return: the deterministic policy after "
             "training; best model: best_model.zip on the same episodes.", "",
             "| task | config | seed | device | envs | steps | steps to threshold | time to threshold [s] "
             "| stopped at | total time [s] | final return | best model | threshold | solved |",
             "|---|---|---:|---|---:|---:|---:|---:|---:|---:|---|---|---:|---|"]  # fmt: skip
    for r in rows:
        if r["failed"]:
            lines.append(f"| — | {r['config']} | {r['seed']} | failed: {r.get('error') or 'no summary'} "
                         "| | | | | | | | | | no |")  # fmt: skip
            continue
        lines.append(f"| {r['env_id']} | {r['config']} ({r['algo']}) | {r['seed']} | {r['device']} | {r['n_envs']:,} "
                     f"| {r['timesteps']:,} | {num(r['threshold_step'], ',')} | {num(r['threshold_time_s'], '.1f')} "
                     f"| {num(r.get('stopped_step'), ',')} | {r['wall_time_s']:.1f} "
                     f"| {r['mean_return']:.1f} ± {r['std_return']:.1f} | {best(r)} "
                     f"| {r['reward_threshold']:g} | {'yes' if r['solved'] else 'no'} |")  # fmt: skip
    lines += ["", "| config | solved | slowest time to threshold [s] | final below best |", "|---|---:|---:|---:|"]
    for config in dict.fromkeys(r["config"] for r in rows):
        mine = [r for r in rows if r["config"] == config]
        solved = [r for r in mine if not r["failed"] and r["solved"]]
        times = [r["threshold_time_s"] for r in mine if not r["failed"]]
        slowest = "—" if not times or None in times else f"{max(times):.1f}"
        below = sum(bool(r.get("final_below_best")) for r in mine)
        lines.append(f"| {config} | {len(solved)}/{len(mine)} | {slowest} | {below}/{len(mine)} |")
    return "\n".join(lines) + "\n"


def _raw_configs(args: argparse.Namespace, configs: list[str]) -> list[tuple[str, dict[str, Any], str]]:
    """(config, raw config after the flags, its run name) for each config, each checked."""
    from abd_gym.agents.config import validate_config
    from abd_gym.agents.train import raw_config_from_args

    out = []
    seeds = sweep.parse_seeds(args.seeds)
    for config in configs:
        raw, name = raw_config_from_args(_sweep_args(args, config))
        for seed in seeds:
            validate_config({**raw, "seed": seed})
        out.append((config, raw, name))
    return out


def _write(out: Path, rows: list[dict[str, Any]], command: str, doc: str | None) -> str:
    rows = sorted(rows, key=lambda r: (r["config"], r["seed"]))
    table = markdown(rows, command, time.strftime("%Y-%m-%d"))
    out.mkdir(parents=True, exist_ok=True)
    (out / "time_to_solve.md").write_text(table)
    (out / "time_to_solve.json").write_text(json.dumps({"command": command, "rows": rows}, indent=2) + "\n")
    if doc:
        Path(doc).write_text(table)
    return table


def run_serial(args: argparse.Namespace, configs: list[str], command: str) -> list[dict[str, Any]]:
    """Every config for each seed in turn, in this process; the table rewritten after each trial."""
    from abd_gym.agents.config import validate_config
    from abd_gym.agents.train import train

    plans = _raw_configs(args, configs)
    seeds = sweep.parse_seeds(args.seeds)
    out = Path(args.out)
    if args.warmup:
        for config, raw, name in plans:
            cfg = validate_config(raw)
            cfg["n_timesteps"] = cfg["eval_freq"] or 20_000
            train(cfg, config_name=name, run_dir=out / "warmup" / name, progress_bar=False, command="warmup")
    rows: list[dict[str, Any]] = []
    for seed in seeds:
        for config, raw, name in plans:
            run_dir = out / name / "runs" / f"{name}-seed{seed}"
            try:
                train(validate_config({**raw, "seed": seed}), config_name=name, run_dir=run_dir, progress_bar=False,
                      command=command)  # fmt: skip
                rows.append(row_from_summary(config, run_dir / "summary.json"))
            except Exception as exc:  # noqa: BLE001 -- one failed trial is a row of the table, not the end of it
                rows.append(dict(config=config, seed=seed, failed=True, error=f"{type(exc).__name__}: {exc}"[:300]))
            gc.collect()  # the trial's envs, model and graphs go before the next trial's are made
            _write(out, rows, command, None)
    return rows


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    configs = args.configs or gpu_configs()
    command = "python -m abd_gym.agents.time_to_solve " + shlex.join(argv if argv is not None else sys.argv[1:])
    if args.serial:
        try:
            _raw_configs(args, configs)
        except (ValueError, FileNotFoundError) as exc:
            print(f"time_to_solve: error: {exc}", file=sys.stderr)
            return 2
        rows = run_serial(args, configs, command)
        print(_write(Path(args.out), rows, command, args.doc))
        return 0 if all(not r["failed"] and r["solved"] for r in rows) else 1
    try:
        plans = [(c, _sweep_args(args, c)) for c in configs]
        plans = [(c, a, sweep.plan(a)) for c, a in plans]  # every config checked before Ray starts
    except (ValueError, FileNotFoundError) as exc:
        print(f"time_to_solve: error: {exc}", file=sys.stderr)
        return 2
    started = sweep._init_ray(plans[0][1])
    rows: list[dict[str, Any]] = []
    try:
        for config, sargs, the_plan in plans:
            results, _ = sweep.sweep(sargs, the_plan)
            rows += collect(config, sweep._rows(results))
    finally:
        if started:
            import ray

            ray.shutdown()
    print(_write(Path(args.out), rows, command, args.doc))
    return 0 if all(not r["failed"] and r["solved"] for r in rows) else 1


if __name__ == "__main__":
    try:
        sys.exit(main())
    except ConfigError as exc:
        print(f"time_to_solve: error: {exc}", file=sys.stderr)
        sys.exit(2)
