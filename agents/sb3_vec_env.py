"""Stable-Baselines3 view of a Gymnasium 1.x ``VectorEnv``.

SB3 algorithms talk to a :class:`stable_baselines3.common.vec_env.VecEnv`: ``step`` returns
``(obs, rewards, dones, infos)`` with NumPy arrays and one info dict per world, and a world that
finishes is reset *in the same step*: its returned observation is the first of the next episode,
the last one of the finished episode sits in ``infos[i]["terminal_observation"]`` and
``infos[i]["TimeLimit.truncated"]`` says the episode was cut by a time limit rather than
terminated.  :class:`GymnasiumVecEnv` gives that view of any Gymnasium vector env:

* ``AutoresetMode.SAME_STEP`` (what :func:`make_vec_env` asks for): the env already resets in the
  same step and reports ``info["final_obs"]`` / ``info["final_info"]``; the adapter only renames.
* ``AutoresetMode.NEXT_STEP`` / ``DISABLED``: after a step in which worlds finish, the adapter resets
  exactly those worlds with ``env.reset(options={"reset_mask": dones})`` (Gymnasium 1.x's partial
  reset) and returns the reset observations.  A NEXT_STEP env that cannot reset a subset of its
  worlds (Gymnasium's own ``CartPoleVectorEnv``, for one) cannot give SB3 correct transitions --
  its reset step would enter the buffers as a fake zero-reward transition -- so the adapter
  checks this when it is built and refuses such an env with a ``ValueError``;
  :func:`make_vec_env` then falls back to a SAME_STEP ``SyncVectorEnv`` of the single env.

The hot path is array code over all worlds; the only per-world Python work is building the list
of info dicts SB3 requires, and only done worlds get keys in it.  Torch tensors (``backend="torch"``
envs) are moved to NumPy on the way out, actions to tensors on the env's device on the way in.

:meth:`GymnasiumVecEnv.step_tensors` is the other way out for a SAME_STEP or NEXT_STEP env with the
Torch backend: the step's tensors as they are, on the env's device, with no per-world info dicts
(the device-resident PPO rollout in :mod:`abd_gym.agents.device_rollout` reads it).  In NEXT_STEP
mode it reads nothing on the host, so the env's step can run as its CUDA graph.
"""
from __future__ import annotations

import inspect
from collections.abc import Sequence
from typing import Any, NamedTuple

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices, VecEnvObs, VecEnvStepReturn

__all__ = ["GymnasiumVecEnv", "TensorStep", "make_vec_env", "make_gym_vector_env", "autoreset_mode_of"]


class TensorStep(NamedTuple):
    """One step of all N worlds as Torch tensors on the env's device (``done`` on the host).

    SAME_STEP: ``obs`` (N, ...) is the first observation of the next episode where a world
    finished; ``final_obs`` (N, ...) holds the finished episode's last observation in those rows
    (None when no world finished); ``done`` is the host bool mask ``terminated | truncated`` the
    SAME_STEP reset already had to read.  NEXT_STEP: ``obs`` is the env's as it is (a finished
    world's last observation; the next step resets it), ``done`` and ``final_obs`` are None (the
    flags stay on the device).
    """

    obs: Any
    rewards: Any  # (N,) float32
    terminated: Any  # (N,) bool
    truncated: Any  # (N,) bool
    done: np.ndarray | None  # (N,) bool, host (SAME_STEP)
    final_obs: Any


# ---------------------------------------------------------------------------------------------
# array helpers


def _is_torch(x: Any) -> bool:
    return type(x).__module__.startswith("torch") and hasattr(x, "detach")


def _to_numpy(x: Any) -> Any:
    """NumPy view of an observation / reward / flag batch (torch, warp, dict of them, or arrays)."""
    if isinstance(x, np.ndarray):
        return x
    if isinstance(x, dict):
        return {k: _to_numpy(v) for k, v in x.items()}
    if isinstance(x, tuple):
        return tuple(_to_numpy(v) for v in x)
    if _is_torch(x):
        return x.detach().cpu().numpy()
    if hasattr(x, "numpy") and callable(x.numpy):  # warp arrays
        return x.numpy()
    return np.asarray(x)


