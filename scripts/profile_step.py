#!/usr/bin/env python3
"""Step a batch of worlds without graph capture, so a profiler sees each kernel launch.

    ncu -k regex:newton -c 1 --section SpeedOfLight --section WarpStateStats \\
        python scripts/profile_step.py --device cuda:0 --case cartpole --worlds 16384

Steps ``--warmup`` steps (compile, load), then ``--steps`` more; profile the fused Newton kernel
(``newton*``) of one of the later steps.

    python scripts/profile_step.py --device cuda:0 --case cartpole --worlds 1024 --scratch lanes --phases

``--phases``: no profiler; the fused kernel reads the GPU's cycle counter between its phases
(fused.PHASES) and this prints the mean cycles per world-step of each, and the whole step's time.
"""
import argparse
import time

import warp as wp

from abd_gym.bench import CASES
from abd_gym.bench_compare import random_states
from abd_gym.simulator import Simulator


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--case", default="cartpole", choices=sorted(CASES))
    ap.add_argument("--worlds", type=int, default=16384)
    ap.add_argument("--scratch", default="auto", help="auto (the simulator's default), global, shared or lanes")
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--steps", type=int, default=2)
    ap.add_argument("--block-dim", type=int, default=None)
    ap.add_argument("--lineinfo", action="store_true", help="compile with line information (source-level profiles)")
    ap.add_argument("--phases", action="store_true", help="time the fused step's phases with the GPU's cycle counter")
    args = ap.parse_args()
    if args.lineinfo:
        wp.config.lineinfo = True
    sim = Simulator(CASES[args.case]["scene"](), num_worlds=args.worlds, dt=0.01, device=args.device,
                    use_graph=args.phases, scratch=None if args.scratch == "auto" else args.scratch,
                    block_dim=args.block_dim)  # fmt: skip
    sim.solver.settings.phase_clock = args.phases
    sim.set_joint_state(random_states(args.case, args.worlds))
    sim.step(args.warmup)
    wp.synchronize_device(sim.device)
    if args.phases:
        sim.solver.phase_cycles.zero_()
        t0 = time.perf_counter()
    sim.step(args.steps)
    wp.synchronize_device(sim.device)
    if args.phases:
        from abd_gym.fused import PHASES

        ms = (time.perf_counter() - t0) / args.steps * 1e3
        c = sim.solver.phase_cycles.numpy().sum(0) / (args.worlds * args.steps)
        print(f"{args.case} {sim.solver.scratch}/{sim.solver.block_dim}: {args.worlds} worlds, "
              f"{ms * 1e3:.1f} us a step "
              f"(with the phase clock), cycles per world-step: " + ", ".join(f"{p} {v:,.0f}" for p, v in zip(PHASES, c)))
    print(f"{args.case}: {args.worlds} worlds, threads {sim.solver.threads}, block {sim.solver.block_dim}, "
          f"Newton iterations {sim.newton_iterations().mean():.2f}")


if __name__ == "__main__":
    main()
