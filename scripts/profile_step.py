#!/usr/bin/env python3
"""Step a batch of worlds without graph capture, so a profiler sees each kernel launch.

    ncu -k regex:newton -c 1 --section SpeedOfLight --section WarpStateStats \\
        python scripts/profile_step.py --device cuda:0 --case cartpole --worlds 16384

Steps ``--warmup`` steps (compile, load), then ``--steps`` more; profile the fused Newton kernel
(``newton*``) of one of the later steps.
"""
import argparse

import warp as wp

from abd_gym.bench import CASES
from abd_gym.bench_compare import random_states
from abd_gym.simulator import Simulator


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--case", default="cartpole", choices=sorted(CASES))
    ap.add_argument("--worlds", type=int, default=16384)
    ap.add_argument("--scratch", default="global")
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--steps", type=int, default=2)
    ap.add_argument("--lineinfo", action="store_true", help="compile with line information (source-level profiles)")
    args = ap.parse_args()
    if args.lineinfo:
        wp.config.lineinfo = True
    sim = Simulator(CASES[args.case]["scene"](), num_worlds=args.worlds, dt=0.01, device=args.device,
                    use_graph=False, scratch=args.scratch)  # fmt: skip
    sim.set_joint_state(random_states(args.case, args.worlds))
    sim.step(args.warmup + args.steps)
    wp.synchronize_device(sim.device)
    print(f"{args.case}: {args.worlds} worlds, threads {sim.solver.threads}, block {sim.solver.block_dim}, "
          f"Newton iterations {sim.newton_iterations().mean():.2f}")


if __name__ == "__main__":
    main()
