#!/usr/bin/env python3
"""Newton's stop against accuracy: the largest joint-angle error over 1 s against an own float64 run
at a small dt, with ``quadratic_stop`` off and on (CPU by default; bench accuracy's run_ours).

    python scripts/stop_accuracy.py [--integrator bdf2] [--device cpu]

Prints, per mechanism, dt and dtype, each setting's error (largest over 1 s and at 1 s), joint
residual and energy drift (results/quadratic_stop.md §2)."""
import argparse

import numpy as np

import abd_gym.bench_accuracy as ba
from abd_gym.bench_compare import random_states


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--integrator", default="implicit_euler")
    ap.add_argument("--reference-dt", type=float, default=5e-4)
    ap.add_argument("--dts", default="0.02,0.01,0.005")
    ap.add_argument("--worlds", type=int, default=8)
    args = ap.parse_args()
    for case in ("double_pendulum", "cartpole"):
        x0 = random_states(case, args.worlds)
        ref, *_ = ba.run_ours(case, x0, args.reference_dt, "float64", 1e-10, args.device, quadratic_stop=0.0)
        for dt in (float(d) for d in args.dts.split(",")):
            for dtype in ("float32", "float64"):
                row = []
                for qs in (0.0, 100.0):
                    out, res, drift, _ = ba.run_ours(case, x0, dt, dtype, 1e-5, args.device, integrator=args.integrator,
                                                     quadratic_stop=qs)  # fmt: skip
                    row.append(f"quadratic_stop {qs:3g}: error {np.abs(out - ref).max():.3e} (at 1 s "
                               f"{np.abs(out[-1] - ref[-1]).max():.3e}) residual {res:.1e} drift {drift:.3e}")
                print(case, dt, dtype, " | ".join(row), flush=True)


if __name__ == "__main__":
    main()
