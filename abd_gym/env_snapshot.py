"""A vector env's state as host values, and that state put back into a rebuilt env.

Pickling or deep-copying an :class:`~abd_gym.vector_env.ABDVectorEnv` rebuilds it from its
constructor arguments (a fresh simulator, kernels from Warp's cache) and then restores, by
``restore``, what ``capture`` took from the original:

* the simulator's per-step arrays (``State``: body coordinates and rates, BDF2 history,
  joint coordinates, controls, status, ...) and each world's clock;
* the per-world physical parameters in force (masses, strength ratios, limits), re-applied
  through the simulator's setters where they were ever randomised;
* the env's episode counters, task values, pending autoresets and the autoreset queues;
* the random generators (``np_random`` and the queues' generator).

A copy then steps as the original does: same observations, rewards and flags, bit for bit.
Device-side machinery (captured graphs, pinned buffers, compiled outcome) is rebuilt on use.
"""
from __future__ import annotations

import numpy as np
import warp as wp

# plain host attributes of the env, copied as they are
ENV_VALUES = ("_np_random", "_np_random_seed", "_next_rng", "_pending", "_has_reset", "_randomize", "_randomized",
              "body_mass", "strength_ratio", "limits")  # fmt: skip
# the autoreset queues (autoreset.NextEpisodes): device arrays, then host arrays
QUEUE_ARRAYS = ("queue", "task_queue", "pending", "taken")
QUEUE_VALUES = ("_taken", "_drawn", "_task_host")


def _host(x) -> np.ndarray:
    """A host copy of a backend or Warp array."""
    if isinstance(x, wp.array):
        return x.numpy().copy()
    if type(x).__module__.startswith("torch"):
        return x.detach().cpu().numpy().copy()
    return np.array(x, copy=True)


def _assign(dst, values: np.ndarray):
    """dst[...] = values in place (a NumPy array, a Torch tensor or a Warp array)."""
    if isinstance(dst, wp.array):
        dst.assign(values)
    elif isinstance(dst, np.ndarray):
        dst[...] = values
    else:
        import torch

        dst.copy_(torch.as_tensor(values, device=dst.device))


def capture(env) -> dict:
    """The state of ``env`` (an ABDVectorEnv) as host values (see the module docstring)."""
    if env._unread or env._pending_in_flight:
        env._pending_now()  # the last GPU step's done mask on the host (raises if it refused NaN actions)
    state = env.sim.state
    snap = {
        "sim": {name: a.numpy().copy() for name, a in vars(state).items() if isinstance(a, wp.array)},
        "time": state.time.copy(),
        "elapsed": _host(env._elapsed),
        "task": _host(env._task),
        "env": {name: getattr(env, name) for name in ENV_VALUES},
    }
    if env._next is not None:
        q = env._next
        snap["queue"] = {name: _host(getattr(q, name)) for name in QUEUE_ARRAYS}
        snap["queue"].update({name: _host(v) for name in QUEUE_VALUES if (v := getattr(q, name)) is not None})
    return snap


def restore(env, snap: dict):
    """Put ``capture``'s values back into ``env``, freshly built with the same constructor arguments."""
    state = env.sim.state
    for name, values in snap["sim"].items():
        getattr(state, name).assign(values)
    state.time[...] = snap["time"]
    _assign(env._elapsed, snap["elapsed"])
    _assign(env._task, snap["task"])  # in place: the task_state attributes view its columns
    for name, value in snap["env"].items():
        setattr(env, name, value)
    if env._randomized:
        _apply_parameters(env)
    if "queue" in snap:
        q = env._next
        for name, values in snap["queue"].items():
            if name in QUEUE_ARRAYS:
                _assign(getattr(q, name), values)
            else:
                setattr(q, name, values)


def _apply_parameters(env):
    """The env's per-world parameters (``body_mass``, ``strength_ratio``, ``limits``) into its
    simulator, every world at once (the setters compute from the nominal values, so the model
    arrays come out as the original's)."""
    sim, free = env.sim, env._free_bodies
    sim.set_body_mass(env.body_mass[:, free], bodies=free)
    if env.scene.num_joints:
        sim.set_joint_strength(env.strength_ratio)
    for k, values in env.limits.items():
        sim.set_limit(k, lower=values[:, 0], upper=values[:, 1], strength=values[:, 2])
