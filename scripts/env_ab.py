#!/usr/bin/env python3
"""A/B of a ``abd_gym.solver`` module flag on vector envs: env and simulator rates with the flag on
and off, in alternating processes.

    python scripts/env_ab.py --flag FUSE_REVOLUTE --tasks Reacher-v0,Acrobot-v0 --envs 1024 --device cuda:0

Each process sets ``abd_gym.solver.<flag>`` and runs abd_gym.envs.bench_envs.env_steps_per_second (Torch
backend, 200 steps, best of 3 windows); the summary gives each task's best "simulator alone" and env
rates with the flag on against off (results/quadratic_stop.md §8)."""
import argparse
import json
import subprocess
import sys


def one(flag, value, task, envs, device):
    import abd_gym.solver

    setattr(abd_gym.solver, flag, bool(int(value)))
    from abd_gym.envs.bench_envs import env_steps_per_second

    env, raw, physics = env_steps_per_second(task, envs, 200, device, backend="torch", raw=True, repeat=3)
    print("RESULT " + json.dumps(dict(task=task, envs=envs, on=int(value), env=env, raw=raw, physics=physics)), flush=True)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--flag", default="FUSE_REVOLUTE")
    ap.add_argument("--tasks", default="Reacher-v0,Acrobot-v0")
    ap.add_argument("--envs", default="1024")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--one", nargs=3, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        return one(args.flag, args.one[0], args.one[1], int(args.one[2]), args.device)
    rows = []
    for r in range(args.rounds):
        for task in args.tasks.split(","):
            for n in args.envs.split(","):
                for value in ("1", "0"):
                    cmd = [sys.executable, __file__, "--flag", args.flag, "--device", args.device, "--one", value, task, n]
                    out = subprocess.run(cmd, capture_output=True, text=True)
                    line = [x for x in out.stdout.splitlines() if x.startswith("RESULT ")]
                    if not line:
                        print(out.stdout[-1500:], out.stderr[-3000:], flush=True)
                        continue
                    rows.append(dict(json.loads(line[-1][7:]), round=r))
                    print(json.dumps(rows[-1]), flush=True)
    for task in args.tasks.split(","):
        for n in (int(x) for x in args.envs.split(",")):
            best = {v: max((x for x in rows if x["task"] == task and x["envs"] == n and x["on"] == v),
                           key=lambda x: x["raw"], default=None) for v in (1, 0)}  # fmt: skip
            if best[1] and best[0]:
                print(f"{task} {n} envs, {args.flag} on / off: simulator alone {best[1]['raw']:.4g} / {best[0]['raw']:.4g} "
                      f"= {best[1]['raw'] / best[0]['raw']:.3f}; env {best[1]['env']:.4g} / {best[0]['env']:.4g} "
                      f"= {best[1]['env'] / best[0]['env']:.3f}", flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
