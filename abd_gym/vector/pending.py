"""NEXT_STEP autoresets' host mask: the worlds that ended in the last step, fetched without waiting.

A world that ends in step t is reset in step t + 1, so step t + 1 needs step t's done mask on the
host.  On a GPU the mask comes by an asynchronous copy to page-locked memory (or the step graph
writes it there itself) and an event that the next step waits on after it has queued its own
physics: the host's work on a step's results overlaps the device's work on the next one.
"""
from __future__ import annotations

import numpy as np
import warp as wp

from .arrays import to_numpy


class Pinned:
    """The page-locked host memory a GPU step talks to the host through (Torch's pinned tensors,
    each with a NumPy view and a Warp array on the GPU over the same memory: under CUDA's unified
    addressing a kernel reads and writes page-locked host memory by its host pointer).

    ``flags`` (3, 2, N): rows done and bad of a step, slots 0 and 1 written by the step graphs
    (vector.kernels' mailed finish_step), slot 2 by a copy; ``mail`` (2, 2) the graphs' slots' device
    pointers of the actions and of the fresh outputs; ``event``: recorded after the step that
    writes the flags.  ``*_np``, ``*_t``, ``*_dev``: the NumPy, Torch and Warp views."""

    def __init__(self, num_envs: int, device):
        import torch

        flags = torch.zeros((3, 2, num_envs), dtype=torch.bool, pin_memory=True)
        mail = torch.zeros((2, 2), dtype=torch.int64, pin_memory=True)
        self.flags_t, self.flags_np, self.event = flags, flags.numpy(), torch.cuda.Event()
        self.mail_t, self.mail_np = mail, mail.numpy().view(np.uint64)  # (mail_t owns the memory)
        self.flags_dev = wp.array(ptr=flags.data_ptr(), dtype=wp.bool, shape=tuple(flags.shape), device=device)
        self.mail_dev = wp.array(ptr=mail.data_ptr(), dtype=wp.uint64, shape=tuple(mail.shape), device=device)


class PendingMask:
    """``mask``: the host bool mask (N,) of worlds to reset at the next step, once fetched.  A step
    checked on the device (the step graph's NaN check) also leaves its verdict: ``unread`` until
    the host has looked, ``refused`` the worlds whose NaN actions made the device refuse it."""

    def __init__(self, num_envs: int, gpu_torch: bool):
        self.num_envs, self.gpu_torch = num_envs, gpu_torch
        self.mask = np.zeros(num_envs, dtype=bool)
        self.pinned = None  # GPU: the Pinned memory the next mask comes through, made on first use
        self.slot = 2  # the slot of the pinned flags that the event's step writes
        self.in_flight = False
        self.unread = False
        self.refused = np.zeros(0, dtype=np.int64)

    def buffers(self, device) -> Pinned:
        """The pinned memory (made once)."""
        if self.pinned is None:
            self.pinned = Pinned(self.num_envs, device)
        return self.pinned

    def fetch(self) -> np.ndarray:
        """The mask of the last step.  On a GPU this waits for the copy of its flags only, which the
        stream finishes before the physics step launched after it."""
        if self.in_flight:
            p = self.pinned
            p.event.synchronize()
            rows = p.flags_np[self.slot]
            self.mask = rows[0].copy()
            if self.unread and rows[1].any():
                self.refused = np.flatnonzero(rows[1])
            self.in_flight = False
        return self.mask

    def defer(self, flags, checked: bool = False, slot: int | None = None, device=None, stream=None):
        """Keep the done mask ``flags`` (with ``checked``: the rows done and bad) as the next step's
        mask without waiting for the device: a non-blocking copy to pinned memory and an event
        recorded on ``stream`` (None: Torch's current stream), which ``fetch`` waits on.  ``slot``:
        the step graph of that slot writes both rows to the pinned memory itself (``flags``
        unused); the copy goes to slot 2, which no graph writes (the first graph step is queued
        before the host reads the copy of the step before it)."""
        if not self.gpu_torch:
            rows = to_numpy(flags)
            self.mask = (rows[0] if checked else rows).copy()
            if checked:
                self.refused = np.flatnonzero(rows[1])
            return
        p = self.buffers(device)
        if slot is None:
            slot = 2
            rows = p.flags_t[slot]
            (rows if checked else rows[0]).copy_(flags, non_blocking=True)
        p.event.record(stream)  # (None: the current stream, which record looks up)
        self.slot = slot
        self.in_flight = True