def _copy_obs(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _copy_obs(v) for k, v in x.items()}
    if isinstance(x, tuple):
        return tuple(_copy_obs(v) for v in x)
    return np.array(x, copy=True)


def _world(x: Any, i: int) -> Any:
    """Observation of world ``i`` from a batch (arrays, dicts of arrays, or object arrays)."""
    if isinstance(x, dict):
        return {k: _world(v, i) for k, v in x.items()}
    if isinstance(x, tuple):
        return tuple(_world(v, i) for v in x)
    item = x[i]
    if _is_torch(item) or (not isinstance(item, (np.ndarray, dict, tuple)) and hasattr(item, "numpy")):
        item = _to_numpy(item)
    if isinstance(item, np.ndarray):
        return item.copy()
    return item


def _set_worlds(dst: Any, src: Any, mask: np.ndarray) -> None:
    if isinstance(dst, dict):
        for k in dst:
            _set_worlds(dst[k], src[k], mask)
    elif isinstance(dst, tuple):
        for d, s in zip(dst, src):
            _set_worlds(d, s, mask)
    else:
        dst[mask] = src[mask]


def _info_of_world(info: dict[str, Any], i: int, n: int) -> dict[str, Any]:
    """World ``i``'s entries of a Gymnasium vector info dict.

    Gymnasium stores a per-world value ``info[key]`` (length ``n``) next to a mask ``info["_" + key]``
    saying which worlds have it; nested dicts (``final_info``) follow the same layout.  Values
    without a mask are taken per world when their length is ``n`` and as they are otherwise.
    """
    out: dict[str, Any] = {}
    for key, value in info.items():
        if key.startswith("_"):
            continue
        mask = info.get("_" + key)
        if mask is not None and not bool(np.asarray(_to_numpy(mask)).reshape(-1)[i]):
            continue
        if isinstance(value, dict):
            out[key] = _info_of_world(value, i, n)
            continue
        if _is_torch(value) or isinstance(value, (np.ndarray, list, tuple)):
            if len(value) == n:
                item = value[i]
                if _is_torch(item):
                    item = item.detach().cpu().numpy()
                if isinstance(item, np.ndarray) and item.ndim == 0 or isinstance(item, np.generic):
                    item = item.item()
                out[key] = item
                continue
        out[key] = value
    return out


def autoreset_mode_of(env: gym.vector.VectorEnv) -> AutoresetMode:
    """The env's autoreset mode from ``metadata["autoreset_mode"]`` (Gymnasium's default: NEXT_STEP)."""
    mode = getattr(env, "metadata", {}).get("autoreset_mode", AutoresetMode.NEXT_STEP)
    if isinstance(mode, AutoresetMode):
        return mode
    for m in AutoresetMode:
        if str(mode) in (m.value, m.name, str(m)):
            return m
    raise ValueError(f"unknown autoreset_mode {mode!r} in the env's metadata")


# ---------------------------------------------------------------------------------------------
# the adapter


