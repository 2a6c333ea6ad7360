"""The vector env's step as device work: NEXT_STEP autoresets on the device, no host reads.

For a task whose episodes start from ``initial_state`` and ``draw_task`` alone and while no
parameters are randomised, the env steps here: the controls (with the NaN check on the device
where ``check_on_device``), the physics and the autoreset of last step's ended worlds
(:mod:`abd_gym.vector.autoreset`), then the outcome (the task's Torch operations, compiled by
torch.compile where ``compile_outcome``, and :mod:`abd_gym.vector.kernels`' bookkeeping) into one
packed output buffer.  With the Torch backend on a GPU and ``use_graph``, the whole step is
captured as graphs and replayed (:mod:`abd_gym.vector.step_graph`).
"""
from __future__ import annotations

import types

import numpy as np
import warp as wp

from . import kernels as env_kernels, step_graph
from .outcome import batch_info, outcome


# Inductor writes a value out once it is read more than realize_reads_threshold times (default 4);
# a task's observation, read by its reward and termination column by column, is then a kernel of
# its own.  Inlined into its readers instead, it fuses into the kernel that writes the packed
# outcome, so that a task's outcome takes fewer kernels
INDUCTOR_OPTIONS = {"realize_reads_threshold": 64, "realize_opcount_threshold": 1000}


def _own_code(method):
    """The bound ``method`` on a copy of its function's code object.  torch.compile keeps a
    function's compiled versions on its code object, which every env (every task, every size)
    would share, up to ``torch._dynamo.config.recompile_limit`` (8), after which new ones run
    uncompiled: a later env of one process would fall back to its eager outcome."""
    f = method.__func__
    g = types.FunctionType(f.__code__.replace(), f.__globals__, f.__name__, f.__defaults__, f.__closure__)
    return types.MethodType(g, method.__self__)


def _can_compile() -> bool:
    """Whether torch.compile can make GPU kernels here (Inductor's Triton backend)."""
    try:
        from torch.utils._triton import has_triton

        return bool(has_triton())
    except ImportError:
        return False


