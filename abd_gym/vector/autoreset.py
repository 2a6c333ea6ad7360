"""The vector env's autoreset on the device: next episodes drawn ahead, applied by a world mask.

A NEXT_STEP autoreset (a world that ended in step t starts its next episode in step t+1) needs
the new episode's initial state in step t+1.  Drawn then on the host, it costs NumPy draws,
uploads and a dozen launches per step, a large part of a small batch's env step.  Here each world keeps a queue of its next ``depth`` initial states on
the device, and the autoreset is two launches on device arrays (the mask of last step's ended
worlds, the queues, each world's count of episodes taken), which need nothing from the host and
which a graph can hold.  The host follows the counts from the ended-world masks it
reads anyway (one step late: the step in which the device takes the row) and tops the queues up
in one upload when a world has used half its queue: an autoreset step returns neither flag, so
a world takes at most one row every two steps, and a queue never runs dry between top-ups.  The
top-up that a step's counts call for is drawn and written at the start of the next step, before
its physics: a draw refused there raises having written nothing (not after a step has run).

Draws come from a generator the env spawns from its own (``np_random``) at each full reset: the
same seed and actions give the same episodes on every backend and device, and ``np_random``'s
own stream (explicit resets) is the same as without autoresets.
"""

import functools
from typing import NamedTuple

import numpy as np
import warp as wp

from ..core import launches, rows
from ..sim.coordinates import FIXED_CODE


DEVICE_ARRAYS = ("queue", "task_queue", "pending", "taken")  # what a snapshot copies from the device
QUEUE_ROWS = 1 << 21  # the queues' rows in all (each 2·joints values) that a default depth stays under


def default_depth(num_worlds: int) -> int:
    """A queue's depth for ``num_worlds`` worlds: the largest power of two from 8 to 64 whose rows
    in all stay under QUEUE_ROWS (64 up to 32,768 worlds, 8 from 262,144).  Deep queues spare the
    host top-ups, each of which costs it draws, uploads and a launch, in which a small batch's
    device runs dry."""
    fit = QUEUE_ROWS // max(int(num_worlds), 1)
    return int(min(64, max(8, 1 << max(fit.bit_length() - 1, 0))))


class TopUp(NamedTuple):
    """Rows drawn and checked for the queues (NextEpisodes.draw_rows), not yet written: ``counts``
    (W,) rows per world, row ``rows[i]`` of world ``worlds[i]``'s queue holding ``coordinates[i]``,
    ``velocities[i]`` (and ``task[i]``: task values, or None)."""

    counts: np.ndarray
    worlds: np.ndarray
    rows: np.ndarray
    coordinates: np.ndarray
    velocities: np.ndarray
    task: np.ndarray | None


