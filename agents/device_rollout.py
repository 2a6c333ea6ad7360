"""PPO with its rollout and its update kept on the policy's device.

SB3's on-policy rollout round-trips every step through NumPy: observations leave the env's device
for the host, go back to the device for the policy, actions come back to the host and go to the
device again, and :class:`~stable_baselines3.common.buffers.RolloutBuffer` stores host arrays that
are copied to the device again for every minibatch.  Here an env with the Torch backend (through
:meth:`GymnasiumVecEnv.step_tensors`) hands its tensors straight to the policy and to a
:class:`TensorRolloutBuffer` of tensors on the policy's device; GAE runs there and minibatches are
gathered there.

With a SAME_STEP env the semantics are SB3's ``OnPolicyAlgorithm.collect_rollouts``: actions
clipped to the Box (or unscaled when squashed), a world cut by its time limit gets
``reward += gamma * V(final_obs)``, ``_last_episode_starts`` marks the first step of each episode,
callbacks are called at the same points, ``num_timesteps`` counts all worlds, and each finished
episode adds VecMonitor's ``{"r", "l", "t"}`` to ``ep_info_buffer``.  The minibatch order is drawn
from NumPy's global generator exactly as SB3 does, so with the same seed the two paths sample the
same minibatches.  Callbacks' ``locals`` carry tensors (``dones`` is a bool tensor on the device)
and no ``infos``.

With a NEXT_STEP env (what training builds for this path: its step reads nothing on the host and
runs as one CUDA graph on a GPU) a world whose episode ended at step k-1 is reset by step k, which
ignores its action and returns the new episode's first observation with reward 0 and no flags.
The transition stored at position k for that world (the old episode's last observation o_k,
a_k, reward 0) is no transition of the task, so the buffer marks it invalid and:

* minibatches are drawn from the valid positions only (a permutation of their flat indices, from
  NumPy's global generator; ``batch_size`` as SB3, the last minibatch smaller if it must be);
* GAE runs on the step's own flags: ``next_non_terminal_{k-1} = 1 - done_{k-1}`` (``done``:
  terminated or truncated), not ``1 - episode_start_k`` (position k holds the old episode's last
  observation); a reset position's own advantage is never used;
* a world cut by its time limit at step k-1 gets ``r_{k-1} += gamma * V(o_k)``, the value the
  policy computed at position k (o_k is the final observation), or the rollout's last values at
  its last step; no extra forward pass;
* "ended at the previous step" is carried from one rollout to the next (position 0 of a rollout
  can be a reset step);
* ``episode_starts`` marks position k+1 after a reset step k (its observation opens the episode);
* episode returns and lengths count the episode's own steps (not the reset step) and reach
  ``ep_info_buffer`` at the rollout's end (read on the host once per rollout; ``"t"`` is that time);
* ``num_timesteps`` counts every world at every step as SB3 does, so 1 in (episode length + 1)
  counted transitions is a reset step that trains nothing.

On a CUDA device the NEXT_STEP rollout's policy and bookkeeping run as CUDA graphs
(:mod:`.graphed_rollout`).  The update is :class:`~.graphed_update.GraphedPPO`'s: without
``target_kl`` on a GPU, PPO's minibatch step replayed from a CUDA graph (parameters equal SB3's
to float32 rounding), elsewhere SB3's ``PPO.train`` bit for bit, with its statistics read once
an update.  The rollout and the update build Torch distributions without argument checks (each
check is a read back to the host).  Each such read waits for the GPU, so that the host cannot
queue the next kernels while the GPU runs.

:func:`rollout_path` says which path a config gets and, for SB3's path, why.
"""
from __future__ import annotations

import time
from collections.abc import Generator, Iterator
from typing import Any

import numpy as np
import torch as th
import warp as wp
from gymnasium import spaces
from gymnasium.vector import AutoresetMode
from stable_baselines3.common.buffers import BaseBuffer, RolloutBuffer
from stable_baselines3.common.type_aliases import RolloutBufferSamples
from stable_baselines3.common.vec_env import VecEnv, VecMonitor

