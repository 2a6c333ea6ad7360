#!/usr/bin/env python3
"""World-steps/s of the lane-split step at 32, 16 and 8 lanes a world against the default layout.

    python scripts/lane_width_sweep.py --device cuda:0 --worlds 512,1024,2048,4096,8192,16384 --out sweep.json

One process; for each mechanism, world count and variant ("default": the solver's choice;
"lanesL": scratch="lanes" with L lanes a world, one group) it steps random states (the ones
``bench compare`` uses) 200 steps to compile and capture, then keeps the fastest of three timed
runs of 200 steps.  Prints a line per row and writes the rows as JSON (results/lane_width_h100.md).
"""
import argparse
import json

from abd_gym.bench import CASES
from abd_gym.bench_compare import fastest_run, random_states
from abd_gym.simulator import Simulator

VARIANTS = {"default": {}, "lanes32": dict(scratch="lanes", block_dim=32, lane_groups=1),
            "lanes16": dict(scratch="lanes", block_dim=16), "lanes8": dict(scratch="lanes", block_dim=8),
            "shared": dict(scratch="shared")}  # fmt: skip


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--worlds", default="512,1024,2048,4096,8192,16384")
    ap.add_argument("--variants", default="default,lanes32,lanes16,lanes8")
    ap.add_argument("--cases", default="cartpole,double_pendulum")
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--out", default="lane_width_sweep.json")
    args = ap.parse_args()
    rows = []
    for case in args.cases.split(","):
        for W in (int(x) for x in args.worlds.split(",")):
            for v in args.variants.split(","):
                sim = Simulator(CASES[case]["scene"](), num_worlds=W, dt=0.01, device=args.device, **VARIANTS[v])
                x0 = random_states(case, W)
                sim.set_joint_state(x0)
                sim.step(args.steps)  # compile and capture
                best = fastest_run(sim, x0, args.steps, 3)
                s = sim.solver
                r = dict(case=case, worlds=W, variant=v, scratch=s.scratch, block_dim=s.block_dim,
                         worlds_per_block=s.worlds_per_block, lane_groups=s.lane_groups,
                         world_steps_per_second=W * args.steps / best,
                         newton_iterations=float(sim.newton_iterations().mean()))  # fmt: skip
                rows.append(r)
                print(f"{case:16s} {W:6d} {v:8s} {s.scratch:6s}/{s.block_dim:3d} G{s.lane_groups} "
                      f"{r['world_steps_per_second'] / 1e6:8.2f} M", flush=True)  # fmt: skip
                with open(args.out, "w") as f:
                    json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
