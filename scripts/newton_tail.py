#!/usr/bin/env python3
"""Newton iterations a step and their tail: mean, p99, max, the mean over steps of the slowest
world of each 32 (a GPU warp waits for its slowest thread, so a batch steps at that pace) and of
the batch's slowest world (where a GPU holds about a world a thread, a step lasts about as long as
that world's solve: the shared step at 16,384 worlds).

    python3 scripts/newton_tail.py [--cases cartpole,fourbar,...] [--worlds 256] [--steps 60] [--device cpu]
        [--reuse-factor 0,1] [--limit-secant auto,0,1] [--threads 12672]

Each case (``abd_gym.bench.cases``) starts from its random states, steps 3 times, then records each
world's Newton iterations and factorisations for ``--steps`` steps, once per ``--reuse-factor``
setting (0: the simulator's default, a fresh factor every iteration) and ``--limit-secant``
setting (ExecutionPlan.limit_secant; auto: the plan's default, which the CPU's is off).

``--threads T``: also the length of a GPU launch of T threads that claim the worlds in order from
its queue as their solves end (fused.kernel.run_worlds), in Newton iterations (each thread's
iterations one after another; the launch lasts as long as its last thread), and its bound,
max(total / T, the slowest world): where T threads hold a batch of 1.29 worlds each (16,384
three-body worlds on 132 SMs: 12,672 threads), the threads with a second world set its length.
"""
from __future__ import annotations

import argparse
import heapq

import numpy as np
import warp as wp

CASES = "cartpole,inverted_pendulum_v5,double_pendulum_cart,inverted_double_pendulum_v5,fourbar,slider_crank,chain5"


def queue_length(its: np.ndarray, threads: int) -> float:
    """Newton iterations a launch of ``threads`` threads lasts for worlds taking ``its`` iterations
    each, thread c starting with world c and each claiming the next unclaimed world when its own
    is done."""
    if len(its) <= threads:
        return float(its.max())
    ends = [float(k) for k in its[:threads]]
    heapq.heapify(ends)
    for k in its[threads:]:
        heapq.heappush(ends, heapq.heappop(ends) + float(k))
    return max(ends)


def tail(case: str, worlds: int, steps: int, device: str, reuse_factor: bool = False,
         limit_secant: bool | None = None, threads: int = 0) -> dict[str, float]:
    from abd_gym.bench.cases import CASES as PEER
    from abd_gym.sim.simulator import Simulator

    c = PEER[case]
    sim = Simulator(c.scene(), num_worlds=worlds, dt=0.01, device=device, reuse_factor=reuse_factor,
                    plan={"limit_secant": limit_secant})  # fmt: skip
    sim.set_joint_state(*c.states(worlds, 0))
    sim.step(3)
    its, fac = [], []
    for _ in range(steps):
        sim.step(1)
        its.append(sim.newton_iterations().copy())
        fac.append(sim.newton_factorizations().copy())
    its, fac = np.array(its), np.array(fac)
    warp = worlds // 32
    queue = {}
    if threads:
        queue = {"queue": np.mean([queue_length(k, threads) for k in its]),
                 "queue_bound": np.mean([max(k.sum() / threads, k.max()) for k in its])}
    return queue | {"mean": its.mean(), "p99": np.percentile(its, 99), "max": its.max(),
            "warp_max": its[:, : warp * 32].reshape(steps, warp, 32).max(-1).mean(), "step_max": its.max(1).mean(),
            "factorizations": fac.mean(),
            "warp_max_factorizations": fac[:, : warp * 32].reshape(steps, warp, 32).max(-1).mean()}  # fmt: skip


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", default=CASES)
    p.add_argument("--worlds", type=int, default=256)
    p.add_argument("--steps", type=int, default=60)
    p.add_argument("--device", default="cpu")
    p.add_argument("--reuse-factor", default="0", help="comma-separated 0/1 (SolverSettings.reuse_factor)")
    p.add_argument("--limit-secant", default="auto", help="comma-separated auto/0/1 (ExecutionPlan.limit_secant)")
    p.add_argument("--threads", type=int, default=0, help="a GPU launch's threads: also its queue's length (0: not)")
    args = p.parse_args()
    wp.config.quiet = True
    reuse = {"0": False, "1": True}
    secant = {"auto": None, "0": False, "1": True}
    print(f"{'case':28s} {'reuse':>5s} {'secant':>6s} {'mean':>6s} {'p99':>5s} {'max':>4s} {'warp-max':>9s} {'step-max':>9s} "
          f"{'fact.':>6s} {'warp-max fact.':>15s}" + (f" {'queue':>6s} {'bound':>6s}" if args.threads else ""))  # fmt: skip
    for case in args.cases.split(","):
        for setting in args.reuse_factor.split(","):
            for sec in args.limit_secant.split(","):
                r = tail(case, args.worlds, args.steps, args.device, reuse[setting], secant[sec], args.threads)
                queue = f" {r['queue']:6.2f} {r['queue_bound']:6.2f}" if args.threads else ""
                print(f"{case:28s} {setting:>5s} {sec:>6s} {r['mean']:6.2f} {r['p99']:5.0f} {r['max']:4.0f} {r['warp_max']:9.2f} "
                      f"{r['step_max']:9.2f} {r['factorizations']:6.2f} {r['warp_max_factorizations']:15.2f}{queue}")  # fmt: skip


if __name__ == "__main__":
    main()
