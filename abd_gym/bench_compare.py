"""``python -m abd_gym.bench compare``: the same cart-pole and double pendulum in abd_gym and in
MuJoCo Warp (optional: ``pip install mujoco mujoco-warp``), same device, same worlds, one process.

Both step with dt = 0.01 from random states; MuJoCo Warp runs its default (semi-implicit Euler)
integrator, replayed as a CUDA graph of 10 steps (on the CPU it steps plainly); abd_gym replays its
own captured step.  Each engine is timed ``--repeat`` times and keeps its fastest run (a short run on
a GPU varies with clocks and whatever ran before it).  Reports world-steps per second and the ratio
ours / MuJoCo Warp.
"""
import argparse
import json
import math
import os
import time

import numpy as np
import warp as wp

from .peer_cases import CASES
from .plan import ExecutionPlan
from .simulator import Simulator
from .solver import SolverSettings

def random_states(case, n, seed=0):
    """Joint coordinates (n, joints) of ``case``'s random starts (peer_cases.CASES)."""
    return CASES[case].states(n, seed)[0]


def mjw_steps_per_second(case, num_worlds, steps, dt, device, repeat=1):
    """MuJoCo Warp's world-steps/s: ``steps`` steps as 10-step CUDA graphs, best of ``repeat`` runs."""
    import mujoco
    import mujoco_warp as mjw

    mjm = mujoco.MjModel.from_xml_string(CASES[case].xml(dt))
    mjd = mujoco.MjData(mjm)
    with wp.ScopedDevice(device):
        m = mjw.put_model(mjm)
        d = mjw.put_data(mjm, mjd, nworld=num_worlds)
        d.qpos.assign(CASES[case].mujoco_qpos(random_states(case, num_worlds)).astype(np.float32))
        mjw.step(m, d)  # compile
        wp.synchronize()
        graph = None
        if wp.get_device(device).is_cuda:
            with wp.ScopedCapture() as capture:
                for _ in range(10):
                    mjw.step(m, d)
            graph = capture.graph
        reps = max(1, steps // 10)
        best = math.inf
        for _ in range(repeat):
            t0 = time.perf_counter()
            for _ in range(reps):
                if graph is not None:
                    wp.capture_launch(graph)
                else:
                    for _ in range(10):
                        mjw.step(m, d)
            wp.synchronize()
            best = min(best, time.perf_counter() - t0)
        return num_worlds * reps * 10 / best


def fastest_run(sim, x0, steps: int, repeat: int) -> float:
    """Seconds of the fastest of ``repeat`` runs of ``sim.step(steps)``, each restarted from the joint
    states ``x0`` and timed between device synchronisations (a short run on a GPU varies with clocks
    and whatever ran before it)."""
    best = math.inf
    for _ in range(repeat):
        sim.set_joint_state(x0)
        wp.synchronize_device(sim.device)
        t0 = time.perf_counter()
        sim.step(steps)
        wp.synchronize_device(sim.device)
        best = min(best, time.perf_counter() - t0)
    return best


def ours_steps_per_second(case, num_worlds, steps, dt, device, dtype="float32", repeat=1, **sim_kwargs):
    """Throughput: ``steps`` steps launched back to back (a CUDA graph each on a GPU), one
    synchronisation at the end; the best of ``repeat`` such runs (each restarted from the same
    states: a short run on a GPU varies with clocks and whatever ran before it).
    Returns (world-steps/s, joint residual [m], bytes per world, the fused step's scratch layout)."""
    sim = Simulator(CASES[case].scene(), num_worlds=num_worlds, dt=dt, device=device, dtype=dtype, **sim_kwargs)
    x0 = random_states(case, num_worlds)
    sim.set_joint_state(x0)
    sim.step(3)
    sps = num_worlds * steps / fastest_run(sim, x0, steps, repeat)
    return sps, float(sim.joint_violation().max()), sim.memory_bytes()["total"] / num_worlds, sim.plan.scratch


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m abd_gym.bench compare", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--worlds", default=None)
    ap.add_argument("--steps", type=int, default=None)
    ap.add_argument("--dt", type=float, default=0.01)
    ap.add_argument("--ours-only", default=None, help="world counts run in abd_gym alone (default 1048576 on GPU)")
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--scratch", default="auto", help="comma-separated layouts of our fused step: auto (the "
                    "simulator's default), global, shared, lanes (each timed against the same MuJoCo Warp run)")
    ap.add_argument("--repeat", type=int, default=3, help="time each engine this many times and keep its fastest")
    ap.add_argument("--integrator", default=None, help="our integrator: bdf2 or implicit_euler (default: the "
                    "simulator's)")
    ap.add_argument("--out", default="bench_out")
    args = ap.parse_args(argv)
    gpu = args.device.startswith("cuda")
    worlds = [int(w) for w in args.worlds.split(",")] if args.worlds else ([1024, 16384, 131072] if gpu else [1, 8])
    alone = args.ours_only if args.ours_only is not None else ("1048576" if gpu else "")
    alone = [int(w) for w in alone.split(",") if w]
    steps = args.steps or (100 if gpu else 10)
    integrator = {} if args.integrator is None else {"integrator": args.integrator}
    rows = []
    for case in args.cases.split(","):
        for w in worlds + alone:
            theirs = float("nan")
            if w not in alone:
                try:
                    theirs = mjw_steps_per_second(case, w, steps, args.dt, args.device, repeat=args.repeat)
                except ImportError:
                    pass
            for scratch in args.scratch.split(","):
                plan = ExecutionPlan(scratch=None if scratch == "auto" else scratch)
                ours, residual, mem, scratch = ours_steps_per_second(case, w, steps, args.dt, args.device,
                                                                     repeat=args.repeat, plan=plan, **integrator)
                rows.append(dict(case=case, num_worlds=w, scratch=scratch, abd_gym=ours, mujoco_warp=theirs,
                                 ratio=ours / theirs, joint_residual=residual, memory_bytes_per_world=mem))  # fmt: skip
                print(f"{case:16s} {w:8d} worlds  abd_gym ({scratch}) {ours:14,.0f}  mujoco_warp {theirs:14,.0f} "
                      f"world-steps/s  ratio {ours / theirs:.3f}  residual {residual:.1e} m  {mem:,.0f} B/world",
                      flush=True)  # fmt: skip
    result = dict(device=args.device, device_name=wp.get_device(args.device).name, dt=args.dt, steps=steps,
                  repeat=args.repeat, integrator=args.integrator or SolverSettings.integrator, rows=rows)  # fmt: skip
    lines = [f"Device: {result['device_name']}, dt = {args.dt}, abd_gym's {result['integrator']}", "",
             "| mechanism | worlds | abd_gym step | abd_gym world-steps/s | MuJoCo Warp world-steps/s | ratio "
             "| joint residual [m] | abd_gym memory [B/world] |", "|---|---:|---|---:|---:|---:|---:|---:|"]  # fmt: skip
    for r in rows:
        lines.append(f"| {r['case']} | {r['num_worlds']} | {r['scratch']} | {r['abd_gym']:,.0f} | {r['mujoco_warp']:,.0f} "
                     f"| {r['ratio']:.3f} "
                     f"| {r['joint_residual']:.1e} | {r['memory_bytes_per_world']:,.0f} |")  # fmt: skip
    print("\n".join(lines))
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "compare.json"), "w") as f:
        json.dump(result, f, indent=1)
    return result
