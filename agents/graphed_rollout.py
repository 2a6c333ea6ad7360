"""The NEXT_STEP rollout's device work as calls of fixed-address tensors, CUDA graphs on a GPU.

A rollout step of :class:`~.device_rollout.DevicePPO` on a NEXT_STEP env is (see that module):
the policy acts on the last observation, the env steps, and the step's transition, flags and
episode statistics go into the buffer.  Launched from Python that is ~60 small kernels a step,
several times the env's own step on a GPU.  :class:`RolloutStep` runs it as

1. :meth:`act`: ``actions, values, log_probs = policy(obs)`` and the env's actions (clipped to the
   Box, or unscaled when squashed), into tensors the env and the buffer read;
2. :meth:`env_step`: the env's step (its own CUDA graph), which writes its observation, rewards
   and flags into tensors it keeps for the rollout (``ABDVectorEnv.fixed_outputs``; copied in
   where the env hands back others);
3. :meth:`record`: at the buffer position held in a device tensor ``pos`` (so that one graph
   serves every position): with a VecNormalize config, the observation and reward normalised
   (:class:`~.device_normalize.DeviceNormalize`); then one kernel
   (:func:`~.rollout_kernels.record_kernel`, a thread per world) writes ``valid = not ended``,
   ``done = terminated or truncated``, ``cut = truncated and not terminated``, the episode's
   return and length so far (of the env's own rewards) and the transition
   ``(obs, action, reward, episode_start, value, log_prob)``, and sets ``obs <- next obs``,
   ``episode_start <- ended``, ``ended <- done``; then ``pos += 1``.

Between two steps of a rollout, 3 and the next step's 1 are one call (:meth:`record_act`).  After
the rollout's last step, :meth:`finish`: the values of the last observation, GAE over the rollout
(:meth:`TensorRolloutBuffer.compute_returns_and_advantage`, one kernel) and the returns and
lengths of the rollout's last ``tail_size`` finished episodes in :attr:`tail` (which
``ep_info_buffer`` keeps), so that reading them is one small copy to the host.

:meth:`act`, :meth:`record`, :meth:`record_act` and :meth:`finish` are each one graph replay on a
GPU (:class:`~.cuda_graph.GraphedCall`), eager on the CPU, with the same arithmetic either way.  The
buffer's storage keeps its addresses from one rollout to the next (:meth:`TensorRolloutBuffer.reset`).
As Torch operations the record and GAE are tens of small kernels each, launched from Python; here
each is one Warp kernel (their cost as measured: results/solver_notes.md).
"""
from __future__ import annotations

import math
from typing import Any

import torch as th
import warp as wp
from gymnasium import spaces

from abd_gym.agents.cuda_graph import GraphedCall
from abd_gym.agents.device_normalize import DeviceNormalize
from abd_gym.agents.rollout_kernels import record_kernel, warp_on_torch_stream

__all__ = ["RolloutStep"]


