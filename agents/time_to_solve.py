"""The time-to-solve table: each config trained for each seed, and how long it took to reach its
task's reward threshold.

    python -m abd_gym.agents.time_to_solve [CONFIG ...] --out DIR [--seeds 0,1,2]
        [--gpus-per-trial G] [--cpus-per-trial C] [--address auto|ray://HOST:PORT] [--num-cpus N] [--device D]
        [--doc docs/time_to_solve.md]

CONFIG defaults to every shipped GPU config (``configs/gpu/*.yaml``).  Each config's seeds run as
an ``abd-gym-sweep`` (Ray Tune: trials in parallel where the resources allow, one GPU each with
``--gpus-per-trial 1``; an interrupted table resumes) in ``DIR/<config>/``.  The time to the
threshold is that of the first periodic evaluation (the config's ``eval_freq``) whose mean return
reaches it: wall time from the start of training to the end of that evaluation, the periodic
evaluations' own time included.  The table (task ×
seed: device, envs, steps, time to the threshold and in total, final return, solved) goes to
``DIR/time_to_solve.md`` and ``.json``, and with ``--doc`` to that file too.
"""
from __future__ import annotations

import argparse
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
    p.add_argument("--doc", help="also write the table to this Markdown file")
    return p.parse_args(argv)


def _sweep_args(args: argparse.Namespace, config: str) -> argparse.Namespace:
    argv = [config, "--out", str(Path(args.out) / config.replace("/", "_")), "--seeds", args.seeds,
            "--gpus-per-trial", str(args.gpus_per_trial), "--cpus-per-trial", str(args.cpus_per_trial)]  # fmt: skip
    for flag, value in (("--address", args.address), ("--num-cpus", args.num_cpus), ("--device", args.device),
                        ("--total-timesteps", args.total_timesteps)):
        if value is not None:
            argv += [flag, str(value)]
    return sweep.parse_args(argv)


def collect(config: str, rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One table row per trial, from the trial's ``summary.json`` (a trial without one: failed)."""
    out = []
    for row in sorted(rows, key=lambda r: r["seed"]):
        summary_path = Path(row.get("run_dir") or "") / "summary.json"
        if not row.get("run_dir") or not summary_path.is_file():
            out.append(dict(config=config, seed=row["seed"], failed=True, error=row.get("error")))
            continue
        s = json.loads(summary_path.read_text())
        out.append(dict(config=config, env_id=s["env_id"], algo=s["algo"], seed=s["seed"], failed=False,
                        device=s["device_description"], n_envs=s["n_envs"], timesteps=s["timesteps"],
                        threshold_step=s.get("threshold_step"), threshold_time_s=s.get("threshold_time_s"),
                        wall_time_s=s["wall_time_s"], mean_return=s["mean_return"], std_return=s["std_return"],
                        reward_threshold=s["reward_threshold"], solved=bool(s["solved"]),
                        run_dir=str(summary_path.parent)))  # fmt: skip
    return out


def markdown(rows: list[dict[str, Any]], command: str, date: str) -> str:
    """The table: one row per trial, then each config's solved count."""

    def num(x, fmt):
        return "—" if x is None else format(x, fmt)

    lines = ["# Time to solve", "",
             f"`{command}`, {date}. Time to the threshold: wall time from the start of training to the end "
             "of the first periodic evaluation whose mean return reaches the task's threshold (the periodic "
             "evaluations' own time included); total: the whole run. Final return: the deterministic policy "
             "after training.", "",
             "| task | config | seed | device | envs | steps | steps to threshold | time to threshold [s] "
             "| total time [s] | final return | threshold | solved |",
             "|---|---|---:|---|---:|---:|---:|---:|---:|---|---:|---|"]  # fmt: skip
    for r in rows:
        if r["failed"]:
            lines.append(f"| — | {r['config']} | {r['seed']} | failed: {r.get('error') or 'no summary'} "
                         "| | | | | | | | no |")  # fmt: skip
            continue
        lines.append(f"| {r['env_id']} | {r['config']} ({r['algo']}) | {r['seed']} | {r['device']} | {r['n_envs']:,} "
                     f"| {r['timesteps']:,} | {num(r['threshold_step'], ',')} | {num(r['threshold_time_s'], '.1f')} "
                     f"| {r['wall_time_s']:.1f} | {r['mean_return']:.1f} ± {r['std_return']:.1f} "
                     f"| {r['reward_threshold']:g} | {'yes' if r['solved'] else 'no'} |")  # fmt: skip
    lines += ["", "| config | solved | slowest time to threshold [s] |", "|---|---:|---:|"]
    for config in dict.fromkeys(r["config"] for r in rows):
        mine = [r for r in rows if r["config"] == config]
        solved = [r for r in mine if not r["failed"] and r["solved"]]
        times = [r["threshold_time_s"] for r in mine if not r["failed"]]
        slowest = "—" if not times or None in times else f"{max(times):.1f}"
        lines.append(f"| {config} | {len(solved)}/{len(mine)} | {slowest} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    configs = args.configs or gpu_configs()
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
    command = "python -m abd_gym.agents.time_to_solve " + shlex.join(argv if argv is not None else sys.argv[1:])
    table = markdown(rows, command, time.strftime("%Y-%m-%d"))
    out = Path(args.out)
    (out / "time_to_solve.md").write_text(table)
    (out / "time_to_solve.json").write_text(json.dumps({"command": command, "rows": rows}, indent=2) + "\n")
    if args.doc:
        Path(args.doc).write_text(table)
    print(table)
    return 0 if all(not r["failed"] and r["solved"] for r in rows) else 1


if __name__ == "__main__":
    try:
        sys.exit(main())
    except ConfigError as exc:
        print(f"time_to_solve: error: {exc}", file=sys.stderr)
        sys.exit(2)
