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

from abd_gym.bench.compare import random_states
from abd_gym.bench.cases import CASES
from abd_gym.solver.plan import ExecutionPlan
from abd_gym.sim.simulator import Simulator


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--case", default="cartpole", choices=list(CASES), help="a mechanism of abd_gym.bench.cases")
    ap.add_argument("--worlds", type=int, default=16384)
    ap.add_argument("--scratch", default="auto", help="auto (the simulator's default), global, shared or lanes")
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--steps", type=int, default=2)
    ap.add_argument("--block-dim", type=int, default=None)
    ap.add_argument("--lane-groups", type=int, default=None, help="lane groups a world (scratch lanes)")
    ap.add_argument("--steps-per-launch", type=int, default=None, help="steps a launch (one-launch step)")
    ap.add_argument("--lineinfo", action="store_true", help="compile with line information (source-level profiles)")
    ap.add_argument("--phases", action="store_true", help="time the fused step's phases with the GPU's cycle counter")
    ap.add_argument("--split", action="store_true",
                    help="device time of the captured step, and of the kernels that open and close a step when they "
                         "run on their own (one_launch=False)")
    ap.add_argument("--launch", choices=("default", "one", "two"), default="default",
                    help="one: the fused kernel opens and closes each world's step (one_launch=True); two: kernels "
                         "of their own do, around it (one_launch=False); default: the simulator's (one with lanes)")
    args = ap.parse_args()
    if args.split and not wp.get_device(args.device).is_cuda:
        ap.error("--split times the device with CUDA events: give a CUDA --device")
    if args.lineinfo:
        wp.config.lineinfo = True
    plan = ExecutionPlan(use_graph=args.phases or args.split, scratch=None if args.scratch == "auto" else args.scratch,
                         block_dim=args.block_dim, one_launch={"default": None, "one": True, "two": False}[args.launch],
                         lane_groups=args.lane_groups, steps_per_launch=args.steps_per_launch,
                         phase_clock=args.phases)  # fmt: skip
    sim = Simulator(CASES[args.case].scene(), num_worlds=args.worlds, dt=0.01, device=args.device, plan=plan)
    sim.set_joint_state(random_states(args.case, args.worlds))
    sim.step(args.warmup)
    wp.synchronize_device(sim.device)
    if args.phases:
        sim.solver.phase_cycles.zero_()
        t0 = time.perf_counter()
    sim.step(args.steps)
    wp.synchronize_device(sim.device)
    if args.phases:
        from abd_gym.solver.fused import PHASES

        ms = (time.perf_counter() - t0) / args.steps * 1e3
        c = sim.solver.phase_cycles.numpy().sum(0) / (args.worlds * args.steps)
        print(f"{args.case} {sim.plan.scratch}/{sim.plan.block_dim} G{sim.plan.lane_groups} "
              f"S{sim.plan.steps_per_launch}: {args.worlds} worlds, "
              f"{ms * 1e3:.1f} us a step "
              f"(with the phase clock), cycles per world-step: " + ", ".join(f"{p} {v:,.0f}" for p, v in zip(PHASES, c)))
    if args.phases:
        # a launch lasts as long as its slowest world: the busiest world's cycles a step
        from abd_gym.solver.fused import WORLD_PHASES

        per_world = sim.solver.phase_cycles.numpy()[:, list(WORLD_PHASES)].sum(1) / args.steps
        print(f"cycles a step per world (open, zero … step, close): mean {per_world.mean():,.0f}, "
              f"max {per_world.max():,.0f}")
    if args.split:
        split(sim, args.steps)
    print(f"{args.case}: {args.worlds} worlds, threads {sim.plan.threads}, block {sim.plan.block_dim}, "
          f"Newton iterations {sim.newton_iterations().mean():.2f}")


def split(sim, steps: int, copies: int = 20):
    """Device time of the captured step, and of the kernels that open and close a step when they run
    as launches of their own (Solver.open_step, close_step; with one_launch the fused kernel does their
    work): each captured ``copies`` times in one graph, so a replay's host cost is spread over
    ``copies`` steps, and timed by CUDA events over ``steps`` steps."""
    solver, state, dev = sim.solver, sim.state, sim.device

    def around():
        solver.open_step(state)
        solver.close_step(state)

    graphs = {}
    for name, part in (("step", lambda: solver.step(state)), ("around", around)):
        with wp.ScopedCapture(device=dev) as cap:
            for _ in range(copies):
                part()
        graphs[name] = cap.graph
    us = {}
    for name, graph in graphs.items():
        wp.capture_launch(graph)
        start, end = wp.Event(dev, enable_timing=True), wp.Event(dev, enable_timing=True)
        reps = max(steps // copies, 1)
        wp.record_event(start)
        for _ in range(reps):
            wp.capture_launch(graph)
        wp.record_event(end)
        wp.synchronize_device(dev)
        us[name] = wp.get_event_elapsed_time(start, end) * 1e3 / (reps * copies)
    launches = "one launch" if sim.plan.one_launch else "open and close launched around Newton"
    print(f"split (device time, {copies} steps a graph): step ({launches}) {us['step']:.1f} us; the open and close "
          f"kernels on their own {us['around']:.1f} us")


if __name__ == "__main__":
    main()