from abd_gym.agents.device_normalize import DeviceNormalize, find_vecnormalize
from abd_gym.agents.graphed_rollout import RolloutStep
from abd_gym.agents.graphed_update import SAMPLED, GraphedPPO, unchecked_distributions
from abd_gym.agents.rollout_kernels import gae_kernel, warp_on_torch_stream
from abd_gym.agents.sb3_vec_env import GymnasiumVecEnv, _accepts

__all__ = ["DEVICE_PATH", "SB3_PATH", "DevicePPO", "TensorRolloutBuffer", "rollout_path", "find_adapter"]

DEVICE_PATH = "device"  # tensors end to end (DevicePPO)
SB3_PATH = "sb3"  # SB3's NumPy rollout


def rollout_path(cfg: dict[str, Any]) -> tuple[str, str]:
    """(``"device"`` or ``"sb3"``, the reason in words) for a validated training config.

    The device path needs PPO and an env that takes ``backend="torch"`` (the abd_gym envs); a
    VecNormalize config normalises on the device (:mod:`.device_normalize`).  The config's
    ``rollout``: ``auto`` takes the device path where it applies on a GPU, and SB3's path on the
    CPU, where the device path's per-step tensor operations cost more than SB3's NumPy
    (results/solver_notes.md); ``sb3`` forces
    SB3's path; ``device`` forces the device path, and raises a ``ValueError`` with the reason where
    it does not apply.
    """
    choice = cfg.get("rollout", "auto")
    if choice == SB3_PATH:
        return SB3_PATH, "the config asks for SB3's rollout (rollout: sb3)"
    refusal = device_path_refusal(cfg)
    if refusal is None:
        if choice == DEVICE_PATH:
            return DEVICE_PATH, "the config asks for the device rollout (rollout: device)"
        if not str(cfg["device"]).startswith("cuda"):
            return SB3_PATH, "SB3's NumPy rollout, the faster on the CPU; rollout: device forces the device path"
        return DEVICE_PATH, "PPO on a GPU, on an env with the Torch backend"
    if choice == DEVICE_PATH:
        raise ValueError(f"rollout: the device rollout does not apply: {refusal}")
    return SB3_PATH, refusal


def device_path_refusal(cfg: dict[str, Any]) -> str | None:
    """Why the device path does not apply to ``cfg`` (in words), or None where it does."""
    if cfg["algo"] != "ppo":
        return f"{cfg['algo']} is not PPO"
    if not _takes_torch_backend(cfg["env_id"]):
        return f"{cfg['env_id']} has no Torch backend"
    return None


def _takes_torch_backend(env_id: str) -> bool:
    import inspect

    import gymnasium as gym
    from gymnasium.envs.registration import load_env_creator

    import abd_gym  # noqa: F401 -- registers the ids

    creator = gym.spec(env_id).vector_entry_point
    if creator is None:
        return False
    creator = load_env_creator(creator) if isinstance(creator, str) else creator
    init = creator.__init__ if inspect.isclass(creator) else creator
    return _accepts(init, "backend") and _accepts(init, "autoreset_mode")


def find_adapter(env: VecEnv) -> GymnasiumVecEnv | None:
    """The :class:`GymnasiumVecEnv` under SB3 VecEnv wrappers, or None."""
    while env is not None and not isinstance(env, GymnasiumVecEnv):
        env = getattr(env, "venv", None)
    return env


class _HostView:
    """A buffer field read as a host NumPy array, for code written against SB3's NumPy buffer
    (``explained_variance`` in ``PPO.train`` reads ``values`` and ``returns``).  ``valid_only``:
    once flattened, a NEXT_STEP rollout's field reads at its valid positions only."""

    def __init__(self, valid_only: bool = False):
        self.valid_only = valid_only

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name

    def __get__(self, buf: Any, owner: type | None = None) -> Any:
        if buf is None:
            return self
        x = buf.tensors[self.name]
        if self.valid_only and buf.next_step and buf.generator_ready:
            x = x[buf._valid_idx]
        return x.detach().cpu().numpy()


