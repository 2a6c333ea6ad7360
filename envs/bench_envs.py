"""Throughput of the batched task environments.

    python -m abd_gym.envs.bench_envs [--tasks CartPole-v0,Acrobot-v0] [--worlds 1,64] [--steps 100] [--device cpu]
        [--backend numpy|torch] [--scratch auto,global,shared,lanes] [--repeat N] [--out DIR]

:func:`env_steps_per_second` times ``VectorEnv.step`` with random actions (drawn beforehand, on the
env's device for the torch backend), after a reset and one warm-up step, autoresets included.
"""
from __future__ import annotations

import argparse
import math
import time

import gymnasium as gym
import numpy as np
import warp as wp

import abd_gym  # noqa: F401 -- registers the abd_gym/ ids


def env_steps_per_second(task_id: str, num_envs: int, steps: int, device: str | None = "cpu", backend: str = "numpy",
                         seed: int = 0, raw: bool = False, configure=None, repeat: int = 1,
                         simulator_options: dict | None = None):  # fmt: skip
    """World-steps per second (``num_envs × steps / seconds``) of ``steps`` calls of ``step``; with
    ``repeat``, the fastest of ``repeat`` consecutive windows of ``steps`` calls in one env (each
    rate below likewise): on a GPU a small batch's env rate is set by the host's Python, so one
    window's rate varies from run to run with the host's load.

    ``task_id``: a registered id, with or without the ``abd_gym/`` namespace.  ``simulator_options``:
    more Simulator settings for the env (e.g. ``{"plan": ExecutionPlan(scratch="shared")}``).
    ``configure``: called with the unwrapped env before its first step (e.g. to change
    ``env.sim.solver.settings``).  With ``raw``, returns
    ``(env rate, simulator-alone rate, physics-time rate)``:

    - simulator alone: the env's simulator stepped ``frame_skip`` steps per env step by itself, after
      the env run (wall clock; its states differ from the env's, which resets keep near rest);
    - physics time: a second, identically seeded env run with the time of each of its physics
      steps summed: the same states and resets as the env run, but the physics' device time only,
      so an upper bound on the simulator's rate.  With the env's step graph (Torch on a GPU), by
      device timestamps around the physics inside that graph (abd_gym.core.timestamps); else each
      ``sim.step`` call between CUDA events on a GPU (which also time the device's waits for the
      host's launches, so they read longer than the timestamps inside a graph), or by the host
      clock on the CPU.
    """
    if "/" not in task_id:
        task_id = f"abd_gym/{task_id}"

    def run(timed: bool):
        env = gym.make_vec(task_id, num_envs=num_envs, vectorization_mode="vector_entry_point", device=device,
                           backend=backend, simulator_options=simulator_options)  # fmt: skip
        u = env.unwrapped
        if configure is not None:
            configure(u)
        sim, inner = u.sim, u.sim.step
        cuda = wp.get_device(u.device).is_cuda
        stamps = None
        if timed and cuda and u.device_step.use_graph:
            # the step graph holds the physics as sim.launch_step: stamped before and after it in
            # the graph (captured at the second step, so wrapped before the first)
            from abd_gym.core.timestamps import Stamps

            stamps, launch = Stamps(u.device, 2 * steps), sim.launch_step

            def stamped(*args, **kwargs):
                stamps.mark()
                launch(*args, **kwargs)
                stamps.mark()

            sim.launch_step = stamped
        events = [wp.Event(u.device, enable_timing=True) for _ in range(2 * steps)] if timed and cuda else []
        spans = []

        def timed_step(num_steps=1):  # the env's own sim.step, bracketed by timers
            k = len(spans)
            if cuda:
                wp.record_event(events[2 * k])
                inner(num_steps)
                wp.record_event(events[2 * k + 1])
                spans.append((events[2 * k], events[2 * k + 1]))
            else:
                t = time.perf_counter()
                inner(num_steps)
                spans.append(time.perf_counter() - t)

        try:
            env.reset(seed=seed)
            rng = np.random.default_rng(seed)
            shape = env.action_space.shape
            actions = [rng.uniform(-1.0, 1.0, size=shape).astype(np.float32) for _ in range(min(steps, 64))]
            if backend == "torch":
                import torch

                actions = [torch.as_tensor(a, device=u.arrays.torch_device) for a in actions]
            for a in actions[:2]:  # warm-up: kernel loads, then the env's graph capture (on a GPU with Torch)
                env.step(a)
            wp.synchronize_device(u.device)
            elapsed = physics = alone = math.inf
            for _ in range(repeat):
                if stamps is not None:
                    stamps.clear()
                elif timed:
                    spans.clear()
                    sim.step = timed_step
                t0 = time.perf_counter()
                for k in range(steps):
                    env.step(actions[k % len(actions)])
                wp.synchronize_device(u.device)
                elapsed = min(elapsed, time.perf_counter() - t0)
                sim.step = inner  # the simulator alone, below, runs without the event timers
                if stamps is not None:
                    t = stamps.read()
                    if len(t) != 2 * steps:
                        raise RuntimeError(f"expected two stamps per env step, got {len(t)} in {steps} steps")
                    physics = min(physics, float((t[1::2] - t[0::2]).sum()) * 1e-9)
                elif timed:
                    if len(spans) != steps:
                        raise RuntimeError(f"expected one sim.step per env step, timed {len(spans)} in {steps} steps")
                    span = sum(wp.get_event_elapsed_time(a, b) / 1000.0 for a, b in spans) if cuda else sum(spans)
                    physics = min(physics, span)
            if timed:
                for _ in range(repeat):
                    t0 = time.perf_counter()
                    for _ in range(steps):
                        sim.step(u.frame_skip)
                    wp.synchronize_device(u.device)
                    alone = min(alone, time.perf_counter() - t0)
                return elapsed, alone, physics
            return elapsed, None, None
        finally:
            sim.step = inner
            if stamps is not None:
                sim.launch_step = launch
            env.close()

    if not (isinstance(repeat, int) and repeat >= 1):
        raise ValueError(f"repeat must be a positive integer, got {repeat!r}")
    elapsed = run(timed=False)[0]
    if not raw:
        return num_envs * steps / elapsed
    _, alone, physics = run(timed=True)
    return tuple(num_envs * steps / t for t in (elapsed, alone, physics))


