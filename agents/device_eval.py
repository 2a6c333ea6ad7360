"""Evaluation episodes stepped and scored on the policy's device.

SB3's ``evaluate_policy`` reads every step back to the host: the observations go to NumPy and back
to the device for the policy, the actions to NumPy and back to the env, and a Python loop visits
every world every step to count its episodes.  With 1,024 evaluation worlds on a GPU that loop,
not the simulation, sets the time of an evaluation.  :class:`DeviceEvaluator` runs the same
episodes on an env with the Torch backend that autoresets in NEXT_STEP mode (what
:func:`~.common.build_eval_env` builds for it): the policy reads the env's observation tensor, the
env reads the policy's action tensor, and each world's return and length accumulate in tensors on
the device, read back once the evaluation is over.

The episodes are ``evaluate_policy``'s:

* world ``i`` of ``n`` plays ``(episodes + i) // n`` episodes (its ``episode_count_targets``) from
  one reset of all worlds, and steps go on until every world has played its episodes;
* the observations are normalised with the eval env's frozen VecNormalize statistics, as
  ``VecNormalize.normalize_obs`` does (float64, then float32 for the policy);
* the action is ``policy._predict``'s (the distribution's mode where deterministic), clipped to the
  Box or unscaled where the policy squashes it, as ``policy.predict`` does;
* a return is the float32 sum of the episode's rewards and a length its count of steps, as
  ``VecMonitor`` keeps them.

A NEXT_STEP env resets a finished world at its next step, which ignores the action and returns
reward 0: that step belongs to no episode.  The returns come back world by world (world 0's
episodes first); ``evaluate_policy`` lists them in the order the episodes ended.  With one episode
a world the two lists hold the same episodes (a test compares them).

On a CUDA device the policy's step and the bookkeeping are each one CUDA graph replay
(:class:`~.cuda_graph.GraphedCall`), and whether every world is done is read every
:attr:`DeviceEvaluator.check_every` steps.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from gymnasium.vector import AutoresetMode
from stable_baselines3.common.vec_env import VecMonitor, VecNormalize

from abd_gym.agents.cuda_graph import GraphedCall
from abd_gym.agents.device_normalize import find_vecnormalize
from abd_gym.agents.graphed_update import unchecked_distributions

__all__ = ["DeviceEvaluator"]


class DeviceEvaluator:
    """Evaluation of a model's policy on ``env`` (an SB3 VecEnv chain over a
    :class:`~.sb3_vec_env.GymnasiumVecEnv` with the Torch backend that autoresets in NEXT_STEP
    mode; VecMonitor and a frozen VecNormalize may wrap it, no other wrapper: the evaluation
    reads the adapter's tensors).  Call it with the model.

    ``check_every``: steps between two reads of "has every world played its episodes" (each read
    waits for the GPU).
    """

    check_every = 16

    def __init__(self, env: Any):
        refusal = self.refusal(env)
        if refusal is not None:
            raise ValueError(f"DeviceEvaluator cannot evaluate on this env: {refusal}")
        from abd_gym.agents.device_rollout import find_adapter

        self.adapter = find_adapter(env)
        self.vecnormalize = find_vecnormalize(env)
        self.n_envs = self.adapter.num_envs
        spec = getattr(self.adapter.env, "spec", None)
        self.max_episode_steps = getattr(spec, "max_episode_steps", None)
        self._state: _EvalState | None = None

    @staticmethod
    def refusal(env: Any) -> str | None:
        """Why ``env`` cannot be evaluated on the device (in words), or None where it can."""
        from abd_gym.agents.device_rollout import find_adapter

        adapter = find_adapter(env)
        if adapter is None:
            return "the env is not a GymnasiumVecEnv"
        layer = env
        while layer is not adapter:  # a wrapper that changes observations or rewards would be skipped
            if not isinstance(layer, (VecMonitor, VecNormalize)):
                return f"the env is wrapped in {type(layer).__name__} (VecMonitor and VecNormalize only)"
            layer = layer.venv
        if adapter.autoreset_mode != AutoresetMode.NEXT_STEP:
            return f"the env autoresets in {adapter.autoreset_mode.name} mode, not NEXT_STEP"
        return adapter.tensor_path_refusal()

    def __call__(self, model: Any, n_episodes: int, *, deterministic: bool = True) -> tuple[list[float], list[int]]:
        """(returns, lengths) of ``n_episodes`` episodes of ``model``'s policy, world by world."""
        n_episodes = int(n_episodes)
        if n_episodes < 1:
            raise ValueError(f"n_episodes must be at least 1, got {n_episodes}")
        state = self._state_for(model, n_episodes, deterministic)
        obs = self.adapter.reset()  # all worlds, seeded as the env's next reset is (SB3's path resets too)
        state.start(th.as_tensor(obs, dtype=th.float32))
        limit = self._step_limit(state.most_episodes)
        model.policy.set_training_mode(False)
        steps = 0
        with unchecked_distributions():
            while True:
                for _ in range(self.check_every):
                    state.act()
                    state.env_step()
                    state.record()
                steps += self.check_every
                if bool(state.finished()):
                    break
                if limit is not None and steps > limit:
                    raise RuntimeError(
                        f"evaluation did not end: after {steps} steps {state.unfinished()} of {self.n_envs} worlds "
                        f"have not played their episodes (episodes end within {self.max_episode_steps} steps)"
                    )
        return state.results()

    def _state_for(self, model: Any, n_episodes: int, deterministic: bool) -> _EvalState:
        key = (id(model.policy), n_episodes, deterministic)
        if self._state is None or self._state.key != key:
            self._state = _EvalState(self, model, n_episodes, deterministic, key)
        else:
            self._state.load_statistics()
        return self._state

    def _step_limit(self, episodes_per_world: int) -> int | None:
        if self.max_episode_steps is None:
            return None
        return episodes_per_world * (int(self.max_episode_steps) + 1) + self.check_every


