"""The vector env's device step (:mod:`abd_gym.vector.device_step`) captured as CUDA graphs and replayed.

Two graphs (slots 0 and 1, replayed in turn), each: the physics (Warp's own capture: its
conditional node on the go flag must not end a Torch capture, whose allocations are tied to the
capture's id) and, nested in it as a child graph (:func:`abd_gym.core.graphs.insert_child_graph`), the
Torch graph of what follows it (captured first), so that a step is one graph launch; where this
Torch or Warp cannot nest it, that graph is replayed after the physics'.  A graph finds the
caller's actions and its fresh outputs by pointers mailed in its slot, and writes its done and
bad rows to its slot of pinned host memory (env_kernels): the host reads step t's rows while step
t + 1 runs, which therefore writes elsewhere.  The graphs hold the task's Python constants as they
were when captured.
"""
from __future__ import annotations

import warp as wp

from . import kernels as env_kernels
from ..core import graphs


class StepGraph:
    """The captured step of a DeviceStep ``ds``: ``pre`` (the Torch graph of the controls, or None
    where the check heads the physics' graph), ``physics`` (the slots' Warp graphs), ``posts`` (their
    Torch graphs where not nested, else None), ``outputs`` (the slots' post outputs) and ``mailed``
    (whether the graphs read the caller's actions by the mailbox)."""

    def __init__(self, ds):
        import torch

        self.ds = ds
        env = ds.env
        self.torch_device = env.arrays.torch_device
        self.pinned = env.pending.buffers(ds.device)
        self.action_buf = torch.zeros((ds.num_envs, env.action_dim), dtype=torch.float32, device=self.torch_device)
        self.replay_stream = None  # Warp's handle of the Torch stream the graphs are replayed on
        self.stream_id = self.torch_stream = None  # that stream's id and Torch object
        self.post_graphs = []  # the Torch graphs nested in the step graphs (kept: their memory)
        self.slot = 0  # the graph (and mailbox and host flags slot) replayed next
        self.side_stream = None  # the graphs' second stream (the autoreset beside the physics)
        self.kept = None  # the action batch the last graph reads (kept until it has)
        # the check's copy of the mailbox (device memory), which the step's last kernel reads
        self.mail_copy = wp.zeros((2, 2), dtype=wp.uint64, device=ds.device)
        self._capture()

    def _capture(self):
        """Capture both slots' graphs (class docstring)."""
        ds = self.ds
        checked = ds.check_on_device
        # the check (one Warp launch, with the default controls) heads the physics' graph and reads
        # the mailed actions: one graph launch and one copy less; Torch operations (a task's own
        # controls, the host-checked path's copy) need Torch's capture, on the actions' copy
        self.mailed = checked and ds.env.default_controls
        self.pre = None
        if not self.mailed:
            self.pre, _ = graphs.capture_torch(self.torch_device, lambda: ds.pre(self.action_buf, checked))
        # the mailed kernels, which no launched step has run, loaded before the capture (a module
        # load is no graph node)
        kernels = [env_kernels.finish_step(True)]
        if self.mailed:
            kernels.append(env_kernels.check_actions(ds.sim.scalar, True, True))
        for kernel in kernels:
            kernel.module.load(ds.device)
        if ds.sim.holds:
            self.side_stream = wp.Stream(ds.device)
        self.physics, self.posts, self.outputs = [], [], []
        # the outcome run once on the captured actions' tensor outside the captures (it only reads):
        # torch.compile specialises on its input and Inductor times a kernel's launch configurations
        # on its first run, which a capture forbids
        ds.outcome(self.action_buf)
        for slot in (0, 1):
            self._capture_slot(slot, checked)

    def _capture_slot(self, slot: int, checked: bool):
        ds, buf, pinned = self.ds, self.action_buf, self.pinned
        mail = self.mail_copy if self.mailed else pinned.mail_dev
        try:
            post, out = graphs.capture_torch(self.torch_device, lambda: ds.post(buf, slot, pinned, mail), keep=True)
            raw = post.raw_cuda_graph()
        except (TypeError, AttributeError, RuntimeError):  # a Torch without keep_graph / raw_cuda_graph
            post, out = graphs.capture_torch(self.torch_device, lambda: ds.post(buf, slot, pinned, mail))
            raw = None

        def step():
            if self.mailed:
                ds.pre(buf, checked, slot, pinned.mail_dev, self.mail_copy)
            ds.physics(True, checked, self.side_stream)
            return raw is not None and graphs.insert_child_graph(ds.device, raw)

        physics, nested = graphs.capture(ds.device, step)
        if raw is not None and not nested:
            post.instantiate()
        # the nested graph's memory (Torch's pool) lives as long as its Torch graph: kept
        self.post_graphs.append(post)
        self.physics.append(physics)
        self.posts.append(None if nested else post)
        self.outputs.append(out)

    def replay(self, a, out=None):
        """The next slot's step graph replayed on Torch's current stream with the actions ``a``;
        returns (the step's packed outputs: ``out``, or else a fresh buffer, that slot's post
        outputs, the slot)."""
        import torch

        slot = self.slot
        self.slot ^= 1
        # the current stream's id by Torch's own query: torch.cuda.current_stream() builds a Stream
        # and resolves the device each call, which a step's host time notices
        sid = torch._C._cuda_getCurrentStream(self.torch_device.index or 0)[0]
        if self.replay_stream is None or self.stream_id != sid:
            ts = torch.cuda.current_stream(self.torch_device)
            self.replay_stream, self.stream_id, self.torch_stream = wp.stream_from_torch(ts), sid, ts
        # the outputs' buffer: fresh from Torch's allocator each step (stream-ordered, as a clone's
        # would be), which the caller keeps, or the caller's own (DeviceStep.fixed_outputs)
        raw = torch.empty(self.ds.out_head, dtype=torch.float32, device=self.torch_device) if out is None else out
        mail = self.pinned.mail_np[slot]
        mail[1] = raw.data_ptr()
        if self.mailed:
            # read by the graph's first kernel: the batch must live until then (kept one call)
            a = a.contiguous()
            mail[0] = a.data_ptr()
            self.kept = a
        else:
            self.action_buf.copy_(a)
        if self.pre is not None:
            self.pre.replay()
        wp.capture_launch(self.physics[slot], stream=self.replay_stream)
        if self.posts[slot] is not None:
            self.posts[slot].replay()
        return raw, self.outputs[slot], slot
