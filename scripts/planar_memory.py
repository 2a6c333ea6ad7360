#!/usr/bin/env python3
"""Device memory a world of each task's mechanism takes, solved in its plane and with 12 unknowns a body.

    python scripts/planar_memory.py [--worlds 1024] [--dtype float32] [--json PATH]

``Simulator.memory_bytes`` per world (model, state, solver; the arrays' capacity, so the same on any
device) with one thread a world and its system in global memory (ExecutionPlan(scratch="global",
threads=worlds)): the layout whose scratch grows with the batch.  Prints a Markdown table.
"""
from __future__ import annotations

import argparse
import json
import sys

import gymnasium as gym

import abd_gym as ag
import abd_gym.envs  # noqa: F401  (registers the tasks)
from abd_gym.vector.registration import TASKS


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--worlds", type=int, default=1024)
    p.add_argument("--dtype", default="float32")
    p.add_argument("--json")
    args = p.parse_args(argv)
    rows = []
    for task in TASKS:
        env = gym.make_vec(f"abd_gym/{task}", num_envs=1, vectorization_mode="vector_entry_point")
        scene = env.unwrapped.sim.scene
        env.close()
        row = dict(task=task)
        for key, planar in (("planar", None), ("full", False)):
            scene.planar = planar
            sim = ag.Simulator(scene, num_worlds=args.worlds, dtype=args.dtype, device="cpu",
                               plan=ag.ExecutionPlan(scratch="global", threads=args.worlds))  # fmt: skip
            mem = sim.memory_bytes()
            row[key] = dict(unknowns=sim.model.num_dofs, plane=str(sim.plane) if sim.plane else None,
                            **{k: v / args.worlds for k, v in mem.items()})  # fmt: skip
        scene.planar = None
        rows.append(row)
    print(f"Bytes a world ({args.worlds} worlds, {args.dtype}, one thread a world, scratch in global memory)\n")
    print("| task | plane | unknowns | solver | total | 12 unknowns a body: unknowns | solver | total | total / 12's |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        a, b = r["planar"], r["full"]
        print(f"| {r['task']} | {a['plane'] or '—'} | {a['unknowns']} | {a['solver']:,.0f} | {a['total']:,.0f} | "
              f"{b['unknowns']} | {b['solver']:,.0f} | {b['total']:,.0f} | {a['total'] / b['total']:.2f} |")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(dict(worlds=args.worlds, dtype=args.dtype, command="python scripts/planar_memory.py "
                           + " ".join(argv if argv is not None else sys.argv[1:]), rows=rows), f, indent=1)  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