class _EvalState:
    """The tensors of one evaluation setting (policy, episodes, deterministic), at fixed addresses so
    that its two steps replay as CUDA graphs from one evaluation to the next."""

    def __init__(self, evaluator: DeviceEvaluator, model: Any, n_episodes: int, deterministic: bool, key: Any):
        self.key = key
        self.evaluator, self.model, self.deterministic = evaluator, model, deterministic
        policy, n = model.policy, evaluator.n_envs
        dev = policy.device
        self.targets = th.tensor([(n_episodes + i) // n for i in range(n)], dtype=th.int64, device=dev)
        self.most_episodes = int(math.ceil(n_episodes / n))
        obs_shape = model.observation_space.shape
        self.obs = th.zeros((n, *obs_shape), dtype=th.float32, device=dev)
        self.rewards = th.zeros(n, dtype=th.float32, device=dev)
        self.dones = th.zeros(n, dtype=th.bool, device=dev)
        self.ended = th.zeros(n, dtype=th.bool, device=dev)
        self.ep_return = th.zeros(n, dtype=th.float32, device=dev)
        self.ep_length = th.zeros(n, dtype=th.int64, device=dev)
        self.count = th.zeros(n, dtype=th.int64, device=dev)
        self.returns = th.zeros((n, self.most_episodes), dtype=th.float32, device=dev)
        self.lengths = th.zeros((n, self.most_episodes), dtype=th.int64, device=dev)
        space = model.action_space
        discrete = isinstance(space, spaces.Discrete)
        self.env_actions = th.zeros((n, *space.shape), dtype=th.int64 if discrete else th.float32, device=dev)
        self.box = isinstance(space, spaces.Box)
        if self.box:
            self.low = th.as_tensor(space.low, dtype=th.float32, device=dev)
            self.high = th.as_tensor(space.high, dtype=th.float32, device=dev)
        self.norm = None
        vn = evaluator.vecnormalize
        if vn is not None and vn.norm_obs:
            shape = np.asarray(vn.obs_rms.mean).shape
            self.norm = dict(mean=th.zeros(shape, dtype=th.float64, device=dev),
                             var=th.zeros(shape, dtype=th.float64, device=dev),
                             clip=float(vn.clip_obs), eps=float(vn.epsilon))  # fmt: skip
            self.load_statistics()
        self.act = GraphedCall(self._act, dev)
        self.record = GraphedCall(self._record, dev)

    def load_statistics(self) -> None:
        """The eval env's VecNormalize statistics now (synced from training before an evaluation)."""
        if self.norm is not None:
            rms = self.evaluator.vecnormalize.obs_rms
            self.norm["mean"].copy_(th.as_tensor(np.asarray(rms.mean, dtype=np.float64)))
            self.norm["var"].copy_(th.as_tensor(np.asarray(rms.var, dtype=np.float64)))

    def start(self, obs: th.Tensor) -> None:
        self.obs.copy_(obs.reshape(self.obs.shape))
        for x in (self.ended, self.ep_return, self.ep_length, self.count, self.returns, self.lengths):
            x.zero_()

    def _act(self) -> None:
        x = self.obs
        if self.norm is not None:
            n = self.norm
            x = th.clamp((x.to(th.float64) - n["mean"]) / th.sqrt(n["var"] + n["eps"]), -n["clip"], n["clip"])
            x = x.to(th.float32)
        with th.no_grad():
            actions = self.model.policy._predict(x, deterministic=self.deterministic)
        if self.box:
            if self.model.policy.squash_output:
                actions = self.low + 0.5 * (actions + 1.0) * (self.high - self.low)
            else:
                actions = th.clamp(actions, self.low, self.high)
        self.env_actions.copy_(actions.reshape(self.env_actions.shape))

    def env_step(self) -> None:
        step = self.evaluator.adapter.step_tensors(self.env_actions)
        self.obs.copy_(step.obs.reshape(self.obs.shape))
        self.rewards.copy_(step.rewards)
        th.logical_or(step.terminated, step.truncated, out=self.dones)

    def _record(self) -> None:
        # a world that ended at the previous step was reset by this one: no episode's step
        playing = ~self.ended & (self.count < self.targets)
        self.ep_return += th.where(playing, self.rewards, 0.0)
        self.ep_length += playing
        finishing = playing & self.dones
        slot = self.count.clamp(max=self.returns.shape[1] - 1)[:, None]
        for table, value in ((self.returns, self.ep_return), (self.lengths, self.ep_length)):
            table.scatter_(1, slot, th.where(finishing, value, table.gather(1, slot)[:, 0])[:, None])
        self.count += finishing
        self.ep_return.masked_fill_(self.dones, 0.0)
        self.ep_length.masked_fill_(self.dones, 0)
        self.ended.copy_(self.dones)

    def finished(self) -> th.Tensor:
        return (self.count >= self.targets).all()

    def unfinished(self) -> int:
        return int((self.count < self.targets).sum())

    def results(self) -> tuple[list[float], list[int]]:
        returns, lengths, targets = (x.cpu().numpy() for x in (self.returns, self.lengths, self.targets))
        out_r: list[float] = []
        out_l: list[int] = []
        for i, k in enumerate(targets):
            out_r += [float(r) for r in returns[i, :k]]
            out_l += [int(l) for l in lengths[i, :k]]
        return out_r, out_l
