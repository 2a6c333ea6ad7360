#!/usr/bin/env python3
"""An evaluation's wall time on SB3's path and on the device, for saved runs.

    python scripts/eval_times.py RUN_DIR [RUN_DIR ...] [--device cuda:0] [--episodes N]
        [--repeat 3] [--json PATH]

For each run (a directory ``abd-gym-train`` wrote), loads its model and observation statistics as
``abd-gym-evaluate`` does and builds its eval env twice, with the config's eval seed: SB3's (NumPy,
SAME_STEP autoreset, ``evaluate_policy``) and the device's (Torch backend, NEXT_STEP,
:class:`~abd_gym.agents.device_eval.DeviceEvaluator`).  Each path evaluates ``--episodes``
(default: the config's ``eval_episodes``) once untimed (compiles and captures), then
``--repeat`` times, alternating the paths.  Prints one row per run: the best wall time of each
path, their ratio, and the mean return and episode length of each path's untimed evaluation (from the seeded reset; with
one episode a world both paths play the same episodes).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from abd_gym.agents.common import EVAL_SEED_OFFSET, build_eval_env, episode_evaluator, eval_env_count
from abd_gym.agents.evaluate import load_run

PATHS = ("sb3", "device")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run_dirs", nargs="+")
    p.add_argument("--device", help="device to evaluate on (default: the run's)")
    p.add_argument("--episodes", type=int, help="episodes an evaluation (default: the config's eval_episodes)")
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--json", help="write the rows to this JSON file")
    return p.parse_args(argv)


def time_run(run_dir: str, *, device: str | None, episodes: int | None, repeat: int) -> dict:
    cfg, model, vecnorm = load_run(run_dir, device=device)
    episodes = episodes or cfg["eval_episodes"]
    evaluators, envs = {}, []
    for path in PATHS:
        env = build_eval_env(cfg, num_envs=eval_env_count(cfg, episodes), seed=cfg["seed"] + EVAL_SEED_OFFSET,
                             vecnormalize=vecnorm, on_device=path == "device")  # fmt: skip
        envs.append(env)
        evaluators[path] = episode_evaluator(env)
    times: dict[str, list[float]] = {p: [] for p in PATHS}
    first: dict[str, tuple[list[float], list[int]]] = {}
    try:
        for path in PATHS:  # untimed (compiles and captures), from the seeded reset
            first[path] = evaluators[path](model, episodes)
        for _ in range(repeat):
            for path in PATHS:
                t = time.perf_counter()
                evaluators[path](model, episodes)
                times[path].append(time.perf_counter() - t)
    finally:
        for env in envs:
            env.close()
    row = dict(run_dir=str(run_dir), env_id=cfg["env_id"], device=cfg["device"], episodes=episodes,
               n_eval_envs=eval_env_count(cfg, episodes))  # fmt: skip
    for path in PATHS:
        returns, lengths = first[path]
        row[f"{path}_s"] = min(times[path])
        row[f"{path}_times_s"] = times[path]
        row[f"{path}_mean_return"] = float(np.mean(returns))
        row[f"{path}_mean_length"] = float(np.mean(lengths))
    row["speedup"] = row["sb3_s"] / row["device_s"]
    return row


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    rows = [time_run(d, device=args.device, episodes=args.episodes, repeat=args.repeat) for d in args.run_dirs]
    print("| env | episodes | SB3 [s] | device [s] | SB3 / device | return (SB3, device) | length (SB3, device) |")
    print("|---|---:|---:|---:|---:|---|---|")
    for r in rows:
        print(f"| {r['env_id']} | {r['episodes']} | {r['sb3_s']:.3f} | {r['device_s']:.3f} | {r['speedup']:.1f}× "
              f"| {r['sb3_mean_return']:.2f}, {r['device_mean_return']:.2f} "
              f"| {r['sb3_mean_length']:.1f}, {r['device_mean_length']:.1f} |")  # fmt: skip
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