class GymnasiumVecEnv(VecEnv):
    """SB3 ``VecEnv`` over a Gymnasium ``VectorEnv`` (see the module docstring).

    ``check_partial_reset``: for NEXT_STEP envs, verify at construction (one reset, one step and a
    masked reset) that ``reset(options={"reset_mask": ...})`` leaves the other worlds alone.
    """

    def __init__(self, env: gym.vector.VectorEnv, *, check_partial_reset: bool = True):
        self.env = env
        self.autoreset_mode = autoreset_mode_of(env)
        self._torch_device = None  # set when the env speaks torch
        self._actions: Any = None
        self._last_obs: Any = None
        super().__init__(env.num_envs, env.single_observation_space, env.single_action_space)
        if self.autoreset_mode == AutoresetMode.NEXT_STEP and check_partial_reset and self.num_envs > 1:
            self._check_partial_reset()

    # -- construction-time check ------------------------------------------------------------
    def _check_partial_reset(self) -> None:
        reason = None
        try:
            obs, _ = self.env.reset(seed=12345)
            self._note_backend(obs)
            obs, *_ = self.env.step(self._env_actions(self._sample_actions()))
            before = _copy_obs(_to_numpy(obs))
            mask = np.zeros(self.num_envs, dtype=bool)
            mask[0] = True
            after, _ = self.env.reset(options={"reset_mask": mask})
            after = _to_numpy(after)
            keep = ~mask
            same = _tree_all(lambda a, b: _unchanged(a[keep], b[keep]), before, after)
            if not same:
                reason = "reset(options={'reset_mask': ...}) also reset worlds outside the mask"
        except Exception as exc:  # noqa: BLE001 -- any failure means no usable partial reset
            reason = f"reset(options={{'reset_mask': ...}}) failed: {exc!r}"
        if reason is not None:
            raise ValueError(
                f"{type(self.env.unwrapped).__name__} autoresets in NEXT_STEP mode and cannot reset a "
                f"subset of worlds ({reason}); SB3 needs same-step resets. Create it with "
                "autoreset_mode=gymnasium.vector.AutoresetMode.SAME_STEP (or vectorization_mode='sync' "
                "with vector_kwargs={'autoreset_mode': AutoresetMode.SAME_STEP}); "
                "abd_gym.agents.sb3_vec_env.make_vec_env does this for a registered id."
            )

    def _sample_actions(self) -> np.ndarray:
        return np.stack([self.action_space.sample() for _ in range(self.num_envs)])

    # -- backend plumbing -------------------------------------------------------------------
    def _note_backend(self, obs: Any) -> None:
        leaf = obs
        while isinstance(leaf, (dict, tuple)):
            leaf = next(iter(leaf.values())) if isinstance(leaf, dict) else leaf[0]
        if _is_torch(leaf):
            self._torch_device = leaf.device

    def _env_actions(self, actions: np.ndarray) -> Any:
        if self._torch_device is not None:
            import torch

            return torch.as_tensor(actions, device=self._torch_device)
        return actions

    # -- VecEnv API ---------------------------------------------------------------------------
    def reset(self) -> VecEnvObs:
        kwargs: dict[str, Any] = {}
        if any(s is not None for s in self._seeds):
            kwargs["seed"] = int(self._seeds[0])  # Gymnasium vector envs seed world i with seed + i
        if any(self._options):
            if any(o != self._options[0] for o in self._options):
                raise ValueError("a Gymnasium vector env takes one options dict for all worlds")
            kwargs["options"] = dict(self._options[0])
        obs, info = self.env.reset(**kwargs)
        self._note_backend(obs)
        obs = _to_numpy(obs)
        self.reset_infos = [_info_of_world(info, i, self.num_envs) if info else {} for i in range(self.num_envs)]
        self._reset_seeds()
        self._reset_options()
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = actions

    def step_wait(self) -> VecEnvStepReturn:
        n = self.num_envs
        obs, rewards, terminated, truncated, info = self.env.step(self._env_actions(self._actions))
        obs = _to_numpy(obs)
        rewards = np.asarray(_to_numpy(rewards), dtype=np.float32).reshape(n)
        terminated = np.asarray(_to_numpy(terminated), dtype=bool).reshape(n)
        truncated = np.asarray(_to_numpy(truncated), dtype=bool).reshape(n)
        dones = terminated | truncated
        infos: list[dict[str, Any]] = [{} for _ in range(n)]
        if not dones.any():
            return obs, rewards, dones, infos

        done_idx = np.flatnonzero(dones)
        if self.autoreset_mode == AutoresetMode.SAME_STEP:
            if "final_obs" not in info:
                raise RuntimeError("SAME_STEP env reported done worlds without info['final_obs']")
            final_obs = info["final_obs"]
            if not (isinstance(final_obs, np.ndarray) and final_obs.dtype == object):
                final_obs = _to_numpy(final_obs)  # one device->host copy, not one per world
            final_info = info.get("final_info", {})
            for i in done_idx:
                i = int(i)
                d = _info_of_world(final_info, i, n) if final_info else {}
                d["terminal_observation"] = _world(final_obs, i)
                d["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
                infos[i] = d
                reset_info = {k: v for k, v in info.items() if k.lstrip("_") not in ("final_obs", "final_info")}
                self.reset_infos[i] = _info_of_world(reset_info, i, n) if reset_info else {}
        else:
            for i in done_idx:
                i = int(i)
                d = _info_of_world(info, i, n) if info else {}
                d["terminal_observation"] = _world(obs, i)
                d["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
                infos[i] = d
            reset_obs, reset_info = self.env.reset(options={"reset_mask": dones})
            obs = _copy_obs(obs)  # the env may hand back (and now overwrite) its own buffer
            _set_worlds(obs, _to_numpy(reset_obs), dones)
            for i in done_idx:
                self.reset_infos[int(i)] = _info_of_world(reset_info, int(i), n) if reset_info else {}
        return obs, rewards, dones, infos

    def close(self) -> None:
        self.env.close()

    # -- tensor path ------------------------------------------------------------------------------
    def tensor_path_refusal(self) -> str | None:
        """Why :meth:`step_tensors` cannot serve this env (None: it can)."""
        if self.autoreset_mode not in (AutoresetMode.SAME_STEP, AutoresetMode.NEXT_STEP):
            return f"the env autoresets in {self.autoreset_mode.name} mode, not SAME_STEP or NEXT_STEP"
        if getattr(self.env.unwrapped, "backend", None) != "torch":
            return "the env does not have the Torch backend"
        if not isinstance(self.observation_space, gym.spaces.Box):
            return f"observation space {type(self.observation_space).__name__} is not a Box"
        return None

    def fixed_outputs(self) -> tuple | None:
        """(obs, rewards, terminated, truncated): the tensors every later NEXT_STEP
        :meth:`step_tensors` writes and returns, where the env offers them
        (``ABDVectorEnv.fixed_outputs``, with no wrapper between), else None."""
        fixed = getattr(self.env, "fixed_outputs", None) if self.env is self.env.unwrapped else None
        if self.autoreset_mode != AutoresetMode.NEXT_STEP or fixed is None:
            return None
        return fixed()

    def step_tensors(self, actions: Any) -> TensorStep:
        """Step all worlds with ``actions`` (a tensor on any device) and return the tensors as the
        env gives them; the env's info dicts are not split per world (no ``infos`` list).  A
        NEXT_STEP env's step is returned without reading anything on the host (see
        :class:`TensorStep`)."""
        import torch

        n = self.num_envs
        device = self._torch_device
        obs, rewards, terminated, truncated, info = self.env.step(actions.to(device))
        rewards = rewards.reshape(n).to(torch.float32)
        terminated = terminated.reshape(n).to(torch.bool)
        truncated = truncated.reshape(n).to(torch.bool)
        if self.autoreset_mode == AutoresetMode.NEXT_STEP:
            return TensorStep(obs, rewards, terminated, truncated, None, None)
        mask = info.get("_final_obs")
        if mask is None:
            return TensorStep(obs, rewards, terminated, truncated, np.zeros(n, dtype=bool), None)
        done = np.asarray(_to_numpy(mask), dtype=bool).reshape(n)
        return TensorStep(obs, rewards, terminated, truncated, done, info["final_obs"])

    # -- attributes and methods ---------------------------------------------------------------
    # A native batched env is one object holding every world: its attributes and methods are
    # shared, so they are read / called once and the result is given for each requested index.
    # Sync/Async vector envs of single envs also expose their sub-envs' attributes per index.

    def _layers(self) -> list[Any]:
        layers, env = [], self.env
        while True:
            layers.append(env)
            nxt = getattr(env, "env", None)
            if nxt is None or nxt is env or not isinstance(nxt, gym.vector.VectorEnv):
                break
            env = nxt
        if self.env.unwrapped not in layers:
            layers.append(self.env.unwrapped)
        return layers

    def _find(self, name: str) -> tuple[Any, Any]:
        """(layer, value) of the outermost wrapper layer (or the unwrapped env) that has ``name``."""
        for layer in self._layers():
            try:
                return layer, getattr(layer, name)
            except AttributeError:
                continue
        raise AttributeError(name)

    def _sub_envs(self) -> Sequence[Any] | None:
        envs = getattr(self.env.unwrapped, "envs", None)
        return envs if isinstance(envs, (list, tuple)) else None

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        idx = list(self._get_indices(indices))
        try:
            _, value = self._find(attr_name)
            return [value for _ in idx]
        except AttributeError:
            pass
        unwrapped = self.env.unwrapped
        if hasattr(unwrapped, "get_attr") and self._sub_envs() is not None:
            values = unwrapped.get_attr(attr_name)
            return [values[i] for i in idx]
        raise AttributeError(f"{type(unwrapped).__name__} has no attribute {attr_name!r}")

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        idx = list(self._get_indices(indices))
        all_worlds = sorted(idx) == list(range(self.num_envs))
        try:
            layer, _ = self._find(attr_name)
        except AttributeError:
            layer = None
        if layer is not None and all_worlds:
            setattr(layer, attr_name, value)
            return
        unwrapped = self.env.unwrapped
        if hasattr(unwrapped, "set_attr") and self._sub_envs() is not None:
            envs = self._sub_envs()
            for i in idx:
                setattr(envs[i].unwrapped if not hasattr(envs[i], attr_name) else envs[i], attr_name, value)
            return
        if layer is None:
            raise AttributeError(f"{type(unwrapped).__name__} has no attribute {attr_name!r}")
        raise ValueError(
            f"{attr_name!r} is one attribute shared by all {self.num_envs} worlds of this batched env; "
            "set it with indices=None"
        )

    def env_method(self, method_name: str, *method_args, indices: VecEnvIndices = None, **method_kwargs) -> list[Any]:
        idx = list(self._get_indices(indices))
        try:
            _, method = self._find(method_name)
        except AttributeError:
            method = None
        if callable(method):
            result = method(*method_args, **method_kwargs)
            return [result for _ in idx]
        envs = self._sub_envs()
        if envs is not None:
            out = []
            for i in idx:
                env = envs[i]
                fn = getattr(env, method_name, None)
                if fn is None and hasattr(env, "get_wrapper_attr"):
                    fn = env.get_wrapper_attr(method_name)
                out.append(fn(*method_args, **method_kwargs))
            return out
        raise AttributeError(f"{type(self.env.unwrapped).__name__} has no method {method_name!r}")

    def env_is_wrapped(self, wrapper_class: type, indices: VecEnvIndices = None) -> list[bool]:
        idx = list(self._get_indices(indices))
        if any(isinstance(layer, wrapper_class) for layer in self._layers()):
            return [True for _ in idx]
        envs = self._sub_envs()
        if envs is not None:
            from stable_baselines3.common.env_util import is_wrapped

            return [is_wrapped(envs[i], wrapper_class) for i in idx]
        return [False for _ in idx]

    def seed(self, seed: int | None = None) -> Sequence[int | None]:
        seeds = super().seed(seed)
        try:
            self.action_space.seed(seeds[0])
        except Exception:  # noqa: BLE001 -- a space without seeding is fine
            pass
        return seeds

    # -- rendering -------------------------------------------------------------------------------
    def get_images(self) -> Sequence[np.ndarray | None]:
        frames = self.env.render()
        if frames is None:
            return [None for _ in range(self.num_envs)]
        frames = _to_numpy(frames) if not isinstance(frames, (list, tuple)) else [_to_numpy(f) for f in frames]
        if isinstance(frames, np.ndarray):
            if frames.ndim == 3:  # one frame (of one world, or a composite of the batch)
                return [frames]
            return list(frames)
        return list(frames)

    def render(self, mode: str | None = None) -> np.ndarray | None:
        mode = mode or self.render_mode
        if mode == "rgb_array" and self.render_mode == "rgb_array":
            images = self.get_images()
            if len(images) == 1:
                return images[0]
        return super().render(mode)


def _unchanged(before: np.ndarray, after: np.ndarray) -> bool:
    """Whether worlds kept their observations across a masked reset: exactly for integer and bool
    observations, to float32 rounding for floating ones (an env may compute a step's observation
    inside its fused step and a reset's in another kernel, which round differently on a GPU, by
    ~1e-7 relative; a world that was reset differs by far more)."""
    if np.issubdtype(before.dtype, np.floating):
        return bool(np.allclose(before, after, rtol=1e-5, atol=1e-6))
    return bool(np.array_equal(before, after))


def _tree_all(fn, a: Any, b: Any) -> bool:
    if isinstance(a, dict):
        return all(_tree_all(fn, a[k], b[k]) for k in a)
    if isinstance(a, tuple):
        return all(_tree_all(fn, x, y) for x, y in zip(a, b))
    return bool(fn(np.asarray(a), np.asarray(b)))


# ---------------------------------------------------------------------------------------------
# construction from a registered id


def _accepts(fn: Any, name: str) -> bool:
    try:
        params = inspect.signature(fn).parameters
    except (TypeError, ValueError):
        return True
    return name in params or any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())


def make_gym_vector_env(
    env_id: str,
    num_envs: int,
    *,
    device: str | None = None,
    render_mode: str | None = None,
    env_kwargs: dict[str, Any] | None = None,
    backend: str | None = None,
    autoreset_mode: AutoresetMode = AutoresetMode.SAME_STEP,
) -> gym.vector.VectorEnv:
    """A Gymnasium vector env for ``env_id`` that autoresets in the same step where possible.

    A registered ``vector_entry_point`` that takes ``autoreset_mode`` (the abd_gym envs) is built
    natively with ``autoreset_mode`` (default SAME_STEP), ``backend`` (default ``"numpy"``;
    ``env_kwargs`` may name it too) and ``device``; otherwise the single env is vectorised with a
    SAME_STEP ``SyncVectorEnv`` (whatever ``autoreset_mode`` says).  ``device`` and ``backend``
    are passed only to creators that accept them.
    """
    import abd_gym  # noqa: F401 -- registers the abd_gym/ ids (once the envs exist)

    spec = gym.spec(env_id)
    kwargs = dict(env_kwargs or {})
    if render_mode is not None:
        kwargs["render_mode"] = render_mode
    if spec.vector_entry_point is not None:
        from gymnasium.envs.registration import load_env_creator

        creator = spec.vector_entry_point
        creator = load_env_creator(creator) if isinstance(creator, str) else creator
        init = creator.__init__ if inspect.isclass(creator) else creator
        if _accepts(init, "autoreset_mode"):
            vkwargs = dict(kwargs)
            vkwargs["autoreset_mode"] = autoreset_mode
            if device is not None and _accepts(init, "device"):
                vkwargs["device"] = device
            if _accepts(init, "backend"):
                if backend is not None:
                    vkwargs["backend"] = backend
                vkwargs.setdefault("backend", "numpy")
            return gym.make_vec(env_id, num_envs=num_envs, vectorization_mode="vector_entry_point", **vkwargs)
    single = spec.entry_point
    if isinstance(single, str):
        from gymnasium.envs.registration import load_env_creator

        single = load_env_creator(single)
    init = single.__init__ if inspect.isclass(single) else single
    if device is not None and _accepts(init, "device"):
        kwargs["device"] = device
    return gym.make_vec(
        env_id,
        num_envs=num_envs,
        vectorization_mode="sync",
        vector_kwargs={"autoreset_mode": AutoresetMode.SAME_STEP},
        **kwargs,
    )


def make_vec_env(
    env_id: str,
    num_envs: int,
    *,
    device: str | None = None,
    seed: int | None = None,
    render_mode: str | None = None,
    env_kwargs: dict[str, Any] | None = None,
    backend: str | None = None,
    autoreset_mode: AutoresetMode = AutoresetMode.SAME_STEP,
) -> GymnasiumVecEnv:
    """SB3 ``VecEnv`` for a registered Gymnasium id (see :func:`make_gym_vector_env`)."""
    venv = GymnasiumVecEnv(
        make_gym_vector_env(
            env_id, num_envs, device=device, render_mode=render_mode, env_kwargs=env_kwargs, backend=backend,
            autoreset_mode=autoreset_mode,
        )
    )
    if seed is not None:
        venv.seed(seed)
    return venv