@functools.lru_cache(maxsize=None)
def _take(dtype):
    @wp.kernel
    def take(pending: wp.array(dtype=wp.int32), go: wp.array(dtype=wp.int32), armed: wp.array(dtype=wp.int32),
             taken: wp.array(dtype=wp.int32), queue: wp.array3d(dtype=dtype),
             xx: wp.array3d(dtype=dtype), elapsed: wp.array(dtype=wp.int64), tick: int,
             task_queue: wp.array2d(dtype=dtype), task: wp.array2d(dtype=wp.float32), task_width: int):  # fmt: skip
        """A pending world w's next initial state, row taken[w] mod depth of its queue (queue row
        slot·W + w), into xx[w], and the same row of its task values into task[w] (the env's
        float32 task array; ``task_width`` 0: none); one more taken.  With ``tick``, every
        world's episode clock (elapsed, env steps) too: restarted at 0 where the world is reset,
        else one step on (the Torch backend's clocks, on the device: one launch less a step).
        None of it where go[0] == 0 (a refused step); ``armed``: the worlds to restart now."""
        w = wp.tid()
        if go[0] == 0:
            armed[w] = 0
            return
        armed[w] = pending[w]
        if tick != 0:
            elapsed[w] = wp.where(pending[w] != 0, wp.int64(0), elapsed[w] + wp.int64(1))
        if pending[w] == 0:
            return
        W = pending.shape[0]
        r = (taken[w] % (queue.shape[0] // W)) * W + w
        for k in range(2):
            for c in range(xx.shape[2]):
                xx[w, k, c] = queue[r, k, c]
        for c in range(task_width):
            task[w, c] = wp.float32(task_queue[r, c])
        taken[w] = taken[w] + 1

    return take


class NextEpisodes:
    """Each world's queue of next initial joint states (``queue``, device (depth·W, 2, max(joints,
    1)): coordinates and rates, row slot·W + w) and of the task's values for those episodes
    (``task_queue``, (depth·W, task_width), the same rows: a Reacher's target), the device mask of
    worlds to autoreset in the next step (``pending``, int32) and each world's count of rows taken
    (``taken``)."""

    def __init__(self, sim, draw, depth: int | None = None, task_width: int = 0, host_task: bool = False,
                 generator=lambda: None):  # fmt: skip
        """``draw(n, gen)`` -> (coordinates, velocities), each (n, num_joints), and with
        ``task_width`` the task values (n, task_width) too: n fresh episodes from the
        np.random.Generator ``gen``; ``generator()``: the one the queues' top-ups draw from
        (None: none), put back where a draw is refused.
        ``depth``: rows per world's queue (default_depth of the world count when None).
        ``host_task``: the task values stay on the host too (``task_rows``: the NumPy backend's
        task arrays are host memory, which a kernel on a GPU cannot write)."""
        if depth is None:
            depth = default_depth(sim.num_worlds)
        if depth < 4:
            raise ValueError(f"depth must be at least 4 (a top-up at half a queue), got {depth}")
        self.sim, self.draw_fn, self.depth, self.generator = sim, draw, int(depth), generator
        m = sim.model
        W, nj = sim.num_worlds, max(m.num_joints, 1)
        dev = sim.device
        self.queue = wp.zeros((self.depth * W, 2, nj), dtype=m.dtype, device=dev)
        self._rows = wp.array(ptr=self.queue.ptr, dtype=m.dtype, shape=(self.depth * W, 2 * nj), device=dev)  # (rows, 2·nj)
        self.xx = wp.zeros((W, 2, nj), dtype=m.dtype, device=dev)  # the pending worlds' states, taken
        self.pending = wp.zeros(W, dtype=wp.int32, device=dev)
        self.armed = wp.zeros(W, dtype=wp.int32, device=dev)  # the pending worlds that restart in this step (go)
        self._go_all = wp.ones(1, dtype=wp.int32, device=dev)
        self.taken = wp.zeros(W, dtype=wp.int32, device=dev)
        self._taken = np.zeros(W, dtype=np.int64)  # the host's count, from the masks it reads
        self._drawn = np.zeros(W, dtype=np.int64)
        self._fixed = m.joint_kind_np == FIXED_CODE
        self._no_clock = None  # apply's stand-in clock array, when the host keeps the clocks
        self.task_width = int(task_width)
        # (1, 1) stand-ins where there are no task values (a kernel's array cannot be None here)
        self.task_queue = wp.zeros((self.depth * W if task_width else 1, max(self.task_width, 1)), dtype=m.dtype,
                                   device=dev)  # fmt: skip
        self._no_task = wp.zeros((1, 1), dtype=wp.float32, device=dev)
        self._task_host = np.zeros((self.depth * W, self.task_width), np.float32) if task_width and host_task else None
        self._stage = rows.Staging(dev)  # the top-ups' rows to the device without waiting for it
        self._cmds = {}  # the queues' recorded launches (launches.replay)

    def restart(self, drawn: "TopUp"):
        """Fresh queues for every world (after a full reset): ``drawn`` is ``draw_rows(gen,
        fresh=True)``'s, from the env's new generator."""
        self.taken.zero_()
        self._taken[:] = 0
        self._drawn[:] = 0
        self._write(drawn)

    def took(self, mask: np.ndarray):
        """The worlds of the host bool ``mask`` (W,) took a row in this step (the host learns it from
        the ended-world mask); counted only: ``top_up`` draws the rows they call for."""
        self._taken += mask

    def top_up(self):
        """Top the queues up once some world has used half of its own (the counts ``took`` left):
        called by the env's step before its physics, so that a refused draw (``draw_rows``: the
        generator put back, nothing written) leaves the step unrun.  The rows are those the end of
        the last step would have drawn: the counts and the generator are the same."""
        if (self._drawn - self._taken).min() <= self.depth // 2:
            drawn = self.draw_rows(self.generator())
            if drawn is not None:
                self._write(drawn)

    def draw_rows(self, gen, fresh: bool = False, limits: dict | None = None) -> "TopUp | None":
        """Draw from ``gen`` and check every world's missing rows (world w: taken + depth − 1 − drawn
        of them; ``fresh``: every queue empty, as ``restart`` leaves it), written nowhere; None
        where none is missing.  Round j draws row drawn + j of each world still short, in world
        order.  A queue holds at most depth − 1 rows ahead: the slot left is the row last taken, so
        a top-up made while the host counts one row too many for a world (a step the device
        refused, which the host learns a call late and takes back: vector_env) never overwrites
        the row the world takes next.  The rows are checked as set_joint_state checks them (limits,
        rates, a closed loop closed), against ``limits`` ({limited joint: (lower (W,), upper
        (W,))}, a reset's written after the check) where given, else those in force; a refused
        draw puts ``gen``'s state back and raises."""
        W, K = len(self._taken), self.depth
        taken, drawn_rows = (np.zeros(W, np.int64),) * 2 if fresh else (self._taken, self._drawn)
        short = taken + K - 1 - drawn_rows
        rounds = int(short.max())
        if rounds <= 0:
            return None
        worlds = [np.flatnonzero(short > j) for j in range(rounds)]
        w = np.concatenate(worlds)
        e = np.concatenate([drawn_rows[ws] + j for j, ws in enumerate(worlds)])
        nj, n = self.sim.model.num_joints, len(w)
        saved = None if gen is None else gen.bit_generator.state  # (a new dict)
        try:
            drawn = [np.asarray(a, dtype=np.float64) for a in self.draw_fn(n, gen)]
            x, xd = drawn[:2]
            task = drawn[2] if self.task_width else None
            for name, a, shape in (("coordinates", x, (n, nj)), ("velocities", xd, (n, nj)),
                                   ("task values", task, (n, self.task_width))):  # fmt: skip
                if a is not None and (a.shape != shape or not np.all(np.isfinite(a))):
                    raise ValueError(f"the task's initial {name} must be finite with shape {shape}, got {a.shape}")
            try:  # a round at a time
                start = 0
                for ws in worlds:
                    rows_at = None if limits is None else {k: (lo[ws], up[ws]) for k, (lo, up) in limits.items()}
                    self.sim.check_joint_state(x[start:start + len(ws)], xd[start:start + len(ws)], worlds=ws,
                                               limits=rows_at)  # fmt: skip
                    start += len(ws)
            except ValueError as err:
                raise ValueError(f"the task's initial state: {err}") from None
        except (TypeError, ValueError):
            if gen is not None:
                gen.bit_generator.state = saved
            raise
        return TopUp(np.maximum(short, 0), w, e, x, xd, task)

    def _write(self, drawn: "TopUp"):
        """``draw_rows``' rows into the queues (one upload each), counted drawn."""
        W, K = len(self._taken), self.depth
        m = self.sim.model
        w, e, n = drawn.worlds, drawn.rows, len(drawn.worlds)
        self._drawn += drawn.counts
        # as set_joint_state: a fixed joint's coordinate is 0; a scene without joints has one 0 column
        xx = np.zeros((n, 2, self.queue.shape[2]), dtype=m.np_dtype)
        xx[:, 0, :m.num_joints] = np.where(self._fixed[None, :], 0.0, drawn.coordinates)
        xx[:, 1, :m.num_joints] = drawn.velocities
        stage = self._stage
        idx_dev = rows.indices((e % K) * W + w, stage, "queue_idx")
        src = stage("queue_rows", xx.reshape(n, -1), m.dtype)
        launches.replay(self._cmds, "queue_top_up", rows.kernels(m.dtype)["scatter"], (n, self._rows.shape[1]),
                        [self._rows, idx_dev, src], self.sim.device)  # fmt: skip
        if self.task_width:
            src = stage("queue_task_rows", drawn.task, m.dtype)
            launches.replay(self._cmds, "queue_task_top_up", rows.kernels(m.dtype)["scatter"], (n, self.task_width),
                            [self.task_queue, idx_dev, src], self.sim.device)  # fmt: skip
            if self._task_host is not None:
                self._task_host[(e % K) * W + w] = drawn.task

    def task_rows(self, mask: np.ndarray) -> np.ndarray:
        """The task values (n, task_width) that the worlds of the host bool ``mask`` take in this
        step (host_task), read before ``took`` counts the rows."""
        w = np.flatnonzero(mask)
        return self._task_host[(self._taken[w] % self.depth) * len(self._taken) + w]

    def clear(self, idx: np.ndarray):
        """No autoreset pending for the worlds ``idx`` (they were just reset by hand)."""
        if len(idx) == self.pending.shape[0]:
            self.pending.zero_()
        elif len(idx):
            wp.launch(rows.fill_int, dim=len(idx), inputs=[self.pending, rows.indices(idx, self._stage, "clear_idx"), 0],
                      device=self.sim.device)  # fmt: skip

    def apply(self, elapsed: wp.array | None = None, task: wp.array | None = None, go: wp.array | None = None):
        """Start the pending worlds' next episodes: two launches on device arrays, for every world
        whether pending or not (a graph holds them with no condition: a conditional node and the
        launches it guarded cost more than these two do on the worlds with nothing to do).
        ``elapsed``: the episode clocks (int64 (W,)) to tick in the same launch; ``task``: the
        env's task values (float32 (W, task_width)) to write there too (else left to the host:
        ``task_rows``); ``go`` (int32 (1,)): nothing happens while go[0] == 0 (the vector env's
        refused step, with no conditional node around these launches)."""
        sim = self.sim
        if elapsed is None and self._no_clock is None:
            self._no_clock = wp.zeros(1, dtype=wp.int64, device=sim.device)
        launches.replay(self._cmds, "queue_take", _take(sim.model.dtype), sim.num_worlds,
                        [self.pending, self._go_all if go is None else go, self.armed, self.taken, self.queue, self.xx,
                         self._no_clock if elapsed is None else elapsed, int(elapsed is not None), self.task_queue,
                         self._no_task if task is None else task, 0 if task is None else self.task_width],
                        sim.device)  # fmt: skip
        sim.set_joint_state_where(self.armed, self.xx)

    def mask(self, xp):
        """The pending mask as a backend bool array (Torch: on the device; NumPy: on the host, from
        the CPU array's memory or by a copy from the GPU, which waits for it)."""
        if xp is np:
            return (self.sim.host_view(self.pending) if self.sim.device.is_cpu else self.pending.numpy()) != 0
        return self.sim.view(self.pending, "torch") != 0

    def set_pending(self, done):
        """The worlds that ended in this step (a backend bool array) autoreset in the next one."""
        if not isinstance(done, np.ndarray):
            self.sim.view(self.pending, "torch").copy_(done)
        elif self.sim.device.is_cpu:
            self.sim.host_view(self.pending)[...] = done
        else:
            self.pending.assign(done.astype(np.int32))

    def bookmark(self) -> np.ndarray:
        """The host's count of rows each world has taken (to ``rewind`` to)."""
        return self._taken.copy()

    def rewind(self, taken: np.ndarray):
        """Set the host's counts back to a ``bookmark`` (a step that the device refused and the host
        counted, learning of the refusal a call late; the device's counts never moved)."""
        self._taken[...] = taken

    def snapshot(self) -> dict:
        """Host copies of the queues, the pending mask and the counts (device and host)."""
        snap = {name: getattr(self, name).numpy().copy() for name in DEVICE_ARRAYS}
        snap.update(taken_host=self._taken.copy(), drawn=self._drawn.copy())
        if self._task_host is not None:
            snap["task_host"] = self._task_host.copy()
        return snap

    def restore(self, snap: dict):
        """``snapshot``'s values back into queues of the same shapes."""
        for name in DEVICE_ARRAYS:
            getattr(self, name).assign(snap[name])
        self._taken, self._drawn = snap["taken_host"].copy(), snap["drawn"].copy()
        if "task_host" in snap:
            self._task_host = snap["task_host"].copy()