class RolloutStep:
    """The NEXT_STEP rollout state of ``algo`` (a :class:`DevicePPO`) in fixed-address tensors:
    ``obs`` (the policy's next input), ``episode_starts``, ``ended``, ``ep_return``, ``ep_length``;
    ``normalize``: the training env's VecNormalize statistics on the device, or None."""

    def __init__(self, algo: Any, capture: bool | None = None, normalize: DeviceNormalize | None = None):
        self.algo = algo
        n, dev = algo._adapter.num_envs, algo.device
        self.n_envs = n
        self.obs = th.zeros((n, *algo.observation_space.shape), dtype=th.float32, device=dev)
        self.episode_starts = th.zeros(n, dtype=th.float32, device=dev)
        self.ended = th.zeros(n, dtype=th.bool, device=dev)
        self.ep_return = th.zeros(n, dtype=th.float32, device=dev)
        self.ep_length = th.zeros(n, dtype=th.int64, device=dev)
        self.pos = th.zeros(1, dtype=th.int64, device=dev)
        fixed = algo._adapter.fixed_outputs()
        if fixed is not None and fixed[0].device == th.device(dev) and fixed[0].numel() == self.obs.numel():
            obs, self.rewards, self.terminated, self.truncated = fixed  # the env writes them in place
            self.next_obs = obs.reshape(self.obs.shape)
        else:  # env_step copies the env's outputs in
            self.next_obs = th.zeros_like(self.obs)
            self.rewards = th.zeros(n, dtype=th.float32, device=dev)
            self.terminated = th.zeros(n, dtype=th.bool, device=dev)
            self.truncated = th.zeros(n, dtype=th.bool, device=dev)
        discrete = isinstance(algo.action_space, spaces.Discrete)
        shape = algo.action_space.shape
        self.actions = th.zeros((n, 1 if discrete else math.prod(shape)), dtype=th.float32, device=dev)
        self.env_actions = th.zeros((n, *shape), dtype=th.int64 if discrete else th.float32, device=dev)
        self.values = th.zeros(n, dtype=th.float32, device=dev)
        self.log_probs = th.zeros(n, dtype=th.float32, device=dev)
        self.last_values = th.zeros(n, dtype=th.float32, device=dev)
        # the last finished episodes: returns, lengths, and their count at [0, tail_size]; as many as
        # ep_info_buffer keeps, or a whole rollout's worth where it keeps all
        episodes = getattr(algo, "ep_info_buffer", None)
        self.tail_size = getattr(episodes, "maxlen", None) or algo.n_steps * n
        self.tail = th.zeros((2, self.tail_size + 1), dtype=th.float32, device=dev)
        self.buffer: Any = None
        self._inputs: list = []  # record_kernel's arguments after the reward, as Warp views
        self.normalize = normalize
        self._training = None if normalize is None else normalize.training
        self.act = GraphedCall(self._act, dev, capture=capture)
        self.record = GraphedCall(self._record, dev, capture=capture)
        self.record_act = GraphedCall(self._record_act, dev, capture=capture)
        self.finish = GraphedCall(self._finish, dev, capture=capture)

    def start(self, buffer: Any) -> None:
        """A rollout into ``buffer`` (reset) from the algorithm's last observation, episode starts,
        ``_ended`` and episode statistics, which then live here (the algorithm's attributes point here)."""
        algo = self.algo
        if buffer.storage is not getattr(self.buffer, "storage", None):
            self.buffer = buffer
            self._inputs = self._kernel_inputs()
            for call in (self.record, self.record_act, self.finish):  # captured on the old storage
                call.reset()
        if self.normalize is not None:
            self.normalize.load()
            if self.normalize.training != self._training:  # the captured step updates the statistics or not
                self._training = self.normalize.training
                self.record.reset()
                self.record_act.reset()
        for mine, name in ((self.obs, "_last_obs"), (self.episode_starts, "_last_episode_starts"),
                           (self.ended, "_ended"), (self.ep_return, "_ep_return"), (self.ep_length, "_ep_length")):
            theirs = getattr(algo, name)
            if theirs is not mine:
                mine.copy_(theirs.reshape(mine.shape))
                setattr(algo, name, mine)
        self.pos.zero_()

    def end(self) -> None:
        """The rollout's end: the normalisation statistics back to the VecNormalize wrapper."""
        if self.normalize is not None:
            self.normalize.store()

    def env_step(self) -> None:
        """The env's step on :attr:`env_actions`, its outputs in :attr:`next_obs`, :attr:`rewards`,
        :attr:`terminated` and :attr:`truncated` for :meth:`record`."""
        step = self.algo._adapter.step_tensors(self.env_actions)
        if step.obs.data_ptr() == self.next_obs.data_ptr():  # written in place (fixed_outputs)
            return
        self.next_obs.copy_(step.obs.reshape(self.next_obs.shape))
        self.rewards.copy_(step.rewards)
        self.terminated.copy_(step.terminated)
        self.truncated.copy_(step.truncated)

    def _act(self) -> None:
        with th.no_grad():
            actions, values, log_probs = self.algo.policy(self.obs)
        self.actions.copy_(actions.reshape(self.actions.shape))
        self.env_actions.copy_(self.algo._env_actions(actions).reshape(self.env_actions.shape))
        self.values.copy_(values.flatten())
        self.log_probs.copy_(log_probs.reshape(self.n_envs))

    def _kernel_inputs(self) -> list:
        """:func:`record_kernel`'s arguments from ``env_reward`` on (fixed tensors: the rollout
        state and the buffer's storage), as Warp views."""
        n, t = self.n_envs, self.buffer.storage
        fields = ("rewards", "episode_starts", "values", "log_probs", "valid", "dones", "cuts", "ep_return",
                  "ep_length")  # fmt: skip
        tensors = [self.rewards, self.terminated, self.truncated, self.actions, self.values, self.log_probs,
                   self.obs.reshape(n, -1), self.episode_starts, self.ended, self.ep_return, self.ep_length,
                   t["observations"].reshape(*t["observations"].shape[:2], -1), t["actions"],
                   *(t[name] for name in fields)]  # fmt: skip
        return [wp.from_torch(x) for x in tensors]

    def _record(self) -> None:
        next_obs, rewards = self.next_obs, self.rewards
        if self.normalize is not None:
            valid = ~self.ended
            dones = self.terminated | self.truncated
            next_obs, rewards = self.normalize.step(next_obs, rewards, valid, dones)
        device = self.obs.device
        with warp_on_torch_stream(device):
            wp.launch(record_kernel, dim=self.n_envs,
                      inputs=[wp.from_torch(self.pos), wp.from_torch(next_obs.reshape(self.n_envs, -1)),
                              wp.from_torch(rewards), *self._inputs],
                      device=wp.device_from_torch(device))  # fmt: skip
        self.pos += 1

    def _record_act(self) -> None:
        self._record()
        self._act()

    def _finish(self) -> None:
        with th.no_grad():
            self.last_values.copy_(self.algo.policy.predict_values(self.obs).flatten())
        self.buffer.compute_returns_and_advantage(last_values=self.last_values, dones=None)
        self._tail()

    def _tail(self) -> None:
        """:attr:`tail`: the returns ``[0, :k]`` and lengths ``[1, :k]`` of the rollout's last
        ``k = min(finished, tail_size)`` finished episodes in row-major order (step, then world),
        ``k`` at ``[0, tail_size]``: a finished episode's rank from the end by a cumulative count,
        each scattered to its slot (the others to the count's slot, then overwritten)."""
        t, size = self.buffer.storage, self.tail_size
        done = t["dones"].flatten() > 0
        count = th.cumsum(done.to(th.int32), 0)
        total = count[-1]
        first = th.clamp(total - size, min=0)  # the finished episodes before the kept ones
        slot = th.where(done & (count > first), count - 1 - first, size).to(th.int64)
        self.tail[0].scatter_(0, slot, t["ep_return"].flatten())
        self.tail[1].scatter_(0, slot, t["ep_length"].flatten())
        self.tail[0, size] = th.clamp(total, max=size).to(th.float32)
