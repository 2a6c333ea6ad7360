"""Writes to some worlds' rows of (W, ...) device arrays, done on the device.

Resetting a few worlds must cost what those worlds need, not a round trip of every world's state
through the host: with 131,072 cart-poles a full copy of q, q̇ and their histories is ~100 MB per
reset, more than the physics step itself.  The rows to write travel as (N, ...) arrays with their
world indices and a kernel scatters them.  They travel through :class:`Staging`, which on a GPU
does not make the host wait for the physics already queued.
"""
import functools

import numpy as np
import warp as wp


@wp.func
def world_of(i: int, idx: wp.array(dtype=wp.int32), mask: wp.array(dtype=wp.int32), masked: int):
    """The world a restart kernel's thread i writes: idx[i], or with ``masked`` world i where
    mask[i] != 0; −1: none (the thread returns)."""
    if masked != 0:
        return wp.where(mask[i] != 0, i, -1)
    return idx[i]


@functools.lru_cache(maxsize=None)
def kernels(dtype):
    @wp.kernel
    def scatter(dst: wp.array2d(dtype=dtype), idx: wp.array(dtype=wp.int32), src: wp.array2d(dtype=dtype)):
        i, c = wp.tid()
        dst[idx[i], c] = src[i, c]

    @wp.kernel
    def restart_unwrapped(idx: wp.array(dtype=wp.int32), coord: wp.array2d(dtype=dtype),
                          coord_vel: wp.array2d(dtype=dtype), dt: dtype, unwrapped: wp.array2d(dtype=dtype),
                          x_hist: wp.array2d(dtype=dtype)):  # fmt: skip
        """World idx[i] after its body states were set: its multi-turn coordinate restarts at the
        principal one, with the BDF2 history x^{n−1} = x − dt·ẋ (a joint state set by coordinates
        does this in kinematics.restart, from the given ones)."""
        i, j = wp.tid()
        k = idx[i]
        u = coord[k, j]
        unwrapped[k, j] = u
        x_hist[k, j] = u - dt * coord_vel[k, j]

    vec12 = wp.types.vector(12, dtype)

    @wp.kernel
    def restart_q(idx: wp.array(dtype=wp.int32), q_src: wp.array2d(dtype=vec12), qd_src: wp.array2d(dtype=vec12),
                  dt: dtype, q: wp.array2d(dtype=vec12), qd: wp.array2d(dtype=vec12),
                  q_prev: wp.array2d(dtype=vec12), q_hist: wp.array2d(dtype=vec12), qd_hist: wp.array2d(dtype=vec12),
                  qd_hist2: wp.array2d(dtype=vec12), order3: wp.array2d(dtype=wp.int32),
                  status: wp.array(dtype=wp.int32), fresh: wp.array(dtype=wp.int32)):  # fmt: skip
        """World idx[i] restarts at (q, q̇) = row i: no past (q^{n−1} = q − dt q̇, q̇^{n−1} = q̇^{n−2} = q̇, and
        ``fresh`` SET: its next step is an implicit Euler one, its energy taken anew), status OK."""
        i, b = wp.tid()
        k = idx[i]
        x = q_src[i, b]
        v = qd_src[i, b]
        q[k, b] = x
        qd[k, b] = v
        q_prev[k, b] = x
        q_hist[k, b] = x - dt * v
        qd_hist[k, b] = v
        qd_hist2[k, b] = v
        order3[k, b] = 0
        if b == 0:
            status[k] = 0
            fresh[k] = 3  # solver.kernels.SET: the state was set

    return dict(scatter=scatter, restart_unwrapped=restart_unwrapped, restart_q=restart_q)


def restart(state, idx: wp.array, q, qd, dt: float, model, stage: "Staging") -> None:
    """The worlds idx (N,) restart at q, q̇ (each broadcast to (N, bodies, 12)); see restart_q."""
    N, nb = idx.shape[0], model.num_bodies
    src = [stage(name, np.broadcast_to(a, (N, nb, 12)), model.vec12) for name, a in (("q", q), ("qd", qd))]
    wp.launch(kernels(model.dtype)["restart_q"], dim=(N, nb),
              inputs=[idx, *src, model.dtype(dt), state.q, state.qd, state.q_prev, state.q_hist, state.qd_hist,
                      state.qd_hist2, state.order3, state.status, state.fresh], device=model.device)  # fmt: skip


@wp.kernel
def fill_int(dst: wp.array(dtype=wp.int32), idx: wp.array(dtype=wp.int32), value: wp.int32):
    dst[idx[wp.tid()]] = value


