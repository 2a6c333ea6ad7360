#!/usr/bin/env python3
"""Worlds a long chain leaves unconverged at the defaults: a chain of ``--links`` links of 0.1 m
with hinges about +y and +x in turn (mechanisms.alternating_chain) and, with ``--mixed``, link
masses from 1e-3 to 1e2 kg (mechanisms.mixed_masses), stepped ``--steps`` times from random states
(angles U(−1, 1) rad, rates U(−2, 2) rad/s, seed 0) in each dtype and integrator.

    python scripts/chain_convergence.py --links 30 --mixed --worlds 64 --steps 500

Prints and writes (``--out``, JSON) per run: the budget (max_iterations) the simulator took, the
count of worlds of each status at the end (a rejected world keeps its status), the most Newton
iterations any OK world took in a step, and the largest joint gap [m] of the OK worlds.
"""
import argparse
import json
import time
import warnings

import numpy as np

import abd_gym as ag
from abd_gym.sim import mechanisms


def run(links, mixed, dtype, integrator, worlds, steps, dt):
    masses = mechanisms.mixed_masses(links) if mixed else None
    scene = mechanisms.alternating_chain(links, length=0.1, masses=masses)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # (conditioning's float32 warning: reported below)
        sim = ag.Simulator(scene, num_worlds=worlds, dt=dt, dtype=dtype, integrator=integrator)
    rng = np.random.default_rng(0)
    sim.set_joint_state(rng.uniform(-1, 1, (worlds, links)), rng.uniform(-2, 2, (worlds, links)))
    most, gap, t0 = 0, 0.0, time.perf_counter()
    for _ in range(steps):
        sim.step()
        ok = sim.world_status() == 0
        most = max(most, int(sim.newton_iterations()[ok].max(initial=0)))
        gap = max(gap, float(sim.joint_violation()[ok].max(initial=0.0)))
    counts = np.bincount(sim.world_status(), minlength=len(ag.WorldStatus))
    return dict(links=links, mixed=mixed, dtype=dtype, integrator=integrator, worlds=worlds, steps=steps, dt=dt,
                max_iterations=sim.solver.settings.max_iterations,
                status={s.name: int(counts[s]) for s in ag.WorldStatus}, most_iterations=most, joint_gap=gap,
                seconds=time.perf_counter() - t0)  # fmt: skip


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--links", type=int, default=30)
    ap.add_argument("--mixed", action="store_true", help="link masses 1e-3 to 1e2 kg (mechanisms.mixed_masses)")
    ap.add_argument("--worlds", type=int, default=64)
    ap.add_argument("--steps", type=int, default=500)
    ap.add_argument("--dt", type=float, default=0.01)
    ap.add_argument("--dtypes", default="float64,float32")
    ap.add_argument("--integrators", default="implicit_euler,bdf2")
    ap.add_argument("--out", default=None, help="JSON file for the rows")
    args = ap.parse_args(argv)
    rows = []
    for dtype in args.dtypes.split(","):
        for integrator in args.integrators.split(","):
            r = run(args.links, args.mixed, dtype, integrator, args.worlds, args.steps, args.dt)
            rows.append(r)
            print(f"{dtype} {integrator}: budget {r['max_iterations']}, {r['status']}, most iterations "
                  f"{r['most_iterations']}, joint gap {r['joint_gap'] * 1e3:.3f} mm", flush=True)  # fmt: skip
            if args.out:
                with open(args.out, "w") as f:
                    json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
