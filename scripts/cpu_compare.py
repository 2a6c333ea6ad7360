#!/usr/bin/env python3
"""abd_gym on the CPU beside MuJoCo C: world-steps per second of each mechanism.

    python scripts/cpu_compare.py [--cases pendulum,cartpole_task,...] [--worlds 1,64,1024]
        [--steps 50] [--repeat 3] [--threads N] [--integrators Euler,RK4] [--planar auto,off] [--json PATH]

Both engines step the case's random starts (``abd_gym.bench.cases.CASES``, seed 0) with dt = 0.01 s.
abd_gym: ``bench compare``'s timing on the CPU device (float32, its default plan: the fused
step's worlds split over as many concurrent launches as the machine has cores), best of
``--repeat``.  MuJoCo C (the ``mujoco`` package): ``mujoco.rollout`` over the same worlds with one
``MjData`` per thread (``--threads``, default: the machine's cores) and a persistent thread pool,
each of ``--integrators`` (MuJoCo's Euler, its default, and RK4), best of ``--repeat``, the
rollout's state output included.  Prints a table (ratio = abd_gym / MuJoCo) and writes the rows
as JSON.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time

import numpy as np

from abd_gym.bench.accuracy import _mujoco_starts
from abd_gym.bench.compare import ours_steps_per_second
from abd_gym.bench.cases import CASES, with_integrator

DT = 0.01
TASK_CASES = ("pendulum", "cartpole_task", "double_pendulum", "acrobot", "reacher", "inverted_pendulum_v5",
              "reacher_v5", "fourbar", "slider_crank", "double_pendulum_cart", "inverted_double_pendulum_v5",
              "chain5")  # fmt: skip


def mujoco_steps_per_second(case: str, num_worlds: int, steps: int, integrator: str, threads: int,
                            repeat: int) -> tuple[float, int]:  # fmt: skip
    """MuJoCo C's world-steps/s over ``steps`` steps of ``num_worlds`` worlds (best of ``repeat``)
    and the count of worlds whose state is non-finite at the end."""
    import mujoco
    from mujoco import rollout

    mjm = mujoco.MjModel.from_xml_string(with_integrator(CASES[case].xml(DT), integrator))
    _, x0 = _mujoco_starts(mjm, case, *CASES[case].states(num_worlds, 0))
    datas = [mujoco.MjData(mjm) for _ in range(threads)]
    out = np.empty((num_worlds, steps, x0.shape[1]))
    rollout.rollout(mjm, datas, x0, nstep=steps, state=out, persistent_pool=True)  # the pool, started
    best = math.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        rollout.rollout(mjm, datas, x0, nstep=steps, state=out, persistent_pool=True)
        best = min(best, time.perf_counter() - t0)
    return num_worlds * steps / best, int((~np.isfinite(out[:, -1])).any(axis=1).sum())


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cases", default=",".join(TASK_CASES))
    p.add_argument("--worlds", default="1,64,1024")
    p.add_argument("--steps", type=int, default=50)
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--threads", type=int, default=os.cpu_count())
    p.add_argument("--integrators", default="Euler,RK4")
    p.add_argument("--planar", default="auto", help="comma-separated forms of abd_gym's step: auto (a planar "
                   "scene's 6 unknowns a body), off (12 unknowns a body)")
    p.add_argument("--json", help="write the rows to this JSON file")
    args = p.parse_args(argv)
    unknown = [c for c in args.cases.split(",") if c not in CASES]
    if unknown:
        p.error(f"unknown case(s) {', '.join(unknown)}: choose from {', '.join(CASES)}")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    integrators = [n for n in args.integrators.split(",") if n]
    rows = []
    for case in args.cases.split(","):
        for w in (int(x) for x in args.worlds.split(",")):
            row = dict(case=case, num_worlds=w)
            for form in args.planar.split(","):
                ours, _, _, layout, bad, unknowns = ours_steps_per_second(
                    case, w, args.steps, DT, "cpu", repeat=args.repeat, planar={"auto": None, "off": False}[form])
                key = "abd_gym" if form == "auto" else f"abd_gym_{form}"
                row.update({key: ours, f"{key}_layout": layout, f"{key}_nonfinite": bad, f"{key}_unknowns": unknowns})
            ours, ours_bad = row.get("abd_gym", math.nan), row.get("abd_gym_nonfinite", 0)
            for name in integrators:
                sps, bad = mujoco_steps_per_second(case, w, args.steps, name, args.threads, args.repeat)
                row[f"mujoco_{name.lower()}"] = sps
                row[f"mujoco_{name.lower()}_nonfinite"] = bad
                row[f"ratio_{name.lower()}"] = None if bad or ours_bad else ours / sps
            rows.append(row)
            print(f"{case:28s} {w:6d} worlds  abd_gym {ours:12,.0f} ({row.get('abd_gym_unknowns')})  " + "  ".join(
                f"MuJoCo {n} {row[f'mujoco_{n.lower()}']:12,.0f}" for n in integrators), flush=True)  # fmt: skip
    forms = [f for f in args.planar.split(",") if f != "auto"]
    head = (["mechanism", "worlds", "unknowns", "abd_gym"] + [f"abd_gym, planar {f}" for f in forms]
            + [c for n in integrators for c in (f"MuJoCo {n}", f"ours / {n}")])  # fmt: skip
    print(f"\nCPU: {platform.processor() or platform.machine()}, {os.cpu_count()} cores; MuJoCo threads "
          f"{args.threads}; dt {DT}; world-steps/s\n")
    print("| " + " | ".join(head) + " |")
    print("|---|---:" + "|---:" * (len(head) - 2) + "|")
    for r in rows:
        unknowns = "/".join(str(r[f"{k}_unknowns"]) for k in ["abd_gym"] * ("abd_gym" in r) + [f"abd_gym_{f}" for f in forms])
        cells = [r["case"], f"{r['num_worlds']:,}", unknowns, f"{r.get('abd_gym', math.nan):,.0f}"]
        cells += [f"{r[f'abd_gym_{f}']:,.0f}" for f in forms]
        for n in integrators:
            ratio = r[f"ratio_{n.lower()}"]
            cells += [f"{r[f'mujoco_{n.lower()}']:,.0f}", "—" if ratio is None else f"{ratio:.2f}×"]
        print("| " + " | ".join(cells) + " |")
    if args.json:
        meta = dict(cpu=platform.processor() or platform.machine(), cores=os.cpu_count(), threads=args.threads,
                    dt=DT, steps=args.steps, repeat=args.repeat, command="python scripts/cpu_compare.py "
                    + " ".join(argv if argv is not None else sys.argv[1:]))  # fmt: skip
        with open(args.json, "w") as f:
            json.dump(dict(meta, rows=rows), f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