class TensorRolloutBuffer(RolloutBuffer):
    """:class:`RolloutBuffer` whose fields are tensors on ``device`` in ``tensors[name]``.

    Shapes and dtypes follow SB3's buffer: (n_steps, n_envs, ...) float32 while filling, flattened
    world-major to (n_steps * n_envs, ...) (scalars per transition to (n_steps * n_envs, 1)) by the
    first :meth:`get` (SB3's ``swap_and_flatten``), so the same index draws the same transition as
    in SB3's buffer.  Actions are stored as float32 (SB3 casts them to float32 when sampling).  The
    SB3 field names read as host NumPy copies.

    ``storage`` holds the (n_steps, n_envs, ...) tensors, allocated once (``tensors`` starts each
    rollout as a view of it); :meth:`reset` leaves their values, which a rollout writes whole
    before its update reads them (every position of the fields it fills, then GAE's).

    ``next_step`` (set after :meth:`reset`, read by :meth:`compute_returns_and_advantage` and
    :meth:`get`): the rollout came from a NEXT_STEP env, and :class:`~.graphed_rollout.RolloutStep`
    wrote each position's ``valid`` (not a reset step), ``dones`` (terminated or truncated) and
    ``cuts`` (truncated, not terminated) as (n_steps, n_envs) float32 into ``storage``;
    ``ep_return`` and ``ep_length`` hold the episode's return and length so far after each position; once
    flattened, ``values`` and ``returns`` read (on the host) at the valid positions only, so that
    PPO's explained variance leaves the reset steps out.
    """

    FIELDS = ("observations", "actions", "rewards", "returns", "episode_starts", "values", "log_probs", "advantages")
    FLAGS = ("valid", "dones", "cuts", "ep_return", "ep_length")
    SAMPLED = SAMPLED  # what minibatches read
    observations = _HostView()
    actions = _HostView()
    rewards = _HostView()
    returns = _HostView(valid_only=True)
    episode_starts = _HostView()
    values = _HostView(valid_only=True)
    log_probs = _HostView()
    advantages = _HostView()

    def reset(self) -> None:
        shapes = {
            "observations": (*self.obs_shape,),
            "actions": (self.action_dim,),
        }
        if getattr(self, "storage", None) is None:  # allocated once: a captured rollout step writes here
            self.storage = {
                name: th.zeros((self.buffer_size, self.n_envs, *shapes.get(name, ())), dtype=th.float32,
                               device=self.device)
                for name in self.FIELDS + self.FLAGS
            }  # fmt: skip
        self.tensors = dict(self.storage)
        self.next_step = False
        self.generator_ready = False
        BaseBuffer.reset(self)

    def add(self, obs: th.Tensor, action: th.Tensor, reward: th.Tensor, episode_start: th.Tensor,
            value: th.Tensor, log_prob: th.Tensor) -> None:  # fmt: skip
        t, p = self.tensors, self.pos
        t["observations"][p] = obs.reshape(self.n_envs, *self.obs_shape)
        t["actions"][p] = action.reshape(self.n_envs, self.action_dim)
        t["rewards"][p] = reward
        t["episode_starts"][p] = episode_start
        t["values"][p] = value.flatten()
        t["log_probs"][p] = log_prob.reshape(self.n_envs)
        self.pos += 1
        if self.pos == self.buffer_size:
            self.full = True

    def compute_returns_and_advantage(self, last_values: th.Tensor, dones: th.Tensor) -> None:
        """GAE(lambda) on the device, in SB3's order of float32 operations:
        ``delta_t = r_t + gamma V_{t+1} (1 - d_{t+1}) - V_t``,
        ``A_t = delta_t + gamma lambda (1 - d_{t+1}) A_{t+1}``, returns ``A + V``.

        ``next_step``: ``1 - d_{t+1}`` is ``1 - done_t`` (the step's own flags; ``dones`` is not
        read) and a position cut by its time limit first gets ``r_t += gamma V_{t+1}``
        (``V_{t+1}``: the next position's value, of the final observation, or ``last_values``);
        one kernel (:func:`~.rollout_kernels.gae_kernel`) runs it, a thread per world."""
        t = self.tensors
        last_values = last_values.detach().flatten().to(th.float32)
        if self.next_step:
            device = last_values.device
            with warp_on_torch_stream(device):
                wp.launch(gae_kernel, dim=self.n_envs,
                          inputs=[*(wp.from_torch(t[k]) for k in ("rewards", "values", "dones", "cuts")),
                                  wp.from_torch(last_values), self.gamma, self.gamma * self.gae_lambda,
                                  wp.from_torch(t["advantages"]), wp.from_torch(t["returns"])],
                          device=wp.device_from_torch(device))  # fmt: skip
            return
        last_gae_lam: Any = 0
        for step in reversed(range(self.buffer_size)):
            if step == self.buffer_size - 1:
                nnt, nv = 1.0 - dones.to(th.float32), last_values
            else:
                nnt, nv = 1.0 - t["episode_starts"][step + 1], t["values"][step + 1]
            delta = t["rewards"][step] + self.gamma * nv * nnt - t["values"][step]
            last_gae_lam = delta + self.gamma * self.gae_lambda * nnt * last_gae_lam
            t["advantages"][step] = last_gae_lam
        th.add(t["advantages"], t["values"], out=t["returns"])  # in place: a captured GAE writes here

    def get(self, batch_size: int | None = None) -> Generator[RolloutBufferSamples, None, None]:
        """Minibatches of ``batch_size`` (the last one smaller if it must be) in an order drawn from
        NumPy's global generator; ``next_step``: of the valid positions only."""
        for batch_inds in self.minibatch_indices(batch_size):
            yield self._get_samples(batch_inds)

    def flatten(self) -> None:
        """The fields PPO's update reads, flattened world-major to (n_steps * n_envs, ...) (once)."""
        assert self.full, ""
        if self.generator_ready:
            return
        n = self.buffer_size * self.n_envs
        for name in self.SAMPLED:
            x = self.tensors[name]
            self.tensors[name] = x.transpose(0, 1).reshape(n, *(x.shape[2:] or (1,)))
        if self.next_step:
            self._valid_idx = th.nonzero(self.tensors["valid"].transpose(0, 1).reshape(n)).flatten()
        self.generator_ready = True

    def minibatch_indices(self, batch_size: int | None = None) -> Iterator[th.Tensor]:
        """The flat indices of each minibatch (int64 on the device), in :meth:`get`'s order."""
        self.flatten()
        if self.next_step:
            m = len(self._valid_idx)
            indices = self._valid_idx[th.as_tensor(np.random.permutation(m), device=self.device)]
        else:
            m = self.buffer_size * self.n_envs
            indices = th.as_tensor(np.random.permutation(m), device=self.device)
        batch_size = m if batch_size is None else batch_size
        for start in range(0, m, batch_size):
            yield indices[start : start + batch_size]

    def _get_samples(self, batch_inds: th.Tensor, env: Any = None) -> RolloutBufferSamples:
        t = self.tensors
        return RolloutBufferSamples(
            t["observations"][batch_inds],
            t["actions"][batch_inds],
            t["values"][batch_inds].flatten(),
            t["log_probs"][batch_inds].flatten(),
            t["advantages"][batch_inds].flatten(),
            t["returns"][batch_inds].flatten(),
        )