def main(argv=None):
    import json
    import os

    from abd_gym.solver.plan import SCRATCHES, ExecutionPlan
    from abd_gym.vector.registration import TASKS

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tasks", default=",".join(TASKS))
    p.add_argument("--worlds", default="1,16,64")
    p.add_argument("--steps", type=int, default=100)
    p.add_argument("--device", default="cpu")
    p.add_argument("--backend", default="numpy", choices=("numpy", "torch"))
    p.add_argument("--scratch", default="auto", help=f"comma-separated fused-step layouts to time: auto (the "
                   f"simulator's default) or {', '.join(SCRATCHES)}")  # fmt: skip
    p.add_argument("--repeat", type=int, default=1, help="keep the fastest of this many windows")
    p.add_argument("--out", default=None, help="folder for envs.json")
    args = p.parse_args(argv)
    rows = []
    print(f"{'task':<28}{'worlds':>8}{'scratch':>9}{'env-steps/s':>16}")
    for task in args.tasks.split(","):
        for n in (int(w) for w in args.worlds.split(",")):
            for scratch in args.scratch.split(","):
                options = None if scratch == "auto" else {"plan": ExecutionPlan(scratch=scratch)}
                sps = env_steps_per_second(task, n, args.steps, args.device, args.backend, repeat=args.repeat,
                                           simulator_options=options)  # fmt: skip
                rows.append(dict(task=task, num_envs=n, scratch=scratch, env_steps_per_second=sps))
                print(f"{task:<28}{n:>8}{scratch:>9}{sps:>16.0f}", flush=True)
    if args.out:
        os.makedirs(args.out, exist_ok=True)
        with open(os.path.join(args.out, "envs.json"), "w") as f:
            json.dump(dict(device=args.device, device_name=wp.get_device(args.device).name, backend=args.backend,
                           steps=args.steps, repeat=args.repeat, rows=rows), f, indent=1)  # fmt: skip


if __name__ == "__main__":
    main()
