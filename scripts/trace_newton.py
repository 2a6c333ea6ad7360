#!/usr/bin/env python3
"""Trace Newton's iterations where a step ends unconverged (the hard cases of tests/test_hard_cases.py).

    python scripts/trace_newton.py --device cuda:0 --integrator implicit_euler

Runs the test's 32 float32 double pendulums at dt 0.05 (released from up to 2.5 rad) with the
default (fused) step and lists the world-steps that end unconverged.  For the first of them it
copies the state before that step into a staged solver (fused=False, no graph: one launch per
iteration) and steps it with each iteration's ‖Δq‖∞, gᵀΔq, α, the energy before and after, the
factor-reuse state and the step's outcome printed for the unconverged worlds; then the same step
with factor reuse off, and in float64 from the same state, for comparison.
"""
import argparse

import numpy as np
import warp as wp

import abd_gym as ag
from abd_gym import mechanisms

STATE = ("q", "qd", "q_prev", "q_hist", "qd_hist", "qd_hist2", "order3", "theta0", "c_prev", "s_prev", "coord", "coord_vel", "unwrapped",
         "x_hist", "x_anchor", "control", "status", "fresh")  # fmt: skip


def traced(sim, worlds):
    """Wrap the staged solver's iteration to print the watched worlds' numbers after each one."""
    s = sim.solver
    inner = s._newton_iteration
    rows = []

    def iteration(state):
        inner(state)
        E = s.E.numpy().sum(1)
        for w in worlds:
            rows.append(dict(world=int(w), it=int(state.iterations.numpy()[w]), E=float(E[w]),
                             dq_max=float(s.dq_max.numpy()[w]), gdq=float(s.gdq.numpy()[w]),
                             alpha=float(s.alpha.numpy()[w]), chord=int(s.chord.numpy()[w]),
                             active=int(s.active.numpy()[w]), converged=int(state.converged.numpy()[w])))  # fmt: skip

    s._newton_iteration = iteration
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--integrator", default="implicit_euler")
    ap.add_argument("--worlds", type=int, default=32)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--max-iterations", type=int, default=50)
    args = ap.parse_args()
    x0 = np.random.default_rng(args.seed).uniform(-2.5, 2.5, (args.worlds, 2))
    make = lambda **kw: ag.Simulator(mechanisms.double_pendulum(), num_worlds=args.worlds, dt=0.05,  # noqa: E731
                                     integrator=args.integrator, device=args.device,
                                     max_iterations=args.max_iterations, **kw)  # fmt: skip
    sim = make()
    sim.set_joint_state(x0)
    bad = []
    for step in range(args.steps):
        snapshot = {n: getattr(sim.state, n).numpy().copy() for n in STATE}
        sim.step()
        conv, its = sim.converged(), sim.newton_iterations()
        if not conv.all():
            worlds = np.flatnonzero(~conv)
            bad.append((step, worlds.tolist(), its[worlds].tolist()))
            if len(bad) == 1:
                first, saved = (step, worlds), snapshot
    print(f"{sim.device} {args.integrator}: unconverged (step, worlds, iterations): {bad}")
    if not bad:
        return
    step, worlds = first
    worlds = worlds[:4]
    for label, kw in (("staged float32, reuse on", {}), ("staged float32, reuse off", {"reuse_factor": False}),
                      ("staged float64", {"dtype": "float64"})):  # fmt: skip
        st = make(fused=False, use_graph=False, **kw)
        for n, a in saved.items():
            arr = getattr(st.state, n)
            arr.assign(a.astype(arr.numpy().dtype))
        rows = traced(st, worlds)
        st.step()
        print(f"\n== step {step}, {label}: converged {st.converged()[worlds].tolist()}, iterations "
              f"{st.newton_iterations()[worlds].tolist()}")  # fmt: skip
        for r in rows:
            print("  world {world:3d} it {it:3d}  E {E:+.9e}  dq_max {dq_max:.3e}  gdq {gdq:+.3e}  alpha {alpha:.4f}  "
                  "chord {chord:+d}  active {active}  converged {converged}".format(**r))
    wp.synchronize()


if __name__ == "__main__":
    main()
