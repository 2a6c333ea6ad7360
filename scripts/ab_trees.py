#!/usr/bin/env python3
"""A/B of whole source trees on one device: one benchmark command run in each tree in turn, in
processes of their own, alternating over rounds, so that both trees see the same machine state.

    git worktree add /tmp/base <commit>        # or: git archive <commit> | tar -x -C /tmp/base
    python scripts/ab_trees.py --trees base=/tmp/base,new=. --rounds 3 --out ab -- \
        python -m abd_gym.bench --device cuda:0 --cases cartpole,double_pendulum --worlds 1024,131072 --repeat 3

The command runs with the tree as its working directory and first on PYTHONPATH, and with
``--out OUT/<tree>_<round>`` appended, where it writes ``bench.json`` (the format of
``python -m abd_gym.bench``) or ``compare.json`` (``python -m abd_gym.bench compare``, whose
``--mjw-integrators ""`` times abd_gym alone on every mechanism); a tree whose module paths differ
may name its own command with ``--command-for TREE='...'``.  Prints each tree's best world-steps/s
per (case, worlds) and its ratio to the first tree, and writes them to ``OUT/ab_trees.json``, after
every round.
"""
import argparse
import json
import os
import shlex
import subprocess
import sys


def rates(out_dir):
    """{(case, worlds): world-steps/s} of the bench.json in out_dir, and {("env TASK", envs): env-steps/s}
    of its env rows; or abd_gym's {(case, worlds): world-steps/s} of its compare.json."""
    path = os.path.join(out_dir, "bench.json")
    if not os.path.exists(path):
        with open(os.path.join(out_dir, "compare.json")) as f:
            return {(r["case"], int(r["num_worlds"])): float(r["abd_gym"]) for r in json.load(f)["rows"]}
    with open(path) as f:
        result = json.load(f)
    out = {(r["case"], int(r["num_worlds"])): float(r["world_steps_per_second"]) for r in result.get("simulator", [])}
    out.update({("env " + r["task"], int(r["num_envs"])): float(r["env_steps_per_second"]) for r in result.get("envs", [])})
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trees", required=True, help="comma-separated NAME=PATH")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--out", default="ab_out")
    ap.add_argument("--command-for", action="append", default=[], help="TREE='command' for a tree with other paths")
    ap.add_argument("command", nargs=argparse.REMAINDER)
    args = ap.parse_args(argv)
    trees = dict(t.split("=", 1) for t in args.trees.split(","))
    own = {k: shlex.split(v) for k, v in (c.split("=", 1) for c in args.command_for)}
    command = [c for c in args.command if c != "--"]
    best = {}
    for r in range(args.rounds):
        for name, path in trees.items():
            out = os.path.abspath(os.path.join(args.out, f"{name}_{r}"))
            cmd = own.get(name, command) + ["--out", out]
            env = dict(os.environ, PYTHONPATH=os.path.abspath(path) + os.pathsep + os.environ.get("PYTHONPATH", ""))
            run = subprocess.run(cmd, cwd=path, env=env, capture_output=True, text=True)
            if run.returncode:
                print(f"{name} round {r} failed:\n{run.stdout[-2000:]}\n{run.stderr[-3000:]}", flush=True)
                continue
            for key, rate in rates(out).items():
                best.setdefault(key, {})[name] = max(rate, best.get(key, {}).get(name, 0.0))
            print(f"round {r} {name} done", flush=True)
        # the table so far, after every round (a run cut short keeps its finished rounds)
        summary(trees, best, r + 1, command, args.out)


def summary(trees: dict, best: dict, rounds: int, command: list, out: str) -> None:
    """Print each tree's best rate per (case, worlds) and its ratio to the first tree; write OUT/ab_trees.json."""
    names, rows = list(trees), []
    for (case, worlds), by_tree in sorted(best.items()):
        base = by_tree.get(names[0], float("nan"))
        row = dict(case=case, worlds=worlds, **{f"{n}_world_steps_per_second": by_tree.get(n) for n in names},
                   **{f"{n}_ratio": by_tree.get(n, float("nan")) / base for n in names[1:]})
        rows.append(row)
        print(f"{case:>16} {worlds:>8}  " + "  ".join(
            f"{n} {by_tree.get(n, float('nan')) / 1e6:8.2f} M (x{by_tree.get(n, float('nan')) / base:.3f})" for n in names),
            flush=True)  # fmt: skip
    os.makedirs(out, exist_ok=True)
    with open(os.path.join(out, "ab_trees.json"), "w") as f:
        json.dump(dict(trees=trees, rounds=rounds, command=command, rows=rows), f, indent=1)


if __name__ == "__main__":
    sys.exit(main())
