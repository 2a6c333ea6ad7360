"""A vector env step's outcome from the task's hooks, and Gymnasium's batched info layout.

``outcome`` serves the env's host step and the NumPy side of its device-autoreset step; the
Torch device step computes the same in :mod:`abd_gym.vector.device_step` (the task's Torch operations,
then :mod:`abd_gym.vector.kernels`).
"""
from __future__ import annotations

import numpy as np


def batch_info(values: dict, mask: np.ndarray) -> dict:
    """Gymnasium's vector info layout: each per-world array ``key`` with a bool mask ``_key``."""
    info = {}
    for key, v in values.items():
        info[key] = v
        info["_" + key] = mask.copy()
    return info


def failed_mask(env):
    """(N,) bool backend array: the worlds whose solve failed (``Simulator.failed_worlds``)."""
    if env.xp is np:
        mask = np.zeros(env.num_envs, dtype=bool)
        mask[env.sim.failed_worlds()] = True
        return mask
    return env.sim.world_status("torch") != 0


def world_status(env):
    """(N,) int32 backend array (a copy): each world's status code (``Simulator.world_status``,
    abd_gym.WorldStatus)."""
    if env.xp is np:
        return env.sim.world_status()
    return env.sim.world_status("torch").clone()


def substeps(env):
    """(N,) int32 backend array (a copy): the substeps of each world's last physics step
    (``Simulator.substeps``: 1, or 2 or 4 where a failed step was retried)."""
    if env.xp is np:
        return env.sim.substeps()
    return env.sim.substeps("torch").clone()


def energy_gained(env):
    """(N,) bool backend array (a copy): each world's last physics step gained more energy than the
    simulator's energy test allows at 4 substeps too, and was kept (``Simulator.energy_gained``)."""
    if env.xp is np:
        return env.sim.energy_gained()
    return env.sim.energy_gained("torch").clone().bool()


def outcome(env, a, pend=None):
    """Observation, reward, terminated, truncated, failed and info values of the step ``env`` just
    took with the clipped actions ``a``; ``pend``: a backend bool mask of the worlds reset in this
    step (reward 0, neither flag), or None.  A broken world gets a zero observation and reward and
    is terminated (by mask, for every world: asking the device whether any world failed would make
    the host wait for it)."""
    xp = env.xp
    obs = env.observation()
    failed = failed_mask(env) | ~xp.isfinite(obs).all(axis=1)
    reward = env.f32(env.reward(obs, a))
    terminated = env.terminated(obs) | failed
    if env.max_episode_steps is not None:
        truncated = env.episodes.elapsed >= env.max_episode_steps
    else:
        truncated = env.episodes.all_false()
    info_values = dict(env.info(obs), sim_status=world_status(env), sim_substeps=substeps(env),
                       sim_energy_gained=energy_gained(env))  # fmt: skip
    zero = failed
    if pend is not None:
        terminated, truncated, zero = terminated & ~pend, truncated & ~pend, failed | pend
    reward = xp.where(zero, 0.0, reward)
    obs = xp.where(failed[:, None], 0.0, obs)
    return obs, reward, terminated, truncated, failed, info_values
