#!/usr/bin/env python3
"""The Newton solve's own error: from a float64 trajectory's states, one float32 step against the
float64 step, per factor-reuse setting and quadratic_stop.

    python3 scripts/solve_error.py [--cases reacher,fourbar,chain5] [--worlds 256] [--steps 30] [--reuse-factor 0,1]
        [--quadratic-stop 100,0]

Each case (``abd_gym.bench.cases``) starts from its random states; a float64 simulator steps them
with implicit Euler (no history, so a step depends on the state alone).  Before each of its steps,
its whole state is copied into a float32 simulator per setting (SolverSettings.reuse_factor and
quadratic_stop), which takes the same step.  Prints
the largest, 99th-percentile and median ‖q₃₂ − q₆₄‖∞ [m] over worlds and steps, and the mean
Newton iterations.  CPU.
"""
from __future__ import annotations

import argparse

import numpy as np
import warp as wp


def solve_error(case: str, worlds: int, steps: int, settings: list[tuple[bool, float]]) -> dict[tuple, tuple]:
    from abd_gym.bench.cases import CASES
    from abd_gym.sim.simulator import Simulator

    c = CASES[case]
    make = lambda **kw: Simulator(c.scene(), num_worlds=worlds, dt=0.01, device="cpu",  # noqa: E731
                                  integrator="implicit_euler", **kw)  # fmt: skip
    ref = make(dtype="float64")
    sims = {(r, qs): make(reuse_factor=r, quadratic_stop=qs) for r, qs in settings}
    ref.set_joint_state(*c.states(worlds, 0))
    errors, iterations = {r: [] for r in settings}, {r: [] for r in settings}
    for _ in range(steps):
        for sim in sims.values():
            for name, a in vars(ref.state).items():
                if isinstance(a, wp.array):
                    b = getattr(sim.state, name)
                    b.assign(a.numpy().astype(b.numpy().dtype))
        ref.step(1)
        for r, sim in sims.items():
            sim.step(1)
            errors[r].append(np.abs(sim.body_q() - ref.body_q()).reshape(worlds, -1).max(1))
            iterations[r].append(sim.newton_iterations().mean())
    return {r: (np.max(errors[r]), np.percentile(errors[r], 99), np.median(errors[r]), np.mean(iterations[r]))
            for r in settings}  # fmt: skip


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", default="reacher,fourbar,chain5")
    p.add_argument("--worlds", type=int, default=256)
    p.add_argument("--steps", type=int, default=30)
    p.add_argument("--reuse-factor", default="0,1", help="comma-separated 0/1 (SolverSettings.reuse_factor)")
    p.add_argument("--quadratic-stop", default="100", help="comma-separated SolverSettings.quadratic_stop values")
    args = p.parse_args()
    wp.config.quiet = True
    settings = [(s == "1", float(qs)) for s in args.reuse_factor.split(",") for qs in args.quadratic_stop.split(",")]
    print(f"{'case':28s} {'reuse':>5s} {'quad. stop':>10s} {'max [m]':>9s} {'p99 [m]':>9s} {'median [m]':>10s} "
          f"{'iterations':>10s}")  # fmt: skip
    for case in args.cases.split(","):
        for (r, qs), (mx, p99, med, its) in solve_error(case, args.worlds, args.steps, settings).items():
            print(f"{case:28s} {int(r):5d} {qs:10g} {mx:9.2e} {p99:9.2e} {med:10.2e} {its:10.2f}")


if __name__ == "__main__":
    main()
