"""Where a PPO training iteration's time goes.

    python -m abd_gym.agents.profile configs/cartpole_ppo.yaml [--device cpu|cuda:0] [--num-envs N]
        [--rollouts K] [--rollout both|auto|device|sb3] [--json PATH] [--torch-threads T] [key=value ...]

(``key=value`` overrides as in ``abd-gym-train``).  For each rollout path (``both``: SB3's NumPy
rollout and the device-resident one of :mod:`abd_gym.agents.device_rollout`, where it applies)
the profiler builds the training env (SAME_STEP autoreset for SB3's path, NEXT_STEP for the
device path) and model as ``abd-gym-train`` does, runs one warm-up
iteration, then K PPO iterations timed only at the rollout / update boundaries (the throughputs)
and K more with every piece timed (the table):

* ``env step``: the Gymnasium vector env's own ``step``;
* ``host<->device``: the adapter's conversions around it (tensors to NumPy, info dicts, or
  nothing but reshapes on the device path) and SB3's ``obs_as_tensor``;
* ``policy``: forward passes of the rollout (actions, values, log-probs; V of cut episodes' last
  observations and of the last observation); on the device path the graphed ``RolloutStep.act``
  of a rollout's first step;
* ``buffer add`` and ``GAE``: the rollout buffer's ``add`` (on the device path the graphed
  ``RolloutStep.record``: the transition, flags and episode statistics; between two steps
  ``RolloutStep.record_act``, which runs the next step's policy in the same graph) and
  ``compute_returns_and_advantage`` (on the device path the graphed ``RolloutStep.finish``: the
  last observation's values, then GAE);
* ``rollout other``: the rest of the rollout loop (action clipping, copies of actions to the host,
  callbacks, episode statistics, the timeout bootstrap's bookkeeping);
* ``update``: ``PPO.train`` (all epochs: minibatch gathering, forward, backward, optimiser).

Each timed piece is closed by ``torch.cuda.synchronize()`` and ``wp.synchronize()`` on a GPU, so
the table's sum is slower than the untimed run; the shares are what it is for.  A piece's time
excludes the pieces timed inside it.  Last, the vector env alone steps the same number of steps
with random actions made where its actions live (the last path's env: NEXT_STEP where the device
path is profiled), best of three runs: its step is bound by the host's Python, whose speed
varies from run to run.  A table is printed and JSON written
(default ``runs/profile-<config>-<YYYYmmdd-HHMMSS>.json``).
"""
from __future__ import annotations

import argparse
import contextlib
import sys
import time
from collections import defaultdict
from datetime import datetime
from pathlib import Path
from typing import Any, Callable

import numpy as np

from abd_gym.agents.common import (build_model, build_train_env, device_description, train_autoreset_mode, versions,
    write_json)
from abd_gym.agents.config import validate_config
from abd_gym.agents.device_rollout import DEVICE_PATH, SB3_PATH, device_path_refusal, find_adapter, rollout_path
from abd_gym.agents.train import raw_config_from_args

__all__ = ["profile", "main", "SECTIONS"]

SECTIONS = ("env step", "host<->device", "policy", "buffer add", "GAE", "rollout other", "update")


class _Clock:
    """Exclusive wall time per section (a section's time excludes the sections timed inside it)
    and how many times each section was entered."""

    def __init__(self, sync: Callable[[], None]):
        self.sync = sync
        self.seconds: dict[str, float] = defaultdict(float)
        self.calls: dict[str, int] = defaultdict(int)
        self._stack: list[list[Any]] = []  # [name, start, time of children]

    @contextlib.contextmanager
    def section(self, name: str):
        self.sync()
        self.calls[name] += 1
        self._stack.append([name, time.perf_counter(), 0.0])
        try:
            yield
        finally:
            self.sync()
            _, start, children = self._stack.pop()
            elapsed = time.perf_counter() - start
            self.seconds[name] += elapsed - children
            if self._stack:
                self._stack[-1][2] += elapsed

    def wrap(self, name: str, fn: Callable) -> Callable:
        def timed(*args, **kwargs):
            with self.section(name):
                return fn(*args, **kwargs)

        return timed


def _syncer(device: str) -> Callable[[], None]:
    if not str(device).startswith("cuda"):
        return lambda: None
    import torch
    import warp as wp

    def sync() -> None:
        torch.cuda.synchronize()
        wp.synchronize()

    return sync


@contextlib.contextmanager
def _patched(pairs: list[tuple[Any, str, Any]]):
    """Set ``obj.name = value`` for each triple; restore (or delete the instance attribute) after."""
    saved = []
    for obj, name, value in pairs:
        had = name in getattr(obj, "__dict__", {})
        saved.append((obj, name, had, getattr(obj, name) if had else None))
        setattr(obj, name, value)
    try:
        yield
    finally:
        for obj, name, had, old in reversed(saved):
            if had:
                setattr(obj, name, old)
            else:
                delattr(obj, name)