class DevicePPO(GraphedPPO):
    """PPO whose rollout stays on the policy's device (see the module docstring).

    The training env must be a :class:`GymnasiumVecEnv` that :meth:`~GymnasiumVecEnv.step_tensors`
    can serve (SAME_STEP or NEXT_STEP autoreset), optionally under :class:`VecMonitor` (whose
    episode clock ``"t"`` is used).  With a NEXT_STEP env, 1 in (episode length + 1) of the
    transitions ``num_timesteps`` counts is a reset step that trains nothing.
    """

    def __init__(self, *args: Any, **kwargs: Any):
        kwargs.setdefault("rollout_buffer_class", TensorRolloutBuffer)
        super().__init__(*args, **kwargs)

    def _excluded_save_params(self) -> list[str]:
        # a saved model loads as a plain PPO with SB3's buffer (and a fresh reset: the last
        # observation is a tensor here, NumPy in SB3's rollout)
        return [*super()._excluded_save_params(), "rollout_buffer_class", "rollout_buffer_kwargs", "_adapter",
                "_ep_return", "_ep_length", "_low", "_high", "_last_obs", "_last_episode_starts",
                "_ended", "_next_step", "_rollout_step", "_vecnormalize"]  # fmt: skip

    def _flat_fields(self) -> dict[str, th.Tensor]:
        buf = self.rollout_buffer
        buf.flatten()
        return {name: buf.tensors[name] for name in SAMPLED}

    def _minibatch_indices(self) -> Iterator[th.Tensor]:
        return self.rollout_buffer.minibatch_indices(self.batch_size)

    def _setup_learn(self, *args: Any, **kwargs: Any) -> Any:
        out = super()._setup_learn(*args, **kwargs)
        if isinstance(self._last_obs, np.ndarray) and getattr(self, "_adapter", None) is not None:
            self._restart_episodes()  # the env was reset (the rollout keeps its observation as a tensor)
        return out

    def _bind(self, env: VecEnv) -> None:
        """Find the adapter under ``env``'s wrappers and set up the episode statistics."""
        adapter = find_adapter(env)
        refusal = "the env is not a GymnasiumVecEnv" if adapter is None else adapter.tensor_path_refusal()
        if refusal is not None:
            raise ValueError(f"DevicePPO needs a SAME_STEP or NEXT_STEP GymnasiumVecEnv with the Torch backend: "
                             f"{refusal}")  # fmt: skip
        self._adapter = adapter
        self._next_step = adapter.autoreset_mode == AutoresetMode.NEXT_STEP
        self._rollout_step = None
        self._vecnormalize = find_vecnormalize(env)
        if self._vecnormalize is not None and not self._next_step:
            raise ValueError("DevicePPO normalises (VecNormalize) on a NEXT_STEP env only: this env autoresets "
                             f"{adapter.autoreset_mode.name}")  # fmt: skip
        monitor = env
        while monitor is not None and not isinstance(monitor, VecMonitor):
            monitor = getattr(monitor, "venv", None)
        self._t_start = monitor.t_start if monitor is not None else time.time()
        self._restart_episodes()
        if isinstance(self.action_space, spaces.Box):
            self._low = th.as_tensor(self.action_space.low, device=self.device)
            self._high = th.as_tensor(self.action_space.high, device=self.device)

    def _restart_episodes(self) -> None:
        """Episode statistics and the NEXT_STEP carry ("ended at the previous step") of a fresh reset."""
        n, dev = self._adapter.num_envs, self.device
        self._ep_return = th.zeros(n, dtype=th.float32, device=dev)
        self._ep_length = th.zeros(n, dtype=th.int64, device=dev)
        self._ended = th.zeros(n, dtype=th.bool, device=dev)

    def _env_actions(self, actions: th.Tensor) -> th.Tensor:
        if not isinstance(self.action_space, spaces.Box):
            return actions
        if self.policy.squash_output:
            return self._low + 0.5 * (actions + 1.0) * (self._high - self._low)
        return th.clamp(actions, self._low, self._high)

    def _as_device(self, x: Any, dtype: th.dtype | None = None) -> th.Tensor:
        return th.as_tensor(x, device=self.device) if dtype is None else th.as_tensor(x, dtype=dtype, device=self.device)

    def _record_episodes(self, rewards: th.Tensor, done: np.ndarray) -> None:
        """VecMonitor's episode statistics on the device; finished episodes go to ``ep_info_buffer``."""
        self._ep_return += rewards
        self._ep_length += 1
        if not done.any():
            return
        idx = th.as_tensor(np.flatnonzero(done), device=self.device)
        returns = self._ep_return[idx].cpu().numpy()
        lengths = self._ep_length[idx].cpu().numpy()
        self._add_episodes(returns, lengths)
        self._ep_return[idx] = 0.0
        self._ep_length[idx] = 0

    def _add_episodes(self, returns: np.ndarray, lengths: np.ndarray) -> None:
        keep = self.ep_info_buffer.maxlen
        if keep:  # the deque keeps the last ``keep`` (100): a dict for each of thousands took ms a rollout
            returns, lengths = returns[-keep:], lengths[-keep:]
        t = round(time.time() - self._t_start, 6)
        self.ep_info_buffer.extend({"r": round(float(r), 6), "l": int(l), "t": t} for r, l in zip(returns, lengths))

    def _flush_episodes(self, buf: TensorRolloutBuffer) -> None:
        """NEXT_STEP: the rollout's finished episodes to ``ep_info_buffer`` in SB3's order (step by
        step, worlds in order): the last ``maxlen`` of them, which the rollout step's :meth:`finish`
        gathered (``tail``), in one read on the host."""
        steps = self._rollout_step
        tail = steps.tail.cpu().numpy()
        tail = tail[:, : int(tail[0, steps.tail_size])]
        if tail.shape[1]:
            self._add_episodes(tail[0], tail[1].astype(np.int64))

    def _bootstrap_timeouts(self, step: Any, rewards: th.Tensor) -> th.Tensor:
        """``rewards + gamma * V(final_obs)`` in the worlds cut by their time limit (not terminated)."""
        if not step.done.any():
            return rewards
        cut = (step.truncated & ~step.terminated).cpu().numpy() & step.done
        if not cut.any():
            return rewards
        rewards = rewards.clone()  # the env's own tensor stays as it gave it
        idx = th.as_tensor(np.flatnonzero(cut), device=self.device)
        final_obs = step.final_obs[idx.to(step.final_obs.device)].to(self.device)
        with th.no_grad():
            terminal_values = self.policy.predict_values(final_obs).flatten()
        rewards[idx] += self.gamma * terminal_values
        return rewards

    def collect_rollouts(self, env: VecEnv, callback: Any, rollout_buffer: RolloutBuffer, n_rollout_steps: int) -> bool:
        with unchecked_distributions():
            return self._collect_rollouts(env, callback, rollout_buffer, n_rollout_steps)

    def _collect_rollouts(self, env: VecEnv, callback: Any, rollout_buffer: RolloutBuffer,
                          n_rollout_steps: int) -> bool:  # fmt: skip
        assert self._last_obs is not None, "No previous observation was provided"
        if getattr(self, "_adapter", None) is None or find_adapter(env) is not self._adapter:
            self._bind(env)
        self.policy.set_training_mode(False)
        self._last_obs = self._as_device(self._last_obs)
        self._last_episode_starts = self._as_device(self._last_episode_starts, th.float32)
        rollout_buffer.reset()
        if self.use_sde:
            self.policy.reset_noise(env.num_envs)
        callback.on_rollout_start()
        if self._next_step:
            return self._collect_next_step(env, callback, rollout_buffer, n_rollout_steps)
        n_steps = 0
        dones = None
        while n_steps < n_rollout_steps:
            actions, values, log_probs, step, new_obs, rewards = self._act(env, n_steps)
            dones = self._as_device(step.done)
            self.num_timesteps += env.num_envs
            callback.update_locals(locals())
            if not callback.on_step():
                return False
            self._record_episodes(rewards, step.done)
            n_steps += 1
            if isinstance(self.action_space, spaces.Discrete):
                actions = actions.reshape(-1, 1)
            rewards = self._bootstrap_timeouts(step, rewards)
            rollout_buffer.add(self._last_obs, actions, rewards, self._last_episode_starts, values, log_probs)
            self._last_obs = new_obs
            self._last_episode_starts = dones.to(th.float32)
        with th.no_grad():
            values = self.policy.predict_values(new_obs)
        rollout_buffer.compute_returns_and_advantage(last_values=values, dones=dones)
        callback.update_locals(locals())
        callback.on_rollout_end()
        return True

    def _act(self, env: VecEnv, n_steps: int) -> tuple:
        """One step of the rollout's policy and env: (actions, values, log-probs, the env's
        TensorStep, the next observation (a copy on the policy's device), the rewards there)."""
        self._sample_noise(n_steps)
        with th.no_grad():
            actions, values, log_probs = self.policy(self._last_obs)
        step = self._adapter.step_tensors(self._env_actions(actions))
        new_obs = step.obs.to(self.device, copy=True)  # the env may write its next step into its tensor
        return actions, values, log_probs, step, new_obs, step.rewards.to(self.device)

    def _sample_noise(self, n_steps: int) -> None:
        """A state-dependent exploration's new noise before step ``n_steps``'s action, as SB3 draws it."""
        if self.use_sde and self.sde_sample_freq > 0 and n_steps % self.sde_sample_freq == 0:
            self.policy.reset_noise(self._adapter.num_envs)

    def _new_rollout_step(self, capture: bool | None = None) -> RolloutStep:
        """The NEXT_STEP rollout's step (``capture``: as :class:`~.cuda_graph.GraphedCall`'s), with
        the training env's VecNormalize statistics on the device where it has them."""
        norm = None
        if self._vecnormalize is not None:
            norm = DeviceNormalize(self._vecnormalize, self._adapter.num_envs, self.device)
        # no capture where a step's launches are not fixed: a state-dependent exploration's noise
        # is redrawn into new tensors, and Categorical sampling (multinomial) reads its
        # probabilities' check back to the host in some Torch versions
        if self.use_sde or isinstance(self.action_space, spaces.Discrete):
            capture = False
        return RolloutStep(self, capture=capture, normalize=norm)

    def _collect_next_step(self, env: VecEnv, callback: Any, rollout_buffer: TensorRolloutBuffer,
                           n_rollout_steps: int) -> bool:  # fmt: skip
        """The rollout on a NEXT_STEP env (module docstring): device work only, no host reads until
        the rollout's end; each step's policy and bookkeeping are one CUDA graph each on a GPU
        (:class:`~.graphed_rollout.RolloutStep`)."""
        rollout_buffer.next_step = True
        steps = getattr(self, "_rollout_step", None)
        if steps is None:
            self._rollout_step = steps = self._new_rollout_step()
        steps.start(rollout_buffer)
        self._sample_noise(0)
        steps.act()
        for n_steps in range(n_rollout_steps):
            steps.env_step()
            self.num_timesteps += env.num_envs
            actions, values, log_probs, rewards = steps.actions, steps.values, steps.log_probs, steps.rewards
            callback.update_locals(locals())
            if not callback.on_step():
                steps.end()
                return False
            if n_steps + 1 < n_rollout_steps:
                self._sample_noise(n_steps + 1)
                steps.record_act()  # this step's record and the next step's policy, one graph
            else:
                steps.record()
        steps.end()
        rollout_buffer.pos, rollout_buffer.full = n_rollout_steps, True
        steps.finish()  # the last observation's values and GAE
        values = steps.last_values
        self._flush_episodes(rollout_buffer)
        callback.update_locals(locals())
        callback.on_rollout_end()
        return True
