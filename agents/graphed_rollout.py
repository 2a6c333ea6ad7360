"""The NEXT_STEP rollout's device work as two calls of fixed-address tensors, CUDA graphs on a GPU.

A rollout step of :class:`~.device_rollout.DevicePPO` on a NEXT_STEP env is (see that module):
the policy acts on the last observation, the env steps, and the step's transition, flags and
episode statistics go into the buffer.  Launched from Python that is ~60 small kernels a step,
several times the env's own step on a GPU.  :class:`RolloutStep` runs it as

1. :meth:`act`: ``actions, values, log_probs = policy(obs)`` and the env's actions (clipped to the
   Box, or unscaled when squashed), into tensors the env and the buffer read;
2. the env's step (its own CUDA graph), its observation, rewards and flags copied in;
3. :meth:`record`: at the buffer position held in a device tensor ``pos`` (so that one graph
   serves every position): ``valid = not ended``; with a VecNormalize config, the observation and
   reward normalised (:class:`~.device_normalize.DeviceNormalize`); the episode's return and
   length so far (of the env's own rewards); the
   flags ``valid``, ``done = terminated or truncated``, ``cut = truncated and not terminated``;
   the transition ``(obs, action, reward, episode_start, value, log_prob)``; then
   ``obs <- next obs``, ``episode_start <- ended``, ``ended <- done``, ``pos += 1``.

and after the rollout's last step :meth:`finish`: the values of the last observation and GAE over
the rollout (:meth:`TensorRolloutBuffer.compute_returns_and_advantage`, a loop of ~6 kernels a step).

1, 3 and :meth:`finish` are each one graph replay on a GPU (:class:`~.cuda_graph.GraphedCall`),
eager on the CPU, with the same arithmetic in the same order either way.  The buffer's storage
keeps its addresses from one rollout to the next (:meth:`TensorRolloutBuffer.reset`).
"""
from __future__ import annotations

import math
from typing import Any

import torch as th
from gymnasium import spaces

from .cuda_graph import GraphedCall
from .device_normalize import DeviceNormalize

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
        self.next_obs = th.zeros_like(self.obs)
        self.episode_starts = th.zeros(n, dtype=th.float32, device=dev)
        self.ended = th.zeros(n, dtype=th.bool, device=dev)
        self.ep_return = th.zeros(n, dtype=th.float32, device=dev)
        self.ep_length = th.zeros(n, dtype=th.int64, device=dev)
        self.rewards = th.zeros(n, dtype=th.float32, device=dev)
        self.terminated = th.zeros(n, dtype=th.bool, device=dev)
        self.truncated = th.zeros(n, dtype=th.bool, device=dev)
        self.pos = th.zeros(1, dtype=th.int64, device=dev)
        discrete = isinstance(algo.action_space, spaces.Discrete)
        shape = algo.action_space.shape
        self.actions = th.zeros((n, 1 if discrete else math.prod(shape)), dtype=th.float32, device=dev)
        self.env_actions = th.zeros((n, *shape), dtype=th.int64 if discrete else th.float32, device=dev)
        self.values = th.zeros(n, dtype=th.float32, device=dev)
        self.log_probs = th.zeros(n, dtype=th.float32, device=dev)
        self.last_values = th.zeros(n, dtype=th.float32, device=dev)
        self.buffer: Any = None
        self.normalize = normalize
        self._training = None if normalize is None else normalize.training
        self.act = GraphedCall(self._act, dev, capture=capture)
        self.record = GraphedCall(self._record, dev, capture=capture)
        self.finish = GraphedCall(self._finish, dev, capture=capture)

    def start(self, buffer: Any) -> None:
        """A rollout into ``buffer`` (reset) from the algorithm's last observation, episode starts,
        ``_ended`` and episode statistics, which then live here (the algorithm's attributes point here)."""
        algo = self.algo
        if buffer.storage is not getattr(self.buffer, "storage", None):
            self.buffer = buffer
            self.record.reset()  # the captured reads and writes go to the old storage
            self.finish.reset()
        if self.normalize is not None:
            self.normalize.load()
            if self.normalize.training != self._training:  # the captured step updates the statistics or not
                self._training = self.normalize.training
                self.record.reset()
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
        """The env's step on :attr:`env_actions`; its outputs copied in for :meth:`record`."""
        step = self.algo._adapter.step_tensors(self.env_actions)
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

    def _record(self) -> None:
        t, pos = self.buffer.storage, self.pos

        def put(name: str, value: th.Tensor) -> None:
            t[name].index_copy_(0, pos, value.to(th.float32)[None])

        dones = self.terminated | self.truncated
        valid = ~self.ended  # a world that ended at the previous step was reset by this one
        next_obs, rewards = self.next_obs, self.rewards
        if self.normalize is not None:
            next_obs, rewards = self.normalize.step(next_obs, rewards, valid, dones)
        self.ep_return += th.where(valid, self.rewards, 0.0)
        self.ep_length += valid
        put("ep_return", self.ep_return)
        put("ep_length", self.ep_length)
        self.ep_return.masked_fill_(dones, 0.0)
        self.ep_length.masked_fill_(dones, 0)
        put("valid", valid)
        put("dones", dones)
        put("cuts", self.truncated & ~self.terminated)
        for name, value in (("observations", self.obs), ("actions", self.actions), ("rewards", rewards),
                            ("episode_starts", self.episode_starts), ("values", self.values),
                            ("log_probs", self.log_probs)):  # fmt: skip
            put(name, value)
        self.obs.copy_(next_obs)
        self.episode_starts.copy_(self.ended)  # a reset step's observation opens an episode
        self.ended.copy_(dones)
        self.pos += 1

    def _finish(self) -> None:
        with th.no_grad():
            self.last_values.copy_(self.algo.policy.predict_values(self.obs).flatten())
        self.buffer.compute_returns_and_advantage(last_values=self.last_values, dones=None)
