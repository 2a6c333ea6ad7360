"""Gymnasium's MuJoCo classics in three engines: env-steps per second on one machine.

    python -m abd_gym.envs.bench_classics [--device cuda:0] [--worlds 1024,16384] [--out DIR]

For each task built from Gymnasium's own asset file (``abd_gym/InvertedPendulum-v5``,
``abd_gym/InvertedDoublePendulum-v5``, ``abd_gym/Reacher-v5``):

- abd_gym: the native vector env (torch backend on a GPU), random actions, autoresets included
  (:func:`abd_gym.envs.bench_envs.env_steps_per_second`, best of ``--repeat`` windows);
- Gymnasium: its own env (MuJoCo C, one ``MjData`` per env) in a ``SyncVectorEnv`` of the same size,
  random actions, autoresets included: one process, so one CPU core;
- MuJoCo Warp: the same XML file on the same device, ``frame_skip`` physics steps per env step with
  the file's integrator, replayed as a CUDA graph: the physics alone (no observation, reward or
  reset), so an upper bound on a MuJoCo Warp env.

Writes ``classics.json`` and prints a Markdown table.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import time

import gymnasium as gym
import numpy as np
import warp as wp

from abd_gym.envs.bench_envs import env_steps_per_second

TASKS = ("InvertedPendulum-v5", "InvertedDoublePendulum-v5", "Reacher-v5")


def gymnasium_steps_per_second(task: str, num_envs: int, steps: int, seed: int = 0) -> float:
    """Env-steps/s of Gymnasium's own env ``task`` in a SyncVectorEnv of ``num_envs``."""
    envs = gym.make_vec(task, num_envs=num_envs, vectorization_mode="sync")
    try:
        envs.reset(seed=seed)
        envs.action_space.seed(seed)
        actions = [envs.action_space.sample() for _ in range(steps + 1)]
        envs.step(actions[0])
        t0 = time.perf_counter()
        for a in actions[1:]:
            envs.step(a)
        return num_envs * steps / (time.perf_counter() - t0)
    finally:
        envs.close()


def mujoco_warp_steps_per_second(task: str, num_envs: int, steps: int, device: str, repeat: int = 3, seed: int = 0):
    """(env-steps/s, all finite) of MuJoCo Warp stepping Gymnasium's XML of ``task`` ``frame_skip``
    times per env step, from qpos0 + U(−0.1, 0.1), with zero controls."""
    import mujoco
    import mujoco_warp as mjw

    env = gym.make(task)
    mjm, frame_skip = env.unwrapped.model, env.unwrapped.frame_skip
    env.close()
    rng = np.random.default_rng(seed)
    qpos = mjm.qpos0[None, :] + rng.uniform(-0.1, 0.1, (num_envs, mjm.nq))
    with wp.ScopedDevice(device):
        m = mjw.put_model(mjm)
        d = mjw.put_data(mjm, mujoco.MjData(mjm), nworld=num_envs)
        d.qpos.assign(qpos.astype(np.float32))
        mjw.step(m, d)  # compile
        wp.synchronize()
        graph = None
        if wp.get_device(device).is_cuda:
            with wp.ScopedCapture() as capture:
                for _ in range(frame_skip):
                    mjw.step(m, d)
            graph = capture.graph
        best = math.inf
        for _ in range(repeat):
            t0 = time.perf_counter()
            for _ in range(steps):
                if graph is not None:
                    wp.capture_launch(graph)
                else:
                    for _ in range(frame_skip):
                        mjw.step(m, d)
            wp.synchronize()
            best = min(best, time.perf_counter() - t0)
        finite = bool(np.isfinite(d.qpos.numpy()).all())
    return num_envs * steps / best, finite


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m abd_gym.envs.bench_classics", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--tasks", default=",".join(TASKS))
    ap.add_argument("--worlds", default=None, help="comma-separated env counts (default 1024,16384 on a GPU, 16 on the CPU)")
    ap.add_argument("--steps", type=int, default=None, help="env steps timed per window (abd_gym, MuJoCo Warp)")
    ap.add_argument("--gym-steps", type=int, default=5, help="env steps timed in Gymnasium's SyncVectorEnv")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--engines", default="abd_gym,gymnasium,mujoco_warp")
    ap.add_argument("--out", default="bench_out")
    args = ap.parse_args(argv)
    gpu = args.device.startswith("cuda")
    worlds = [int(w) for w in args.worlds.split(",")] if args.worlds else ([1024, 16384] if gpu else [16])
    steps = args.steps or (200 if gpu else 10)
    engines = set(args.engines.split(","))
    rows = []
    for task in args.tasks.split(","):
        for n in worlds:
            row = dict(task=task, num_envs=n, abd_gym=math.nan, gymnasium=math.nan, mujoco_warp=math.nan,
                       mujoco_warp_finite=None)  # fmt: skip
            if "abd_gym" in engines:
                row["abd_gym"] = env_steps_per_second(f"abd_gym/{task}", n, steps, device=args.device,
                                                      backend="torch" if gpu else "numpy", repeat=args.repeat)
            if "gymnasium" in engines:
                row["gymnasium"] = gymnasium_steps_per_second(task, n, args.gym_steps)
            if "mujoco_warp" in engines:
                try:
                    row["mujoco_warp"], row["mujoco_warp_finite"] = mujoco_warp_steps_per_second(
                        task, n, steps, args.device, args.repeat)
                except ImportError:
                    pass
            rows.append(row)
            print(f"{task:26s} {n:7d} envs  abd_gym {row['abd_gym']:14,.0f}  gymnasium {row['gymnasium']:12,.0f}  "
                  f"mujoco_warp {row['mujoco_warp']:14,.0f} env-steps/s", flush=True)  # fmt: skip
    result = dict(device=args.device, device_name=wp.get_device(args.device).name, cpu=platform.processor() or
                  platform.machine(), steps=steps, gym_steps=args.gym_steps, repeat=args.repeat, rows=rows)  # fmt: skip
    print(table(result))
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "classics.json"), "w") as f:
        json.dump(result, f, indent=1)
    return result


def table(result) -> str:
    lines = [f"Device: {result['device_name']}; Gymnasium on one core of the same host", "",
             "| task | envs | abd_gym env-steps/s | Gymnasium (MuJoCo C) | abd_gym / Gymnasium | MuJoCo Warp physics "
             "| abd_gym / MuJoCo Warp |", "|---|---:|---:|---:|---:|---:|---:|"]  # fmt: skip
    for r in result["rows"]:
        mjw = f"{r['mujoco_warp']:,.0f}" + ("" if r["mujoco_warp_finite"] in (None, True) else " (non-finite)")
        lines.append(f"| {r['task']} | {r['num_envs']:,} | {r['abd_gym']:,.0f} | {r['gymnasium']:,.0f} | "
                     f"{r['abd_gym'] / r['gymnasium']:,.1f}× | {mjw} | {r['abd_gym'] / r['mujoco_warp']:.2f}× |")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
