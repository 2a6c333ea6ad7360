"""The vector env's arrays in its backend: NumPy on the host, or Torch on the simulator's device.

A task's hooks compute with ``xp`` (``numpy`` or ``torch``) and these helpers, so that one hook
serves both backends.  dtype names: "float" (float32), "int" (int64), "bool".
"""
from __future__ import annotations

import numpy as np
import warp as wp

BACKENDS = ("numpy", "torch")


def is_torch(x) -> bool:
    return type(x).__module__.startswith("torch")


def to_numpy(x) -> np.ndarray:
    """A backend array (or anything array-like) as a host NumPy array (a Torch tensor copied)."""
    if is_torch(x):
        return x.detach().cpu().numpy()
    return np.asarray(x)


def host_copy(x) -> np.ndarray:
    """A host copy of a backend or Warp array."""
    if isinstance(x, wp.array):
        return x.numpy().copy()
    if is_torch(x):
        return x.detach().cpu().numpy().copy()
    return np.array(x, copy=True)


def assign(dst, values: np.ndarray):
    """dst[...] = values in place (a NumPy array, a Torch tensor or a Warp array)."""
    if isinstance(dst, wp.array):
        dst.assign(values)
    elif isinstance(dst, np.ndarray):
        dst[...] = values
    else:
        import torch

        dst.copy_(torch.as_tensor(values, device=dst.device))


class Backend:
    """Array helpers of one backend: ``xp`` (the module) and, for Torch, ``torch_device`` (the
    simulator's device as Torch names it; None for NumPy)."""

    def __init__(self, backend: str, device):
        if backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
        self.name = backend
        if backend == "torch":
            import torch

            self.xp = torch
            self.torch_device = torch.device(wp.device_to_torch(device))
        else:
            self.xp = np
            self.torch_device = None

    def asarray(self, values, dtype="float"):
        """Host values as a backend array (on the simulator's device for Torch)."""
        if self.xp is np:
            return np.asarray(values, dtype={"float": np.float32, "int": np.int64, "bool": bool}[dtype])
        import torch

        dt = {"float": torch.float32, "int": torch.int64, "bool": torch.bool}[dtype]
        return torch.as_tensor(np.asarray(values), dtype=dt, device=self.torch_device)

    def zeros(self, *shape, dtype="float"):
        """A backend array of zeros of ``shape``."""
        return self.asarray(np.zeros(shape), dtype)

    def upload(self, values: np.ndarray):
        """Host values as a tensor on the env's device.  To a GPU through pinned memory and a
        non-blocking copy: a copy from pageable memory makes the host wait for the device's queue
        (the step's physics), which is what a reset in every step would then cost."""
        t = self.xp.from_numpy(np.ascontiguousarray(values))
        if self.torch_device.type == "cuda":
            return t.pin_memory().to(self.torch_device, non_blocking=True)
        return t

    def index(self, idx: np.ndarray):
        """World indices (host int array) as a backend index array."""
        return idx if self.xp is np else self.upload(np.asarray(idx, dtype=np.int64))

    def fill(self, array, idx, value):
        """array[idx] = value (a Python scalar; ``idx`` a backend index array).  Torch's
        ``index_fill_``: ``t[i] = 0.0`` makes a host tensor of the scalar and copies it, which
        waits for the device."""
        if self.xp is np:
            array[idx] = value
        else:
            array.index_fill_(0, idx, value)

    def put(self, array, idx: np.ndarray, values):
        """array[idx] = values (host values into a backend array of the same dtype)."""
        if self.xp is np:
            array[idx] = values
        else:
            array[self.index(idx)] = self.upload(np.asarray(values)).to(array.dtype)

    def f32(self, x):
        """``x`` (a backend array) as float32."""
        return x.astype(np.float32, copy=False) if self.xp is np else x.to(self.xp.float32)

    def copy(self, x):
        """A new backend array equal to ``x``."""
        return x.copy() if self.xp is np else x.clone()
