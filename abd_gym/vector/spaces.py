"""The vector env's batching: its spaces, the actions it accepts and its autoreset modes.

Actions lie in ``[-b, b]`` per action entry (``Box``, float32; the task's ``action_bound`` b, 1 unless
a task sets it); observations are
float32 within finite symmetric bounds; the batched spaces add a leading ``num_envs`` axis.
"""
from __future__ import annotations

import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space

from .arrays import is_torch, to_numpy
from ..sim.inputs import REAL_KINDS, real_values


def autoreset_mode(mode) -> AutoresetMode:
    """``mode`` (an AutoresetMode, or its value or name) as an AutoresetMode."""
    if isinstance(mode, AutoresetMode):
        return mode
    for m in AutoresetMode:
        if str(mode) in (m.value, m.name):
            return m
    raise ValueError(f"autoreset_mode must be one of {[m.name for m in AutoresetMode]}, got {mode!r}")


def make_spaces(action_dim: int, observation_high, num_envs: int, action_bound: float = 1.0):
    """(single action space, single observation space, action space, observation space): actions
    ``Box(-action_bound, action_bound, (action_dim,))``, observations ``Box(-high, high)``, float32,
    and their batches."""
    high = np.asarray(observation_high, dtype=np.float32)
    if not np.all(np.isfinite(high)) or np.any(high <= 0):
        raise ValueError(f"observation bounds must be positive and finite, got {high}")
    single_action = spaces.Box(-action_bound, action_bound, shape=(action_dim,), dtype=np.float32)
    single_obs = spaces.Box(-high, high, dtype=np.float32)
    return single_action, single_obs, batch_space(single_action, num_envs), batch_space(single_obs, num_envs)


def real_actions(actions) -> np.ndarray:
    """``actions`` (array-like; a Torch tensor copied to the host) as a NumPy array of real numbers,
    unconverted: a TypeError naming them for complex, bool, object or string values
    (inputs.real_values), which a cast to float32 would take in silence or with NumPy's warning."""
    a = to_numpy(actions) if is_torch(actions) else actions
    if type(a) is np.ndarray and a.dtype.kind in REAL_KINDS:
        return a
    return real_values("actions", a)


def prepare_actions(actions, arrays, num_envs: int, action_dim: int, check: bool = True, bound: float = 1.0):
    """The action batch as a float32 backend array (N, action_dim) (``arrays``: the env's Backend);
    with ``check``, clipped to [-bound, bound], and a batch with NaN raises here (which, for a Torch tensor
    on a GPU, waits for the device); without, left to the device's check."""
    N, d = num_envs, action_dim
    xp = arrays.xp
    if xp is np:
        a = np.array(real_actions(actions), dtype=np.float32)
    else:
        if not is_torch(actions):
            a = xp.as_tensor(np.asarray(real_actions(actions), dtype=np.float32))
        elif actions.dtype.is_complex or actions.dtype == xp.bool:
            raise TypeError(f"actions must be real numbers (integer or float), got dtype {actions.dtype}")
        else:
            a = actions
        a = a.to(device=arrays.torch_device, dtype=xp.float32)
    if tuple(a.shape) != (N, d):
        if a.ndim == 1 and d == 1 and a.shape[0] == N:
            a = a.reshape(N, 1)
        else:
            raise ValueError(f"actions must have shape ({N}, {d}), got {tuple(a.shape)}")
    if not check:
        return a  # checked and clipped on the device
    nan = xp.isnan(a)
    if bool(nan.any()):
        worlds = np.flatnonzero(to_numpy(nan).any(axis=1))
        raise ValueError(f"actions contain NaN in worlds {worlds.tolist()[:10]}; nothing was stepped "
                         "(replace or mask NaN actions before calling step)")  # fmt: skip
    return xp.clip(a, -bound, bound)
