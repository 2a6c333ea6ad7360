#!/usr/bin/env python3
"""A/B of whole source trees on one device: world-steps/s of each, alternating processes.

    git archive 050a255 abd_gym envs scripts | (mkdir -p tmp_gpu/base && tar -x -C tmp_gpu/base)
    python scripts/ab_trees.py --trees base,new --cases cartpole,double_pendulum --worlds 1024 --rounds 2

A tree is a folder under ``--under`` (default tmp_gpu/) holding a copy of ``abd_gym`` (e.g. an
older commit's, from ``git archive``); "new" is this checkout.  Each run is ``scripts/ab_step.py
--variant new`` in a process of its own with that tree first on PYTHONPATH, the trees alternating
over ``--rounds`` rounds; a SUMMARY line per case and batch gives each tree's best world-steps/s,
its ratio to the first tree and the mean Newton iterations of its last step.  (scripts/ab_step.py
A/Bs patches of one tree; this one A/Bs commits, e.g. ones that change the State.)  Writes every
run to ``--out``/ab_trees.json.
"""
import argparse
import json
import os
import subprocess
import sys

HERE = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--trees", default="base,new")
    ap.add_argument("--under", default=os.path.join(HERE, "tmp_gpu"))
    ap.add_argument("--cases", default="cartpole,double_pendulum")
    ap.add_argument("--worlds", default="1024")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--out", default=os.environ.get("OUT", "."))
    args = ap.parse_args()
    trees, rows = args.trees.split(","), []
    os.makedirs(args.out, exist_ok=True)
    for W in (int(w) for w in args.worlds.split(",")):
        for case in args.cases.split(","):
            for r in range(args.rounds):
                for tree in trees:
                    d = HERE if tree == "new" else os.path.join(args.under, tree)
                    env = dict(os.environ, PYTHONPATH=d + os.pathsep + os.environ.get("PYTHONPATH", ""))
                    cmd = [sys.executable, os.path.join(HERE, "scripts", "ab_step.py"), "--variant", "new", "--case", case,
                           "--save", os.path.join(args.out, f"q_{tree}_{case}_{W}.npy"), "--device", args.device,
                           "--worlds", str(W), "--steps", str(args.steps), "--repeat", "5" if W <= 4096 else "3"]  # fmt: skip
                    out = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=d)
                    line = [x for x in out.stdout.splitlines() if x.startswith("{")]
                    if out.returncode or not line:
                        print(out.stdout[-1500:], out.stderr[-3000:], flush=True)
                        continue
                    row = dict(json.loads(line[-1]), tree=tree, round=r)
                    rows.append(row)
                    print(json.dumps(row), flush=True)
            mine = [x for x in rows if x["case"] == case and x["worlds"] == W]
            best = {t: max((x["world_steps_per_second"] for x in mine if x["tree"] == t), default=0.0) for t in trees}
            its = {t: next((x["newton_iterations"] for x in mine if x["tree"] == t), float("nan")) for t in trees}
            print(f"SUMMARY {case} {W}: " + "  ".join(
                f"{t} {best[t] / 1e6:.2f} M (x{best[t] / max(best[trees[0]], 1e-9):.3f}, iterations {its[t]:.2f})"
                for t in trees), flush=True)  # fmt: skip
    with open(os.path.join(args.out, "ab_trees.json"), "w") as f:
        json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