def _instrument(model, clock: _Clock, fine: bool) -> list[tuple[Any, str, Any]]:
    """(object, attribute, timed replacement) for the pieces of an iteration."""
    pairs = [
        (model, "collect_rollouts", clock.wrap("rollout other", model.collect_rollouts)),
        (model, "train", clock.wrap("update", model.train)),
    ]
    if not fine:
        return pairs
    import stable_baselines3.common.on_policy_algorithm as opa

    adapter = find_adapter(model.env)
    buf, policy = model.rollout_buffer, model.policy
    pairs += [
        (adapter.env, "step", clock.wrap("env step", adapter.env.step)),
        (adapter, "step_wait", clock.wrap("host<->device", adapter.step_wait)),
        (adapter, "step_tensors", clock.wrap("host<->device", adapter.step_tensors)),
        (opa, "obs_as_tensor", clock.wrap("host<->device", opa.obs_as_tensor)),
        (policy, "forward", clock.wrap("policy", policy.forward)),
        (policy, "predict_values", clock.wrap("policy", policy.predict_values)),
        (buf, "add", clock.wrap("buffer add", buf.add)),
        (buf, "compute_returns_and_advantage", clock.wrap("GAE", buf.compute_returns_and_advantage)),
    ]
    steps = getattr(model, "_rollout_step", None)  # the device path's graphed policy and bookkeeping
    if steps is not None:
        pairs += [(steps, "act", clock.wrap("policy", steps.act)), (steps, "record", clock.wrap("buffer add", steps.record)),
                  (steps, "record_act", clock.wrap("buffer add", steps.record_act)),
                  (steps, "finish", clock.wrap("GAE", steps.finish))]  # fmt: skip
    return pairs


def _iterations(model, k: int, clock: _Clock, fine: bool) -> float:
    """Run ``k`` PPO iterations with the pieces timed; the wall time of the whole run."""
    steps = k * model.n_steps * model.env.num_envs
    with _patched(_instrument(model, clock, fine)):
        clock.sync()
        t0 = time.perf_counter()
        model.learn(total_timesteps=steps, reset_num_timesteps=False)
        clock.sync()
        return time.perf_counter() - t0


def profile_path(cfg: dict[str, Any], rollout: str, k: int) -> dict[str, Any]:
    """Profile one rollout path: throughputs (boundary timing) and the per-piece table."""
    env = build_train_env(cfg, rollout=rollout)
    model = build_model(cfg, env, rollout=rollout)
    steps_per_iteration = model.n_steps * env.num_envs
    sync = _syncer(cfg["device"])
    model.learn(total_timesteps=steps_per_iteration)  # warm-up: compile, allocate, reset
    coarse = _Clock(sync)
    wall = _iterations(model, k, coarse, fine=False)
    rollout_s = coarse.seconds["rollout other"]
    fine = _Clock(sync)
    fine_wall = _iterations(model, k, fine, fine=True)
    total = sum(fine.seconds.values())
    sections = {
        name: {"s_per_iteration": fine.seconds[name] / k, "share": fine.seconds[name] / total if total else 0.0,
               "calls_per_iteration": fine.calls[name] / k}
        for name in SECTIONS
    }
    env.close()
    steps = k * steps_per_iteration
    return {
        "autoreset_mode": train_autoreset_mode(rollout).name,
        "steps_per_iteration": steps_per_iteration,
        "train_steps_per_s": steps / wall,
        "rollout_steps_per_s": steps / rollout_s,
        "update_s_per_iteration": coarse.seconds["update"] / k,
        "instrumented_steps_per_s": steps / fine_wall,
        "sections": sections,
    }


def vector_env_rate(cfg: dict[str, Any], rollout: str, steps: int) -> float:
    """The vector env's own env-steps/s with random actions (made on its device), no policy: the
    best of three runs of ``steps`` steps."""
    venv = build_train_env(cfg, rollout=rollout)
    adapter = find_adapter(venv)
    env, n = adapter.env, adapter.num_envs
    space = adapter.action_space
    rng = np.random.default_rng(cfg["seed"])
    obs, _ = env.reset(seed=cfg["seed"])
    torch_device = obs.device if type(obs).__module__.startswith("torch") else None
    if torch_device is not None:
        import torch

        low = torch.as_tensor(space.low, device=torch_device)
        high = torch.as_tensor(space.high, device=torch_device)

        def actions():
            return low + (high - low) * torch.rand((n, *space.shape), device=torch_device)
    else:

        def actions():
            return rng.uniform(space.low, space.high, size=(n, *space.shape)).astype(space.dtype)

    sync = _syncer(cfg["device"])
    for _ in range(10):
        env.step(actions())
    rates = []
    for _ in range(3):
        sync()
        t0 = time.perf_counter()
        for _ in range(steps):
            env.step(actions())
        sync()
        rates.append(steps * n / (time.perf_counter() - t0))
    venv.close()
    return max(rates)