class Staging:
    """Host arrays onto the device, each under a name, valid until that name's next upload but one.

    On a GPU through pinned host memory and an asynchronous copy, into buffers kept from one upload
    to the next: ``wp.array(numpy_array)`` allocated device memory and copied from pageable memory
    each time, which can make the host wait for the work already queued.  Each name has two slots (a
    pinned buffer, a device buffer and an event recorded after the copy): the host writes a slot
    only after the copy that last read it has run, and a kernel that reads a device buffer is
    queued before the copy that overwrites it two uploads later.  On the CPU: rows of a
    persistent array, written in place (a CPU launch has run before the next write)."""

    def __init__(self, device):
        self.device = wp.get_device(device)
        self._slots = {}  # name -> [next slot, [slot, slot]]
        self._views = {}

    def __call__(self, name: str, values: np.ndarray, wp_dtype) -> wp.array:
        """``values`` (N, ...) as a device array of ``wp_dtype`` elements (trailing dimensions of a
        vector or matrix dtype are its elements)."""
        scalar = getattr(wp_dtype, "_wp_scalar_type_", wp_dtype)
        values = np.ascontiguousarray(values, dtype=wp.dtype_to_numpy(scalar))
        inner = len(getattr(wp_dtype, "_shape_", ()))
        shape = values.shape[: values.ndim - inner] if inner else values.shape
        entry = self._slots.setdefault(name, [0, [None, None]])
        k = entry[0]
        entry[0] = 1 - k
        slot = entry[1][k]
        nbytes = values.nbytes
        if slot is None or slot["capacity"] < nbytes:
            if slot is not None and slot["event"] is not None:
                wp.synchronize_event(slot["event"])  # its pinned memory may still be read
            capacity = max(256, 1 << (max(nbytes, 1) - 1).bit_length())
            cpu = self.device.is_cpu
            host = wp.empty(capacity, dtype=wp.uint8, device="cpu", pinned=not cpu)
            slot = entry[1][k] = dict(capacity=capacity, host=host, host_np=host.numpy(),
                                      dev=host if cpu else wp.empty(capacity, dtype=wp.uint8, device=self.device),
                                      event=None if cpu else wp.Event(self.device), recorded=False)  # fmt: skip
        if slot["recorded"]:
            wp.synchronize_event(slot["event"])  # the copy that last read this pinned buffer has run
        slot["host_np"][:nbytes] = values.reshape(-1).view(np.uint8)
        if not self.device.is_cpu and nbytes:
            wp.copy(slot["dev"], slot["host"], count=nbytes)
            wp.record_event(slot["event"])
            slot["recorded"] = True
        key = (name, k, shape, wp_dtype, slot["dev"].ptr)
        view = self._views.get(key)
        if view is None:
            if len(self._views) > 256:  # one per (name, slot, row count) seen: bounded
                self._views.clear()
            view = self._views[key] = wp.array(ptr=slot["dev"].ptr, dtype=wp_dtype, shape=shape, device=self.device)
        return view


def indices(idx: np.ndarray, stage: Staging, name: str = "idx") -> wp.array:
    """World indices (N,) as a device int32 array."""
    return stage(name, np.asarray(idx, dtype=np.int32), wp.int32)


def _rows_view(array: wp.array, scalar):
    """The (W, k) scalar view of a contiguous (W, ...) array of scalars, vectors or matrices."""
    if not array.is_contiguous:
        raise ValueError("row writes need a contiguous array")
    k = int(np.prod(_row_shape(array), dtype=np.int64))
    return wp.array(ptr=array.ptr, dtype=scalar, shape=(array.shape[0], k), device=array.device)


def write(array: wp.array, idx: wp.array, values, np_dtype, stage: Staging) -> None:
    """array[idx] = values for a (W, ...) array (values broadcast to the (N, ...) rows, in the
    array's scalar layout: (N, C, 12) for a (W, C) array of vec12)."""
    N = idx.shape[0]
    if N == 0:
        return
    scalar = wp.float32 if np_dtype == np.float32 else wp.float64
    view = _rows_view(array, scalar)
    src = np.broadcast_to(values, (N,) + _row_shape(array)).astype(np_dtype).reshape(N, view.shape[1])
    src = stage("rows", src, scalar)
    wp.launch(kernels(scalar)["scatter"], dim=(N, view.shape[1]), inputs=[view, idx, src], device=array.device)


def _row_shape(array: wp.array) -> tuple:
    """One row's shape in scalars: array.shape[1:] followed by the element's own shape."""
    return tuple(array.shape[1:]) + tuple(getattr(array.dtype, "_shape_", ()))
