"""The vector env's autoreset on the device: next episodes drawn ahead, applied by a world mask.

A NEXT_STEP autoreset (a world that ended in step t starts its next episode in step t+1) needs
the new episode's initial state in step t+1.  Drawn then on the host, it costs a host round of
NumPy draws, uploads and a dozen launches per step (~400 µs of host time at 1,024 CartPole
worlds on an H100, a third of the env step).  Here every world's *next* initial state is drawn
ahead and kept on the device, and the autoreset is a fixed launch sequence on device arrays (the
mask of last step's ended worlds, these rows), which needs nothing from the host and which a
graph can hold.  A world's next row is drawn again when the host learns that its row was used
(the step after it ended, the same step the device uses the row): an autoreset step returns
neither flag, so that world cannot use its next row before the step after, which the draw's
upload precedes in the stream.

Draws come from a generator the env spawns from its own (``np_random``) at each full reset, in
world order, for every world at that reset and then for the worlds each autoreset used: the same
seed and actions give the same episodes on every backend and device, and ``np_random``'s own
stream (explicit resets) is the same as without autoresets.
"""
from __future__ import annotations

import numpy as np
import warp as wp

from . import rows
from .coordinates import FIXED_CODE


class NextEpisodes:
    """Each world's next initial joint state (``xx``, device (W, 2, max(joints, 1)): coordinates
    and rates) and the device mask of worlds to autoreset in the next step (``pending``, int32)."""

    def __init__(self, sim, draw):
        """``draw(n)`` -> (coordinates, velocities), each (n, num_joints): n fresh episodes."""
        self.sim, self.draw_fn = sim, draw
        m = sim.model
        W, nj = sim.num_worlds, max(m.num_joints, 1)
        self.xx = wp.zeros((W, 2, nj), dtype=m.dtype, device=sim.device)
        self._rows = wp.array(ptr=self.xx.ptr, dtype=m.dtype, shape=(W, 2 * nj), device=sim.device)  # its (W, 2·nj) view
        self.pending = wp.zeros(W, dtype=wp.int32, device=sim.device)
        self._fixed = m.joint_kind_np == FIXED_CODE

    def draw(self, idx: np.ndarray):
        """Draw the next initial state of the worlds ``idx`` (host indices, in world order)."""
        n = len(idx)
        if n == 0:
            return
        m = self.sim.model
        nj = m.num_joints
        x, xd = (np.asarray(a, dtype=np.float64) for a in self.draw_fn(n))
        for name, a in (("coordinates", x), ("velocities", xd)):
            if a.shape != (n, nj) or not np.all(np.isfinite(a)):
                raise ValueError(f"the task's initial {name} must be finite with shape ({n}, {nj}), got {a.shape}")
        # as set_joint_state: a fixed joint's coordinate is 0; a scene without joints has one 0 column
        xx = np.zeros((n, 2, self.xx.shape[2]), dtype=m.np_dtype)
        xx[:, 0, :nj] = np.where(self._fixed[None, :], 0.0, x)
        xx[:, 1, :nj] = xd
        stage = self.sim._stage
        idx_dev = rows.indices(idx, stage, "next_idx")
        src = stage("next_rows", xx.reshape(n, -1), m.dtype)
        # a recorded launch, replayed with the new arguments (a plain launch's argument packing was
        # most of a draw's ~130 µs on the CPU)
        self.sim._replay("next_draw", rows.kernels(m.dtype)["scatter"], (n, self._rows.shape[1]), [self._rows, idx_dev, src])

    def clear(self, idx: np.ndarray):
        """No autoreset pending for the worlds ``idx`` (they were just reset by hand)."""
        if len(idx) == self.pending.shape[0]:
            self.pending.zero_()
        elif len(idx):
            wp.launch(rows.fill_int, dim=len(idx), inputs=[self.pending, rows.indices(idx, self.sim._stage, "next_idx"), 0],
                      device=self.sim.device)  # fmt: skip

    def apply(self):
        """Start the pending worlds' next episodes (device launches only)."""
        self.sim.set_joint_state_where(self.pending, self.xx)

    def mask(self, xp):
        """The pending mask as a backend bool array (Torch: on the device; NumPy: on the host, from
        the CPU array's memory or by a copy from the GPU, which waits for it)."""
        if xp is np:
            return (self.sim._host_view(self.pending) if self.sim.device.is_cpu else self.pending.numpy()) != 0
        return self.sim._out(self.pending, "torch") != 0

    def set_pending(self, done):
        """The worlds that ended in this step (a backend bool array) autoreset in the next one."""
        if not isinstance(done, np.ndarray):
            self.sim._out(self.pending, "torch").copy_(done)
        elif self.sim.device.is_cpu:
            self.sim._host_view(self.pending)[...] = done
        else:
            self.pending.assign(done.astype(np.int32))