def profile(cfg: dict[str, Any], *, rollouts: int = 5, paths: str = "both") -> dict[str, Any]:
    """Profile ``cfg`` (validated) on the chosen rollout paths; the report as a dict."""
    chosen, reason = rollout_path(cfg)
    if paths == "both":
        todo = [SB3_PATH] + ([DEVICE_PATH] if device_path_refusal(cfg) is None else [])
    elif paths == "auto":
        todo = [chosen]
    else:
        todo = [rollout_path(dict(cfg, rollout=paths))[0]]
    if cfg["algo"] != "ppo":
        raise ValueError(f"the profiler times PPO iterations; {cfg['algo']} is not PPO")
    out: dict[str, Any] = {
        "env_id": cfg["env_id"],
        "n_envs": cfg["n_envs"],
        "device": cfg["device"],
        "device_description": device_description(cfg["device"]),
        "hyperparams": cfg["hyperparams"],
        "iterations": rollouts,
        "default_rollout": chosen,
        "default_rollout_reason": reason,
        "paths": {},
    }
    for path in todo:
        out["paths"][path] = profile_path(cfg, path, rollouts)
    steps = rollouts * next(iter(out["paths"].values()))["steps_per_iteration"] // cfg["n_envs"]
    out["vector_env_steps_per_s"] = vector_env_rate(cfg, todo[-1], steps)
    out["versions"] = versions()
    return out


def format_report(report: dict[str, Any]) -> str:
    paths = list(report["paths"])
    head = f"{'piece':<16}" + "".join(f"{p + ' ms/iter':>16}{'share':>8}" for p in paths)
    lines = [
        f"{report['env_id']} on {report['device_description']}: {report['n_envs']} envs, "
        f"{report['iterations']} iterations per path",
        head,
        "-" * len(head),
    ]
    for name in SECTIONS:
        row = f"{name:<16}"
        for p in paths:
            s = report["paths"][p]["sections"][name]
            row += f"{1e3 * s['s_per_iteration']:>16.2f}{100 * s['share']:>7.1f}%"
        lines.append(row)
    lines.append("-" * len(head))
    for key, label in (("train_steps_per_s", "training"), ("rollout_steps_per_s", "rollout phase")):
        lines.append(f"{label + ' steps/s':<24}" + "".join(f"{report['paths'][p][key]:>16,.0f}{'':>8}" for p in paths))
    lines.append(f"{'autoreset':<24}" + "".join(f"{report['paths'][p]['autoreset_mode']:>16}{'':>8}" for p in paths))
    lines.append(f"{'vector env alone, random actions':<34}{report['vector_env_steps_per_s']:>14,.0f} steps/s")
    lines.append(f"default rollout: {report['default_rollout']} ({report['default_rollout_reason']})")
    return "\n".join(lines)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m abd_gym.agents.profile", description=__doc__.split("\n\n")[0])
    p.add_argument("config", help="config file, or a name in configs/ (cartpole_ppo)")
    p.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides (dotted keys, YAML values)")
    p.add_argument("--device", help="cpu or cuda:N (env and policy)")
    p.add_argument("--num-envs", type=int, help="worlds in the training env (n_envs)")
    p.add_argument("--rollouts", type=int, default=5, help="PPO iterations timed per path (K)")
    p.add_argument("--rollout", choices=("both", "auto", DEVICE_PATH, SB3_PATH), default="both")
    p.add_argument("--json", help="output file (default runs/profile-<config>-<timestamp>.json)")
    p.add_argument("--torch-threads", type=int, default=1, help="CPU threads for torch (0: torch's default)")
    args = p.parse_intermixed_args(argv)
    args.seed = None
    args.total_timesteps = None
    args.eval_episodes = None
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        raw, name = raw_config_from_args(args)
        cfg = validate_config(raw)
    except (ValueError, FileNotFoundError) as exc:
        print(f"profile: error: {exc}", file=sys.stderr)
        return 2
    if args.torch_threads:
        import torch

        torch.set_num_threads(args.torch_threads)
    report = profile(cfg, rollouts=args.rollouts, paths=args.rollout)
    report["command"] = " ".join(["python -m abd_gym.agents.profile", *(sys.argv[1:] if argv is None else argv)])
    print(format_report(report))
    path = Path(args.json) if args.json else Path("runs") / f"profile-{name}-{datetime.now():%Y%m%d-%H%M%S}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json(path, report)
    print(f"written: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
