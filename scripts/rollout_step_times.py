#!/usr/bin/env python3
"""Where the device rollout's time goes, piece by piece, without synchronising between pieces.

    python scripts/rollout_step_times.py gpu/cartpole_ppo --device cuda:0 --num-envs 4096 \\
        hyperparams.n_steps=16 hyperparams.batch_size=16384 [--rollouts 20] [--json PATH]

(``key=value`` overrides as in ``abd-gym-train``.)  Builds the training env and ``DevicePPO`` as
``abd-gym-train`` does, trains three iterations (compiles, captures), then times ``--rollouts``
calls of ``collect_rollouts`` (no updates between them).  Each piece (the buffer's reset, the
rollout step's ``start``, ``act``, ``env_step``, ``record_act``, ``record``, ``end`` and
``finish``, the callbacks and the flush of finished episodes) is bracketed by a host clock and, on a GPU, a CUDA event on the
current stream, so that the GPU's queue is never drained inside the rollout as the profiler's
synchronised pieces do (``python -m abd_gym.agents.profile``).  Per rollout it prints:

* host [ms]: the host's time in each piece (a graph replay's launch, the env's Python);
* GPU [ms]: the interval between the events that bracket each piece, which holds the piece's
  kernels, or the GPU's idle wait for the host where the host is behind.

The JSON also gives how many times each piece was entered a rollout (``calls``).

The marks cost a few µs of host time each, so the wall time is longer than the profiler's
untimed rollout phase.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from collections import defaultdict
from pathlib import Path

import torch as th
from stable_baselines3.common.callbacks import CallbackList

from abd_gym.agents.common import build_model, build_train_env
from abd_gym.agents.config import validate_config
from abd_gym.agents.train import raw_config_from_args

PIECES = (("rollout_buffer", "reset", "buffer reset"), ("steps", "start", "start"), ("steps", "act", "act"),
          ("steps", "record_act", "record and act"), ("steps", "env_step", "env step"), ("steps", "record", "record"),
          ("steps", "end", "end"),
          ("steps", "finish", "finish"), ("model", "_flush_episodes", "flush"))  # fmt: skip
OTHER = "collect_rollouts, the rest"


class Marks:
    """(name, host time, CUDA event or None) at each piece's entry ("<name") and exit (">name")."""

    def __init__(self, cuda: bool):
        self.cuda = cuda
        self.marks: list[tuple[str, float, th.cuda.Event | None]] = []

    def mark(self, name: str) -> None:
        event = None
        if self.cuda:
            event = th.cuda.Event(enable_timing=True)
            event.record()
        self.marks.append((name, time.perf_counter(), event))

    def bracket(self, obj, attr: str, name: str) -> None:
        fn = getattr(obj, attr)

        def timed(*args, **kwargs):
            self.mark("<" + name)
            out = fn(*args, **kwargs)
            self.mark(">" + name)
            return out

        setattr(obj, attr, timed)

    def intervals(self):
        """(owner, host seconds, GPU seconds or None) of each interval between two marks; the owner
        is the innermost open piece."""
        stack = []
        for (n0, t0, e0), (_, t1, e1) in zip(self.marks, self.marks[1:]):
            if n0.startswith("<"):
                stack.append(n0[1:])
            elif n0.startswith(">"):
                stack.pop()
            yield (stack[-1] if stack else OTHER), t1 - t0, (e0.elapsed_time(e1) * 1e-3 if self.cuda else None)


def rollout_times(cfg: dict, rollouts: int) -> dict:
    cuda = str(cfg["device"]).startswith("cuda")
    sync = th.cuda.synchronize if cuda else (lambda: None)
    env = build_train_env(cfg, rollout="device")
    model = build_model(cfg, env, rollout="device")
    n_steps, n_envs = model.n_steps, env.num_envs
    model.learn(total_timesteps=3 * n_envs * n_steps)
    owners = {"rollout_buffer": model.rollout_buffer, "steps": model._rollout_step, "model": model}
    marks = Marks(cuda)
    for owner, attr, name in PIECES:
        marks.bracket(owners[owner], attr, name)
    callback = CallbackList([])
    callback.init_callback(model)
    marks.bracket(callback, "update_locals", "callbacks")
    marks.bracket(callback, "on_step", "callbacks")
    host, gpu, calls, wall = defaultdict(float), defaultdict(float), defaultdict(int), 0.0
    for k in range(rollouts + 2):  # two more first, untimed
        marks.marks.clear()
        sync()
        marks.mark("begin")
        model.collect_rollouts(model.env, callback, model.rollout_buffer, n_steps)
        marks.mark("end")
        sync()
        if k < 2:
            continue
        wall += marks.marks[-1][1] - marks.marks[0][1]
        for name, _, _ in marks.marks:
            if name.startswith("<"):
                calls[name[1:]] += 1
        for owner, h, g in marks.intervals():
            host[owner] += h
            if g is not None:
                gpu[owner] += g
    env.close()

    def per_rollout(d):
        return {k: 1e3 * v / rollouts for k, v in sorted(d.items(), key=lambda kv: -kv[1])}

    return dict(env_id=cfg["env_id"], n_envs=n_envs, n_steps=n_steps, device=str(cfg["device"]), rollouts=rollouts,
                wall_ms=1e3 * wall / rollouts, rollout_steps_per_s=rollouts * n_envs * n_steps / wall,
                host_ms=per_rollout(host), gpu_ms=per_rollout(gpu) if cuda else None,
                calls={k: v / rollouts for k, v in sorted(calls.items())})  # fmt: skip


def format_times(r: dict) -> str:
    lines = [f"{r['env_id']}, {r['n_envs']} envs, {r['n_steps']} steps a rollout, {r['device']}: "
             f"{r['wall_ms']:.2f} ms a rollout ({r['rollout_steps_per_s']:,.0f} env-steps/s, timed)",
             f"{'piece':<28}{'host ms':>10}{'GPU ms':>10}{'GPU µs/step':>13}"]  # fmt: skip
    for name, h in r["host_ms"].items():
        g = r["gpu_ms"].get(name) if r["gpu_ms"] else None
        per_step = "" if g is None else f"{1e3 * g / r['n_steps']:>13.1f}"
        lines.append(f"{name:<28}{h:>10.3f}{'' if g is None else format(g, '>10.3f')}{per_step}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("config", help="config file, or a name in configs/ (gpu/cartpole_ppo)")
    p.add_argument("overrides", nargs="*", metavar="key=value")
    p.add_argument("--device", help="cpu or cuda:N")
    p.add_argument("--num-envs", type=int)
    p.add_argument("--rollouts", type=int, default=20)
    p.add_argument("--json", help="write the times here")
    args = p.parse_intermixed_args(argv)
    args.seed = args.total_timesteps = args.eval_episodes = None
    raw, _ = raw_config_from_args(args)
    cfg = validate_config({**raw, "rollout": "device"})
    r = rollout_times(cfg, args.rollouts)
    r["command"] = " ".join(["python scripts/rollout_step_times.py", *(sys.argv[1:] if argv is None else argv)])
    print(format_times(r))
    if args.json:
        Path(args.json).write_text(json.dumps(r, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