class DeviceStep:
    """The device step of ``env`` (an ABDVectorEnv), with its settings:

    * ``use_graph``: the step replayed as graphs (Torch on a GPU with autoresets on the device);
      the simulator's one-launch step is then built to hold worlds (``Solver.holds``);
    * ``check_on_device``: the actions' NaN check runs on the device (with the step graph, where
      Warp has conditional graph nodes): a refused batch steps nothing, and the next call raises
      (``pending_now``), having taken back the host's bookkeeping (``take_back``);
    * ``compile_outcome``: the task's outcome compiled by torch.compile.

    Its device arrays (``buffers``): the go flag (int32 (1,), 1 steps, 0 refuses, sticky until the
    host reads why) and the step's outputs packed in one byte buffer ``out_raw``."""

    def __init__(self, env, graph: bool | None, compile_outcome: bool | None):
        self.env, self.sim, self.next = env, env.sim, env.next_episodes
        self.xp, self.num_envs, self.device = env.xp, env.num_envs, env.device
        cuda_torch = env.xp is not np and env.device.is_cuda
        if graph and not (cuda_torch and self.next is not None):
            raise ValueError("graph=True needs the Torch backend on a CUDA device and NEXT_STEP autoresets of a task "
                             "without _reset_task")  # fmt: skip
        self.use_graph = cuda_torch and self.next is not None if graph is None else bool(graph)
        # the step graph runs the autoreset beside the physics, which then holds the pending worlds
        # (physics): where the step is one launch, its kernel is built with that check
        if self.use_graph:
            self.sim.enable_hold()
        # a host check would make the host wait for the device each step
        self.check_on_device = self.use_graph and wp.is_conditional_graph_supported()
        # the task's observation, reward and termination (a dozen one-line Torch operations, each a
        # kernel of the step graph) compiled into a few fused kernels; by default with the step
        # graph only (the compile takes seconds; op by op the host's launches, not the device's
        # kernels, are what a step waits for)
        if compile_outcome and env.xp is np:
            raise ValueError("compile_outcome=True needs the Torch backend")
        self.compile_outcome = self.use_graph and _can_compile() if compile_outcome is None else bool(compile_outcome)
        self.outcome_fn = None
        self.graph = None  # the StepGraph, captured at the second step
        self.warm = False  # a step has run (every kernel loaded)
        self.go = None
        self.undo = None  # a step checked on the device: the host's bookkeeping before it
        self.arrays = None  # Warp views of the buffers, by name (buffers)
        self.fixed = None  # the caller's buffer for every step's packed outputs (fixed_outputs), or None
        self.fixed_views = self.fixed_status = None  # unpack(fixed) and status_of(fixed), handed back by every step

    # ------------------------------------------------------------------ buffers
    def buffers(self):
        """The Torch path's arrays, made once (Torch tensors and Warp views of them): the go flag
        and the step's outputs packed in one byte buffer: observations and rewards (float32, the
        observations' rows then the rewards), then the flags' rows terminated, truncated, failed,
        done and bad (a NaN action)."""
        if self.go is not None:
            return
        torch, env = self.xp, self.env
        N, d = self.num_envs, env.single_observation_space.shape[0]
        dev = env.arrays.torch_device
        self.go = wp.ones(1, dtype=wp.int32, device=self.device)
        # one buffer (4-byte words: the observations' and rewards' float32, the status' int32; the
        # flags' bytes after them), so that one clone of its head copies every output returned
        F = 4 * N * (d + 2)
        self.out_raw = torch.zeros(-(-(F + 5 * N) // 4), dtype=torch.float32, device=dev)
        self.out_head = -(-(F + 3 * N) // 4)
        obs, reward = self.unpack(self.out_raw, 0)
        self.out_b = self.out_raw.view(torch.uint8)[F: F + 5 * N].view(torch.bool).view(5, N)
        ep = env.episodes
        self.arrays = dict(scale=wp.from_torch(env.action_scale), obs=wp.from_torch(obs),
                           reward=wp.from_torch(reward), status=wp.from_torch(self.status_of(self.out_raw)),
                           flags=wp.from_torch(self.out_b),
                           bad=wp.from_torch(self.out_b[4]), elapsed=wp.from_torch(ep.elapsed),
                           task=wp.from_torch(ep.task) if ep.task_width else None)  # fmt: skip

    def fixed_outputs(self):
        """Views (observations, rewards, terminated, truncated) of one buffer that every later step
        writes its outputs into and returns, in place of a fresh buffer each step (Torch only); the
        info values are then handed back uncopied too (a graph slot's, rewritten two steps later).
        A caller that reads each step's outputs before the next step's launch (a training rollout,
        on the same stream) saves a copy of each; a caller that keeps them must copy them."""
        if self.xp is np:
            raise ValueError("fixed_outputs needs the Torch backend")
        self.buffers()
        if self.fixed is None:
            self.fixed = self.xp.empty(self.out_head, dtype=self.xp.float32, device=self.out_raw.device)
            self.fixed_views = self.unpack(self.fixed)
            self.fixed_status = self.status_of(self.fixed)
        return self.fixed_views[:4]

    def unpack(self, raw, rows: int = 3):
        """Views of the packed outputs ``raw`` (4-byte words, the buffer or a copy of its head, at
        storage offset 0): observations (N, d), rewards (N,), then the first ``rows`` flag rows
        (terminated, truncated, failed, done, bad: bytes after the rewards and the status), each
        (N,).  Built by as_strided, one Torch call a view, where slicing and retyping would take
        several calls a step."""
        torch = self.xp
        N, d = self.num_envs, self.env.single_observation_space.shape[0]
        F = 4 * N * (d + 2)
        flags = raw.view(torch.bool) if rows else None
        return (raw.as_strided((N, d), (d, 1)), raw.as_strided((N,), (1,), N * d),
                *(flags.as_strided((N,), (1,), F + k * N) for k in range(rows)))  # fmt: skip

    def status_of(self, raw):
        """The worlds' status codes (N,) int32 in the packed outputs ``raw`` (after the rewards):
        ``info["sim_status"]``, a copy of the simulator's that the step's last kernel writes."""
        N, d = self.num_envs, self.env.single_observation_space.shape[0]
        return raw.view(self.xp.int32).as_strided((N,), (1,), N * (d + 1))

    # ------------------------------------------------------------------ the step's parts
    def pre(self, a, checked: bool, slot: int | None = None, mail=None, mail_copy=None):
        """The controls of the actions ``a``.  ``checked`` (on the device; ``a`` not yet clipped, and
        clipped in place, NaN as 0): each world's NaN flag, and the go flag cleared by any of them
        (and left cleared, refusing every later step, until the host has read why: ``take_back``).
        The controls are set either way: a refused batch's (NaN as 0) stay in the simulator's
        control array, an input that the next step sets again, not a world's state.  ``slot`` (a
        step graph's, checked): the actions are read from the batch mailed in that slot of ``mail``
        (device view of the pinned mailbox) and clipped into ``a``, the slot copied to
        ``mail_copy`` (device memory, which ``post`` then reads)."""
        env = self.env
        if not checked:
            self.sim.set_controls(env.controls(a))
            return
        scaled = env.default_controls
        k = self.arrays
        mailed = slot is not None
        wp.launch(env_kernels.check_actions(self.sim.scalar, scaled, mailed), dim=self.num_envs,
                  inputs=[wp.from_torch(a), k["scale"], float(env.action_bound), k["bad"], self.go,
                          self.sim.controls("warp"), mail if mailed else None, slot or 0,
                          mail_copy if mailed else None],
                  device=self.device)  # fmt: skip
        if not scaled:
            self.sim.set_controls(env.controls(a))

    def physics(self, capturing: bool, checked: bool, side_stream=None):
        """The simulator's step, then the autoreset of last step's ended worlds (autoreset.py);
        ``checked``: only where the go flag is set (a conditional node of the step graph, which the
        device decides).  Captured where the step can hold worlds: both at once on ``side_stream``
        and the current stream (below)."""
        sim, frame_skip = self.sim, self.env.frame_skip
        if capturing and self.xp is not np and sim.holds:
            # the physics and the autoreset at once, on two streams of the graph: the step holds the
            # pending worlds (it neither reads nor writes their rows) while the autoreset restarts
            # them, and both leave a refused batch (go cleared) alone themselves, with no
            # conditional node: the node's cost and the autoreset's launches overlap the physics
            go = self.go if checked else None
            if side_stream is None:
                raise RuntimeError("the step's side stream is made before its capture (StepGraph)")
            with wp.ScopedStream(side_stream):  # waits for the stream's work so far (the check)
                self.next.apply(self.arrays["elapsed"], self.arrays["task"], go=go)
            sim.launch_step(frame_skip, hold=self.next.pending, go=go)
            wp.get_stream(self.device).wait_stream(side_stream)
            return

        def run():
            if capturing:
                sim.launch_step(frame_skip)  # the env's graph holds the step; the clock ticks at replay
            else:
                sim.step(frame_skip)
            # the autoreset: two launches for every world (no condition on whether any world is
            # pending: in a graph a conditional node cost more than the launches it spared), the
            # first of which ticks the episode clocks with Torch; with NumPy the host keeps the
            # clocks and, on the CPU, skips the launches when its mask has no pending world
            if self.xp is not np:
                self.next.apply(self.arrays["elapsed"], self.arrays["task"])
            elif capturing or not self.device.is_cpu or self.next.mask(np).any():
                self.next.apply()

        if checked:
            wp.capture_if(self.go, on_true=run)
        else:
            run()

    def post(self, a, slot: int | None = None, pinned=None, mail=None):
        """Observation, reward and flags of the step, those of the worlds reset in it replaced as in
        ``step`` (reward 0, both flags False), the ended worlds marked for the next step.  With
        Torch, in env_kernels' launch after the task's own operations (a step the device refused
        changes no pending mask), into the packed outputs; returns (the outputs, info values, the
        flags' rows done and bad); the worlds' status is among the packed outputs (``status_of``),
        not in the info values.  ``slot`` (a step graph's): the outputs go to the buffer mailed in
        that slot and the rows done and bad to its slot of the ``pinned`` host flags (the packed
        outputs are not written), whose pointer is read from ``mail`` (the pinned mailbox's device
        view, or the check's copy of it in device memory)."""
        env = self.env
        if self.xp is np:
            return self._post_host(a)
        k, N = self.arrays, self.num_envs
        pending = self.next.pending
        packed, info_values = self.outcome(a)
        steps = -1 if env.max_episode_steps is None else env.max_episode_steps
        mailed = slot is not None
        wp.launch(env_kernels.finish_step(mailed), dim=N,
                  inputs=[wp.from_torch(packed), self.sim.world_status("warp"), self.go, pending, k["elapsed"], steps,
                          k["obs"], k["reward"], k["status"], k["flags"], mail if mailed else None, slot or 0,
                          pinned.flags_dev if mailed else None], device=self.device)  # fmt: skip
        return self.unpack(self.out_raw), info_values, self.out_b[3:5]

    def _post_host(self, a):
        """``post`` with NumPy: the host keeps the clocks and the task values."""
        env, ep = self.env, self.env.episodes
        pend = self.next.mask(np)
        ep.elapsed += 1
        ep.elapsed[pend] = 0
        if ep.task_width and pend.any():  # the rows the device's worlds took (host_task)
            ep.task[pend] = self.next.task_rows(pend)
        obs, reward, terminated, truncated, failed, info_values = outcome(env, a, pend)
        done = terminated | truncated
        self.next.set_pending(done)
        return (obs, reward, terminated, truncated, failed), info_values, done

    def outcome(self, a):
        """:meth:`task_outcome` of ``a``, compiled by torch.compile where ``compile_outcome`` (on the
        first call)."""
        if self.outcome_fn is None:
            import torch

            fn = self.task_outcome
            self.outcome_fn = (torch.compile(_own_code(fn), dynamic=False, options=INDUCTOR_OPTIONS)
                               if self.compile_outcome else fn)  # fmt: skip
        return self.outcome_fn(a)

    def task_outcome(self, a):
        """The task's outcome after a step with the clipped actions ``a``: (N, d + 2) float32 of the
        observation (clipped to the space), the reward and the termination (1 or 0), and the info
        values (Torch; what torch.compile fuses: one output, one kernel where Inductor can)."""
        env, torch = self.env, self.xp
        obs = env.observation()
        reward = env.f32(env.reward(obs, a))
        term = env.terminated(obs).to(torch.float32)
        return torch.cat([obs, reward[:, None], term[:, None]], dim=1), env.info(obs)

    def run(self, a):
        """One env step as device work only (no host reads, no host-dependent branches on a GPU), so
        that CUDA graphs can hold it: controls, physics with the autoreset, outcome."""
        checked = self.check_on_device
        self.pre(a, checked)
        self.physics(False, checked)
        return self.post(a)

    # ------------------------------------------------------------------ the env step
    def step(self, a):
        """``env.step`` with NEXT_STEP autoresets on the device: on a GPU with Torch, graph replays
        (after one step of plain launches, which loads every kernel), else the same work launched.
        With the check on the device, the host learns a call late whether a step ran, and keeps
        what it needs to take its bookkeeping of a refused one back (``take_back``)."""
        env, checked, pm = self.env, self.check_on_device, self.env.pending
        torch_backend = self.xp is not np
        if torch_backend:
            self.buffers()
        if checked:
            before = (self.sim.time.copy(), self.next.bookmark())
        replayed = self.use_graph and self.warm
        slot = None
        if replayed:
            if self.graph is None:
                self.graph = step_graph.StepGraph(self)
            raw, (_, info_values, flags), slot = self.graph.replay(a, self.fixed)
        else:
            if checked:
                a = a.clone()  # clipped in place by the check
            out, info_values, flags = self.run(a)
            self.warm = True
            raw = None
            if self.fixed is not None:
                self.fixed.copy_(self.out_raw[: self.out_head])
                raw = self.fixed
            elif torch_backend:
                # the step's outputs are rewritten by the next step: the caller gets its own copies
                # (one clone of the packed bytes)
                raw = self.out_raw[: self.out_head].clone()
        if raw is not None:  # Torch: the outputs are views of raw
            fixed = raw is self.fixed
            out = self.fixed_views if fixed else self.unpack(raw)
            if not fixed:  # else handed back in place, as the outputs
                info_values = {k: v.clone() for k, v in info_values.items()}
            info_values = dict(info_values, sim_status=self.fixed_status if fixed else self.status_of(raw),
                               sim_substeps=self.sim.substeps("torch").clone(),
                               sim_energy_gained=self.sim.energy_gained("torch").clone().bool())  # fmt: skip
        obs, reward, terminated, truncated, failed = out
        # the worlds the device just reset (last step's ended ones, known on the host now): their
        # info is a reset's (none), their clock restarts, they took a row of their queues; this
        # read raises if the device refused the last step
        # (whole-mask NumPy operations: a few calls a step, each cheaper on a large batch than an
        # index list and fancy indexing)
        mask = self.pending_now()
        if replayed:
            self.sim.tick(env.frame_skip)
        if checked:
            self.undo = before + (mask.copy(),)
        has_info = ~mask
        if mask.any():
            self.sim.time[mask] = 0.0
            self.next.took(mask)
            mask[...] = False  # (none left pending)
        if not checked and flags.ndim == 2:
            flags = flags[0]  # the done row
        pm.defer(flags, checked, slot, self.device, self.torch_stream)
        pm.unread = checked
        info_values = dict(info_values, sim_failed=failed)
        return obs, reward, terminated, truncated, batch_info(info_values, has_info)

    @property
    def torch_stream(self):
        """The Torch stream the step graph was last replayed on (None: none yet, Torch's current)."""
        return None if self.graph is None else self.graph.torch_stream

    def pending_now(self) -> np.ndarray:
        """The env's pending mask (``PendingMask.fetch``), after the verdict of a step checked on the
        device: if the device refused it, the host's bookkeeping is taken back and this raises."""
        pm = self.env.pending
        mask = pm.fetch()
        if pm.unread:
            pm.unread = False
            if len(pm.refused):
                self.take_back()
        return mask

    def take_back(self):
        """The device refused the last step (NaN actions) and every step since: the host's
        bookkeeping of that step is taken back (clocks, queue rows, pending mask), the go flag set
        again, and the refusal raised."""
        pm = self.env.pending
        clock, taken, pending = self.undo
        self.sim.time[...] = clock
        self.next.rewind(taken)
        pm.mask = pending
        self.go.fill_(1)
        worlds, pm.refused = pm.refused, np.zeros(0, dtype=np.int64)
        raise ValueError(f"the actions of the last step contained NaN in worlds {worlds.tolist()[:10]}; no world "
                         "was stepped by that call or this one (on the device the check reports a call late; replace "
                         "or mask NaN actions before calling step)")  # fmt: skip
