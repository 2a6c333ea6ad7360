"""Benchmark: one ``gym.make`` env on the CPU against Gymnasium's own env of the same task.

    python -m abd_gym.bench single [--steps 5000] [--rounds 3] [--ids CartPole-v0,...] [--clock wall|process]
                                   [--out DIR]

What a ``gym.make`` user, a tutorial or SB3's ``DummyVecEnv`` gets: a single env, Gymnasium's
wrappers included (``TimeLimit``, ``OrderEnforcing``, ``PassiveEnvChecker``), stepped with random
actions (drawn from the action space, seeded) and reset whenever an episode ends, so resets count
as they do in use.  Each abd_gym task is paired with Gymnasium's env of the same task where there
is one (CartPole-v1, Pendulum-v1, Acrobot-v1, and Gymnasium's MuJoCo InvertedPendulum-v5,
InvertedDoublePendulum-v5 and Reacher-v5, whose model files the ``-v5`` tasks are built from).
The two envs run in alternating rounds of ``--steps`` steps in this one process, so a busy
machine slows both alike; each keeps its fastest round (``--clock process`` times this process's
CPU time instead of wall time, for a machine that other work shares).  Columns: steps/s of the abd_gym env,
of its unwrapped env (the wrappers' share), of Gymnasium's env, their ratio, and the episodes
each ended in a round.  Prints a table and writes ``single.json`` to ``--out``.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import time

import gymnasium as gym
import numpy as np

from ..vector.registration import NAMESPACE, TASKS

# Gymnasium's env of the same task, for the abd_gym ids that have one
PEERS = {
    "CartPole-v0": "CartPole-v1",
    "Pendulum-v0": "Pendulum-v1",
    "Acrobot-v0": "Acrobot-v1",
    "InvertedPendulum-v5": "InvertedPendulum-v5",
    "InvertedDoublePendulum-v5": "InvertedDoublePendulum-v5",
    "Reacher-v5": "Reacher-v5",
}


def _make(env_id: str):
    """``gym.make(env_id)``; None where it cannot be made here (e.g. ``mujoco`` missing)."""
    try:
        return gym.make(env_id)
    except (ImportError, gym.error.DependencyNotInstalled, FileNotFoundError) as e:
        print(f"  {env_id}: not made ({type(e).__name__}: {e})")
        return None


class Runner:
    """An env stepped with a fixed sequence of random actions, reset when an episode ends."""

    def __init__(self, env, steps: int, seed: int, clock=time.perf_counter):
        self.env, self.clock = env, clock
        env.action_space.seed(seed)
        self.actions = [env.action_space.sample() for _ in range(steps)]
        env.reset(seed=seed)

    def round(self, env=None, steps: int | None = None) -> tuple:
        """(steps/s, episodes ended) of one pass over the actions (``env``: another layer of the
        same env, e.g. its unwrapped env, which this then truncates where ``TimeLimit`` would, so
        that both reset alike; ``steps``: over the first that many only)."""
        env = env or self.env
        step, reset = env.step, env.reset
        limit = self.env.spec.max_episode_steps if env is not self.env and self.env.spec else None
        actions = self.actions[:steps]
        reset()
        episodes = length = 0
        t0 = self.clock()
        for a in actions:
            _, _, terminated, truncated, _ = step(a)
            length += 1
            if terminated or truncated or length == limit:
                reset()
                episodes += 1
                length = 0
        return len(actions) / (self.clock() - t0), episodes


CLOCKS = {"wall": time.perf_counter, "process": time.process_time}


def time_pair(name: str, steps: int, rounds: int, seed: int = 0, clock: str = "wall") -> dict | None:
    """Best-of-``rounds`` steps/s of abd_gym's ``name`` (wrapped and unwrapped) and of its peer, by
    ``clock`` ("wall", or "process": this process's CPU time, which time other work takes from a
    busy machine's cores does not count)."""
    ours = _make(f"{NAMESPACE}/{name}")
    if ours is None:
        return None
    peer_id = PEERS.get(name)
    peer = _make(peer_id) if peer_id else None
    runners = {"abd_gym": Runner(ours, steps, seed, CLOCKS[clock])}
    if peer is not None:
        runners["gymnasium"] = Runner(peer, steps, seed, CLOCKS[clock])
    for r in runners.values():
        r.round(steps=200)  # warm-up: kernels loaded, graphs captured, first-call checks done
    passes = [("abd_gym", runners["abd_gym"], None), ("unwrapped", runners["abd_gym"], ours.unwrapped)]
    if peer is not None:
        passes.append(("gymnasium", runners["gymnasium"], None))
    best = {}
    for _ in range(rounds):
        for key, runner, env in passes:
            rate, episodes = runner.round(env)
            if rate > best.get(key, (0.0, 0))[0]:
                best[key] = (rate, episodes)
    ours.close()
    if peer is not None:
        peer.close()
    row = {"id": f"{NAMESPACE}/{name}", "steps_per_s": best["abd_gym"][0], "episodes": best["abd_gym"][1],
           "unwrapped_steps_per_s": best["unwrapped"][0], "peer": peer_id if peer is not None else None,
           "peer_steps_per_s": best["gymnasium"][0] if peer is not None else None,
           "peer_episodes": best["gymnasium"][1] if peer is not None else None}  # fmt: skip
    row["ratio"] = row["steps_per_s"] / row["peer_steps_per_s"] if peer is not None else None
    return row


def _table(rows: list) -> str:
    head = f"{'id':36s} {'steps/s':>9s} {'unwrapped':>9s} {'eps':>5s}  {'Gymnasium env':26s} {'steps/s':>9s} {'eps':>5s} {'ratio':>6s}"
    lines = [head, "-" * len(head)]
    for r in rows:
        peer = (f"{r['peer']:26s} {r['peer_steps_per_s']:9,.0f} {r['peer_episodes']:5d} {r['ratio']:6.2f}" if r["peer"]
                else f"{'-':26s} {'':9s} {'':5s} {'':6s}")  # fmt: skip
        lines.append(f"{r['id']:36s} {r['steps_per_s']:9,.0f} {r['unwrapped_steps_per_s']:9,.0f} {r['episodes']:5d}  {peer}")
    return "\n".join(lines)


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo on Linux), else what ``platform`` says."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m abd_gym.bench single", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    ap.add_argument("--ids", default=None, help="comma-separated task names, e.g. CartPole-v0 (default: every task)")
    ap.add_argument("--steps", type=int, default=5000, help="steps a round")
    ap.add_argument("--rounds", type=int, default=3, help="alternating rounds; each env keeps its fastest")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--clock", choices=sorted(CLOCKS), default="wall",
                    help="wall time, or this process's CPU time (steadier on a machine that other work shares)")
    ap.add_argument("--out", default="bench_out")
    args = ap.parse_args(argv)
    import abd_gym  # noqa: F401 (registers the tasks)

    names = args.ids.split(",") if args.ids else list(TASKS)
    unknown = [n for n in names if n not in TASKS]
    if unknown:
        raise SystemExit(f"unknown task(s) {unknown}; tasks: {list(TASKS)}")
    rows = [row for name in names if (row := time_pair(name, args.steps, args.rounds, args.seed, args.clock)) is not None]
    print(_table(rows))
    os.makedirs(args.out, exist_ok=True)
    path = os.path.join(args.out, "single.json")
    meta = {"benchmark": "single", "device": "cpu", "steps": args.steps, "rounds": args.rounds, "seed": args.seed,
            "clock": args.clock,
            "date": time.strftime("%Y-%m-%d"), "machine": cpu_model(),
            "cores": os.cpu_count(), "python": platform.python_version(), "gymnasium": gym.__version__}  # fmt: skip
    with open(path, "w") as f:
        json.dump({**meta, "rows": rows}, f, indent=1)
    print(f"wrote {path}")
    return rows
