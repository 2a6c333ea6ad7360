"""Writes to some worlds' rows of (W, ...) device arrays, done on the device.

Resetting a few worlds must cost what those worlds need, not a round trip of every world's state
through the host: with 131,072 cart-poles a full copy of q, q̇ and their histories is ~100 MB per
reset, more than the physics step itself.  The rows to write travel as (N, ...) arrays with their
world indices and a kernel scatters them.
"""
import functools

import numpy as np
import warp as wp

from .warp_ops import ops


@functools.lru_cache(maxsize=None)
def kernels(dtype):
    vec12 = ops(dtype).vec12

    @wp.kernel
    def scatter_vec12(dst: wp.array2d(dtype=vec12), idx: wp.array(dtype=wp.int32), src: wp.array2d(dtype=vec12)):
        i, c = wp.tid()
        dst[idx[i], c] = src[i, c]

    @wp.kernel
    def scatter_scalar(dst: wp.array2d(dtype=dtype), idx: wp.array(dtype=wp.int32), src: wp.array2d(dtype=dtype)):
        i, c = wp.tid()
        dst[idx[i], c] = src[i, c]

    @wp.kernel
    def restart_unwrapped(idx: wp.array(dtype=wp.int32), coord: wp.array2d(dtype=dtype),
                          coord_vel: wp.array2d(dtype=dtype), given: wp.array2d(dtype=dtype), has_given: int, dt: dtype,
                          unwrapped: wp.array2d(dtype=dtype), x_hist: wp.array2d(dtype=dtype)):  # fmt: skip
        """A set state's multi-turn coordinate (given, else the principal one) and its BDF2 history
        x^{n−1} = x − dt·ẋ."""
        i, j = wp.tid()
        k = idx[i]
        u = coord[k, j]
        if has_given != 0:
            u = given[i, j]
        unwrapped[k, j] = u
        x_hist[k, j] = u - dt * coord_vel[k, j]

    return dict(scatter_vec12=scatter_vec12, scatter_scalar=scatter_scalar, restart_unwrapped=restart_unwrapped)


@wp.kernel
def fill_int(dst: wp.array(dtype=wp.int32), idx: wp.array(dtype=wp.int32), value: wp.int32):
    dst[idx[wp.tid()]] = value


def indices(idx: np.ndarray, device) -> wp.array:
    """World indices (N,) as a device int32 array."""
    return wp.array(np.ascontiguousarray(idx, dtype=np.int32), dtype=wp.int32, device=device)


def write(array: wp.array, idx: wp.array, values, np_dtype) -> None:
    """array[idx] = values for a (W, C) array of scalars or vec12 (values broadcast to (N, C[, 12]))."""
    N = idx.shape[0]
    if N == 0:
        return
    scalar = array.dtype in (wp.float32, wp.float64)
    k = kernels(wp.float32 if np_dtype == np.float32 else wp.float64)
    shape = (N, array.shape[1]) if scalar else (N, array.shape[1], 12)
    src = wp.array(np.ascontiguousarray(np.broadcast_to(values, shape), dtype=np_dtype), dtype=array.dtype,
                   device=array.device)  # fmt: skip
    wp.launch(k["scatter_scalar" if scalar else "scatter_vec12"], dim=(N, array.shape[1]), inputs=[array, idx, src],
              device=array.device)  # fmt: skip


def fill(array: wp.array, idx: wp.array, value: int) -> None:
    """array[idx] = value for a (W,) int32 array."""
    if idx.shape[0]:
        wp.launch(fill_int, dim=idx.shape[0], inputs=[array, idx, int(value)], device=array.device)
