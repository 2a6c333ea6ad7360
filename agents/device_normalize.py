"""SB3's VecNormalize for the NEXT_STEP device rollout, computed on the device.

:class:`~stable_baselines3.common.vec_env.VecNormalize` keeps running statistics in NumPy on the
host: each step it updates the observations' mean and variance with the step's observations
(Chan's parallel update of a ``RunningMeanStd``), normalises them,
``o' = clip((o - mean) / sqrt(var + eps), -clip_obs, clip_obs)``, accumulates each world's
discounted return ``R <- gamma R + r``, updates the returns' variance with it and scales the
reward, ``r' = clip(r / sqrt(var_R + eps), -clip_reward, clip_reward)``, then sets ``R = 0`` where
an episode ended.  :class:`DeviceNormalize` does the same in float64 tensors inside the rollout's
recorded step (:mod:`.graphed_rollout`), so that a VecNormalize config trains on the device path.

The statistics live in the training env's VecNormalize wrapper between rollouts: :meth:`load`
copies them to the device when a rollout starts and :meth:`store` writes them back when it ends
(so saving ``vecnormalize.pkl``, evaluation's ``sync_envs_normalization`` and a resumed run see
them; an evaluation in the middle of a rollout sees the statistics of the rollout's start).

A NEXT_STEP env steps differently from the SAME_STEP env VecNormalize sees on SB3's path, and the
masks make the statistics take the same samples:

* the observation returned at a step that ended an episode is the episode's last one (SB3's env
  returns the next episode's first, and the last only in ``infos``): it is normalised but not
  added to the observations' statistics; the next episode's first observation, returned by the
  reset step after it, is added then;
* a reset step (``valid`` false: reward 0, its action ignored) adds nothing to the returns.
"""
from __future__ import annotations

from typing import Any

import numpy as np
import torch as th

__all__ = ["DeviceNormalize", "find_vecnormalize", "masked_update"]


def find_vecnormalize(env: Any) -> Any:
    """The VecNormalize wrapper in ``env``'s chain of SB3 VecEnv wrappers, or None."""
    from stable_baselines3.common.vec_env import VecNormalize

    while env is not None and not isinstance(env, VecNormalize):
        env = getattr(env, "venv", None)
    return env


def masked_update(mean: th.Tensor, var: th.Tensor, count: th.Tensor, x: th.Tensor, mask: th.Tensor) -> None:
    """``RunningMeanStd.update`` (Chan et al.'s parallel mean and population variance) in place with
    the rows ``x[mask]`` (x: (n, ...) float64, mask: (n,) bool); no rows: unchanged.  No host read:
    the empty case is a ``where``, so the update can be captured in a CUDA graph."""
    m = mask.to(x.dtype).reshape(-1, *([1] * (x.dim() - 1)))
    n = m.sum()
    safe_n = th.clamp(n, min=1.0)
    batch_mean = (m * x).sum(0) / safe_n
    batch_var = (m * (x - batch_mean) ** 2).sum(0) / safe_n
    delta = batch_mean - mean
    total = count + n
    new_mean = mean + delta * n / total
    new_var = (var * count + batch_var * n + delta**2 * count * n / total) / total
    mean.copy_(th.where(n > 0, new_mean, mean))
    var.copy_(th.where(n > 0, new_var, var))
    count.copy_(total)


class DeviceNormalize:
    """The statistics and settings of ``wrapper`` (a VecNormalize over the training env) in tensors on
    ``device`` for ``n_envs`` worlds; :meth:`step` normalises one step."""

    def __init__(self, wrapper: Any, n_envs: int, device: th.device):
        self.wrapper = wrapper
        self.norm_obs, self.norm_reward = bool(wrapper.norm_obs), bool(wrapper.norm_reward)
        self.clip_obs, self.clip_reward = float(wrapper.clip_obs), float(wrapper.clip_reward)
        self.epsilon, self.gamma = float(wrapper.epsilon), float(wrapper.gamma)
        obs_shape = wrapper.obs_rms.mean.shape

        def zeros(*shape: int) -> th.Tensor:
            return th.zeros(shape, dtype=th.float64, device=device)

        self.obs_mean, self.obs_var, self.obs_count = zeros(*obs_shape), zeros(*obs_shape), zeros()
        self.ret_mean, self.ret_var, self.ret_count = zeros(), zeros(), zeros()
        self.returns = zeros(n_envs)
        self.training = bool(wrapper.training)

    def load(self) -> None:
        """The wrapper's statistics, returns and ``training`` flag onto the device."""
        w = self.wrapper
        for dst, src in ((self.obs_mean, w.obs_rms.mean), (self.obs_var, w.obs_rms.var),
                         (self.obs_count, w.obs_rms.count), (self.ret_mean, w.ret_rms.mean),
                         (self.ret_var, w.ret_rms.var), (self.ret_count, w.ret_rms.count),
                         (self.returns, w.returns)):  # fmt: skip
            dst.copy_(th.as_tensor(np.asarray(src, dtype=np.float64)).reshape(dst.shape))
        self.training = bool(w.training)

    def store(self) -> None:
        """This rollout's statistics and returns back into the wrapper (one read from the device)."""
        w, tensors = self.wrapper, self._tensors()
        flat = th.cat([t.reshape(-1) for t in tensors]).cpu()
        parts = [p.reshape(t.shape).numpy() for p, t in zip(flat.split([t.numel() for t in tensors]), tensors)]
        obs_mean, obs_var, obs_count, ret_mean, ret_var, ret_count, returns = parts
        w.obs_rms.mean, w.obs_rms.var, w.obs_rms.count = obs_mean.copy(), obs_var.copy(), float(obs_count)
        w.ret_rms.mean, w.ret_rms.var, w.ret_rms.count = ret_mean.copy(), ret_var.copy(), float(ret_count)
        w.returns = returns.copy()

    def _tensors(self) -> tuple[th.Tensor, ...]:
        return (self.obs_mean, self.obs_var, self.obs_count, self.ret_mean, self.ret_var, self.ret_count, self.returns)

    def step(self, obs: th.Tensor, rewards: th.Tensor, valid: th.Tensor,
             dones: th.Tensor) -> tuple[th.Tensor, th.Tensor]:  # fmt: skip
        """(normalised observations float32, normalised rewards float32) of one step of the env:
        ``obs`` (n, ...) and ``rewards`` (n,) as it returned them, ``valid`` (not a reset step) and
        ``dones`` (the step ended an episode) bool (n,); the statistics updated first where
        ``training`` (as VecNormalize does)."""
        x = obs.to(th.float64)
        if self.training and self.norm_obs:
            masked_update(self.obs_mean, self.obs_var, self.obs_count, x, ~dones)
        if self.norm_obs:
            x = th.clamp((x - self.obs_mean) / th.sqrt(self.obs_var + self.epsilon), -self.clip_obs, self.clip_obs)
        r = rewards.to(th.float64)
        if self.training:
            self.returns.copy_(th.where(valid, self.returns * self.gamma + r, self.returns))
            masked_update(self.ret_mean, self.ret_var, self.ret_count, self.returns, valid)
        if self.norm_reward:
            r = th.clamp(r / th.sqrt(self.ret_var + self.epsilon), -self.clip_reward, self.clip_reward)
        self.returns.masked_fill_(dones, 0.0)
        return x.to(th.float32), r.to(th.float32)
