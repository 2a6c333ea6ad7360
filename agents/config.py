"""Training configs: one YAML per task and algorithm, keys close to RL Baselines3 Zoo's.

```yaml
env_id: abd_gym/CartPole-v0      # a registered Gymnasium id
algo: ppo                        # ppo, sac, a2c, td3, ddpg, dqn
n_envs: 16                       # worlds in the vector env
n_timesteps: 100000              # total environment steps (all worlds)
policy: MlpPolicy
normalize: true                  # or a dict of VecNormalize kwargs, e.g. {norm_reward: false}
device: cpu                      # env and policy device ("cuda:0" on a GPU)
seed: 0
eval_episodes: 20
hyperparams:                     # keyword arguments of the algorithm's __init__
  learning_rate: lin_3e-4        # "lin_X": linear schedule from X to 0, as in the zoo
  n_steps: 32
policy_kwargs:                   # keyword arguments of the policy's __init__
  net_arch: [64, 64]
  activation_fn: nn.Tanh         # resolved by name in torch.nn, never eval'd
```

Optional keys: ``env_kwargs`` (passed to the env), ``n_eval_envs``, ``checkpoint_freq`` (in
total steps), ``eval_freq`` (a periodic evaluation every that many total steps; 0, the default,
is off), ``rollout`` (PPO's rollout: ``auto``, the default, keeps it on the policy's device where
the env and config allow, see ``abd_gym.agents.device_rollout``; ``sb3`` forces SB3's NumPy
rollout; ``device`` requires the device one), ``stop_when_solved`` (stop training once that
many periodic evaluations in a row are solved with a standard error to spare, see
``abd_gym.agents.progress.ThresholdEval``; 0, the default, trains for ``n_timesteps``; needs
``eval_freq``), ``notes``.  Unknown keys, unknown algorithms or policies, unregistered ids and
values of the wrong type fail at load time with a ``ValueError`` that names the key.  ``1e-3`` reads as
a number (PyYAML alone would read it as a string).
"""
from __future__ import annotations

import collections.abc
import copy
import difflib
import inspect
import re
import types
import typing
from pathlib import Path
from typing import Any

import yaml

from abd_gym import configs as _configs

__all__ = [
    "ALGOS",
    "ConfigError",
    "load_config",
    "validate_config",
    "apply_overrides",
    "algorithm_class",
    "algorithm_kwargs",
    "policy_kwargs",
    "normalize_kwargs",
    "linear_schedule",
    "resolve_class",
    "yaml_load",
    "find_config",
    "config_names",
    "CONFIG_DIR",
]

CONFIG_DIR = Path(_configs.__file__).resolve().parent  # the shipped configs (abd_gym.configs)


class ConfigError(ValueError):
    """A config that cannot be used; the message names the offending key."""


# ---------------------------------------------------------------------------------------------
# YAML


class _Loader(yaml.SafeLoader):
    """SafeLoader that also reads ``1e-3`` / ``3e5`` (no dot) as floats, as YAML 1.2 does."""


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"),
)


def yaml_load(text: str) -> Any:
    return yaml.load(text, Loader=_Loader)  # noqa: S506 -- a SafeLoader subclass


# ---------------------------------------------------------------------------------------------
# algorithms, schedules, classes by name


def _algos() -> dict[str, type]:
    from stable_baselines3 import A2C, DDPG, DQN, PPO, SAC, TD3

    return {"ppo": PPO, "sac": SAC, "a2c": A2C, "td3": TD3, "ddpg": DDPG, "dqn": DQN}


ALGOS = tuple(sorted(["ppo", "sac", "a2c", "td3", "ddpg", "dqn"]))


def algorithm_class(name: str) -> type:
    algos = _algos()
    if not isinstance(name, str) or name.lower() not in algos:
        raise ConfigError(f"algo: unknown algorithm {name!r}; known: {', '.join(ALGOS)}")
    return algos[name.lower()]


class linear_schedule:  # noqa: N801 -- reads like the zoo's function
    """``progress_remaining`` (1 -> 0) times the initial value; picklable for model.save."""

    def __init__(self, initial: float):
        self.initial = float(initial)

    def __call__(self, progress_remaining: float) -> float:
        return progress_remaining * self.initial

    def __repr__(self) -> str:
        return f"lin_{self.initial:g}"


# Modules searched for a class given by name ("nn.Tanh", "torch.nn.ReLU", "th.optim.Adam", ...).
_CLASS_MODULES = {
    "nn": "torch.nn",
    "th.nn": "torch.nn",
    "torch.nn": "torch.nn",
    "optim": "torch.optim",
    "th.optim": "torch.optim",
    "torch.optim": "torch.optim",
    "torch_layers": "stable_baselines3.common.torch_layers",
    "stable_baselines3.common.torch_layers": "stable_baselines3.common.torch_layers",
    "buffers": "stable_baselines3.common.buffers",
    "stable_baselines3.common.buffers": "stable_baselines3.common.buffers",
    "stable_baselines3": "stable_baselines3",
}


def resolve_class(name: str, base: type | None = None, key: str = "") -> type:
    """The class called ``name`` in torch.nn / torch.optim / SB3's layer and buffer modules.

    Only attribute look-ups in those modules: nothing is evaluated.  ``base`` (if given) must be
    a base class of the result.
    """
    import importlib

    if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_.]*", name):
        raise ConfigError(f"{key}: expected a class name like 'nn.Tanh', got {name!r}")
    prefix, _, attr = name.rpartition(".")
    modules = [_CLASS_MODULES[prefix]] if prefix in _CLASS_MODULES else []
    if prefix and not modules:
        raise ConfigError(f"{key}: {name!r} is not in an allowed module ({', '.join(sorted(_CLASS_MODULES))})")
    if not modules:
        modules = sorted(set(_CLASS_MODULES.values()))
    for mod_name in modules:
        obj = getattr(importlib.import_module(mod_name), attr, None)
        if isinstance(obj, type) and (base is None or issubclass(obj, base)):
            return obj
    what = f" subclass of {base.__module__}.{base.__qualname__}" if base is not None else ""
    raise ConfigError(f"{key}: no{what} called {name!r}")


# ---------------------------------------------------------------------------------------------
# type checking against signatures


def _is_union(ann: Any) -> bool:
    return typing.get_origin(ann) in (typing.Union, types.UnionType)


def _alternatives(ann: Any) -> tuple[Any, ...]:
    return typing.get_args(ann) if _is_union(ann) else (ann,)


def _type_base(ann: Any) -> type | None:
    """``X`` for an annotation ``type[X]`` (possibly inside a union), else None."""
    for alt in _alternatives(ann):
        if typing.get_origin(alt) is type:
            args = typing.get_args(alt)
            return args[0] if args and isinstance(args[0], type) else object
    return None


def _accepts_callable(ann: Any) -> bool:
    return any(
        typing.get_origin(a) is collections.abc.Callable or a is collections.abc.Callable for a in _alternatives(ann)
    )


def _matches(value: Any, ann: Any) -> bool:
    if ann is inspect.Parameter.empty or ann is Any or isinstance(ann, (str, typing.ForwardRef)):
        return True
    if ann is None or ann is type(None):
        return value is None
    if _is_union(ann):
        return any(_matches(value, a) for a in typing.get_args(ann))
    origin, args = typing.get_origin(ann), typing.get_args(ann)
    if ann is bool:
        return isinstance(value, bool)
    if ann is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if ann is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if ann is str:
        return isinstance(value, str)
    if origin is collections.abc.Callable or ann is collections.abc.Callable:
        return callable(value)
    if origin is type:
        return isinstance(value, type) and (not args or not isinstance(args[0], type) or issubclass(value, args[0]))
    if origin in (dict, collections.abc.Mapping) or ann is dict:
        if not isinstance(value, dict):
            return False
        if len(args) == 2:
            return all(_matches(k, args[0]) and _matches(v, args[1]) for k, v in value.items())
        return True
    if origin in (list, collections.abc.Sequence) or ann is list:
        if not isinstance(value, list):
            return False
        return not args or all(_matches(v, args[0]) for v in value)
    if origin is tuple or ann is tuple:
        if not isinstance(value, tuple):
            return False
        if args and args[-1] is not Ellipsis:
            return len(args) == len(value) and all(_matches(v, a) for v, a in zip(value, args))
        return True
    if isinstance(ann, type):
        try:
            return isinstance(value, ann)
        except TypeError:
            return True
    return True  # an annotation we do not model: accept


def _ann_str(ann: Any) -> str:
    if isinstance(ann, type):
        return ann.__name__
    return str(ann).replace("typing.", "").replace("collections.abc.", "")


def _coerce(value: Any, ann: Any, key: str) -> Any:
    """YAML value -> the Python object the signature wants ("lin_X", class names, lists->tuples)."""
    if ann is inspect.Parameter.empty:
        return value
    alts = _alternatives(ann)
    if isinstance(value, str):
        if value.startswith("lin_") and _accepts_callable(ann):
            try:
                return linear_schedule(float(value[4:]))
            except ValueError:
                raise ConfigError(f"{key}: bad linear schedule {value!r} (expected 'lin_<number>')") from None
        base = _type_base(ann)
        if base is not None and str not in alts:
            return resolve_class(value, base, key)
    if isinstance(value, list) and any(typing.get_origin(a) is tuple for a in alts) and list not in alts:
        return tuple(value)
    if isinstance(value, float) and value.is_integer() and int in alts and float not in alts:
        return int(value)  # 1e6 written for an int parameter
    return value


def _check_kwargs(section: str, values: dict[str, Any], fn: Any, *, exclude: set[str], what: str) -> dict[str, Any]:
    """Coerce and type-check ``values`` against ``fn``'s signature; return the coerced dict."""
    if not isinstance(values, dict):
        raise ConfigError(f"{section}: expected a mapping, got {type(values).__name__}")
    params = {k: p for k, p in inspect.signature(fn).parameters.items() if k != "self"}
    out = {}
    for key, value in values.items():
        name = f"{section}.{key}"
        if not isinstance(key, str) or key not in params or key in exclude:
            if key in exclude and key in params:
                raise ConfigError(f"{name}: set through the config's own keys, not {section}")
            known = sorted(k for k in params if k not in exclude and not k.startswith("_"))
            raise ConfigError(f"{name}: unknown keyword for {what}; known: {', '.join(known)}")
        ann = params[key].annotation
        value = _coerce(value, ann, name)
        if not _matches(value, ann):
            raise ConfigError(f"{name}: expected {_ann_str(ann)}, got {type(value).__name__} {value!r}")
        out[key] = value
    return out


# ---------------------------------------------------------------------------------------------
# the schema

_TOP_LEVEL: dict[str, tuple[Any, Any]] = {
    # key: (type, default); REQUIRED marks required keys
    "env_id": (str, "REQUIRED"),
    "algo": (str, "REQUIRED"),
    "n_timesteps": (int, "REQUIRED"),
    "n_envs": (int, 8),
    "policy": (str, "MlpPolicy"),
    "normalize": ((bool, dict), False),
    "device": (str, "cpu"),
    "seed": (int, 0),
    "eval_episodes": (int, 10),
    "n_eval_envs": ((int, type(None)), None),
    "checkpoint_freq": ((int, type(None)), None),
    "eval_freq": (int, 0),
    "stop_when_solved": (int, 0),
    "hyperparams": (dict, {}),
    "policy_kwargs": (dict, {}),
    "env_kwargs": (dict, {}),
    "rollout": (str, "auto"),
    "notes": ((str, type(None)), None),
}
TOP_LEVEL_KEYS = tuple(_TOP_LEVEL)
ROLLOUTS = ("auto", "device", "sb3")

# Algorithm keywords the trainer sets itself.
_ALGO_EXCLUDE = {"policy", "env", "seed", "tensorboard_log", "policy_kwargs", "_init_setup_model"}
# Zoo-style extras under hyperparams for off-policy algorithms: an action noise.
_NOISE_KEYS = {"noise_type", "noise_std"}


def _check_top_level_type(key: str, value: Any) -> Any:
    typ, _ = _TOP_LEVEL[key]
    types_ = typ if isinstance(typ, tuple) else (typ,)
    if int in types_ and isinstance(value, float) and value.is_integer():
        value = int(value)  # n_timesteps: 1e6
    ok = any(
        (t is int and isinstance(value, int) and not isinstance(value, bool))
        or (t is not int and isinstance(value, t))
        for t in types_
    )
    if not ok:
        names = " or ".join("null" if t is type(None) else t.__name__ for t in types_)
        raise ConfigError(f"{key}: expected {names}, got {type(value).__name__} {value!r}")
    return value


def _check_env_id(env_id: str) -> None:
    import gymnasium as gym

    try:
        import abd_gym  # noqa: F401 -- registers the abd_gym/ ids
    except Exception:  # noqa: BLE001 -- an id from elsewhere still validates below
        pass
    try:
        gym.spec(env_id)
    except Exception as exc:  # noqa: BLE001 -- gymnasium raises several error types here
        raise ConfigError(f"env_id: unknown task {env_id!r} (not registered with Gymnasium: {exc})") from None


def _check_env_kwargs(env_id: str, env_kwargs: dict[str, Any]) -> None:
    import gymnasium as gym
    from gymnasium.envs.registration import load_env_creator

    spec = gym.spec(env_id)
    creators = [c for c in (spec.vector_entry_point, spec.entry_point) if c is not None]
    for creator in creators:
        fn = load_env_creator(creator) if isinstance(creator, str) else creator
        fn = fn.__init__ if inspect.isclass(fn) else fn
        try:
            params = inspect.signature(fn).parameters
        except (TypeError, ValueError):
            return
        if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
            return
        if all(k in params for k in env_kwargs):
            return
    for key in env_kwargs:
        raise ConfigError(f"env_kwargs.{key}: not a keyword argument of {env_id}'s constructor")


def validate_config(raw: dict[str, Any]) -> dict[str, Any]:
    """Checked copy of a config with defaults filled in (values stay as written: plain YAML)."""
    if not isinstance(raw, dict):
        raise ConfigError(f"config: expected a mapping at the top level, got {type(raw).__name__}")
    for key in raw:
        if key not in _TOP_LEVEL:
            raise ConfigError(f"{key}: unknown config key; known: {', '.join(TOP_LEVEL_KEYS)}")
    cfg: dict[str, Any] = {}
    for key, (_, default) in _TOP_LEVEL.items():
        if key in raw:
            cfg[key] = _check_top_level_type(key, raw[key])
        elif isinstance(default, str) and default == "REQUIRED":
            raise ConfigError(f"{key}: required config key is missing")
        else:
            cfg[key] = copy.deepcopy(default)

    algo_cls = algorithm_class(cfg["algo"])
    cfg["algo"] = cfg["algo"].lower()
    _check_env_id(cfg["env_id"])
    for key in ("n_envs", "n_timesteps", "eval_episodes"):
        if cfg[key] < 1:
            raise ConfigError(f"{key}: must be at least 1, got {cfg[key]}")
    if cfg["rollout"] not in ROLLOUTS:
        raise ConfigError(f"rollout: one of {', '.join(ROLLOUTS)}, got {cfg['rollout']!r}")
    if cfg["eval_freq"] < 0:
        raise ConfigError(f"eval_freq: must be 0 (off) or at least 1, got {cfg['eval_freq']}")
    if cfg["stop_when_solved"] < 0:
        raise ConfigError(f"stop_when_solved: must be 0 (off) or at least 1, got {cfg['stop_when_solved']}")
    if cfg["stop_when_solved"] and not cfg["eval_freq"]:
        raise ConfigError(
            f"stop_when_solved: {cfg['stop_when_solved']} needs periodic evaluations; set eval_freq (now 0), "
            "or stop_when_solved=0"
        )
    for key in ("n_eval_envs", "checkpoint_freq"):
        if cfg[key] is not None and cfg[key] < 1:
            raise ConfigError(f"{key}: must be at least 1, got {cfg[key]}")
    if cfg["policy"] not in algo_cls.policy_aliases:
        raise ConfigError(
            f"policy: unknown policy {cfg['policy']!r} for {cfg['algo']}; known: {', '.join(algo_cls.policy_aliases)}"
        )
    # Checks below raise on a bad value; the coerced objects are rebuilt when training.
    algorithm_kwargs(cfg)
    policy_kwargs(cfg)
    normalize_kwargs(cfg)
    _check_env_kwargs(cfg["env_id"], cfg["env_kwargs"])
    return cfg


def algorithm_kwargs(cfg: dict[str, Any]) -> dict[str, Any]:
    """The algorithm's keyword arguments from ``hyperparams`` (schedules and classes built)."""
    algo_cls = algorithm_class(cfg["algo"])
    hp = dict(cfg.get("hyperparams") or {})
    if not isinstance(cfg.get("hyperparams") or {}, dict):
        raise ConfigError("hyperparams: expected a mapping")
    noise = {k: hp.pop(k) for k in list(hp) if k in _NOISE_KEYS}
    kwargs = _check_kwargs("hyperparams", hp, algo_cls.__init__, exclude=_ALGO_EXCLUDE, what=algo_cls.__name__)
    if noise:
        if "action_noise" not in inspect.signature(algo_cls.__init__).parameters:
            key = next(iter(noise))
            raise ConfigError(f"hyperparams.{key}: {algo_cls.__name__} takes no action noise")
        kwargs["action_noise"] = _noise_spec(noise)  # built once the action space is known
    return kwargs


def _noise_spec(noise: dict[str, Any]) -> dict[str, Any]:
    kind = noise.get("noise_type", "normal")
    std = noise.get("noise_std", 0.1)
    if kind not in ("normal", "ornstein-uhlenbeck"):
        raise ConfigError(f"hyperparams.noise_type: expected 'normal' or 'ornstein-uhlenbeck', got {kind!r}")
    if not isinstance(std, (int, float)) or isinstance(std, bool) or std < 0:
        raise ConfigError(f"hyperparams.noise_std: expected a non-negative number, got {std!r}")
    return {"noise_type": kind, "noise_std": float(std)}


def policy_kwargs(cfg: dict[str, Any]) -> dict[str, Any]:
    """The policy's keyword arguments (``activation_fn: nn.Tanh`` resolved to the class)."""
    algo_cls = algorithm_class(cfg["algo"])
    policy_cls = algo_cls.policy_aliases.get(cfg.get("policy", "MlpPolicy"))
    if policy_cls is None:
        raise ConfigError(f"policy: unknown policy {cfg.get('policy')!r}")
    return _check_kwargs(
        "policy_kwargs",
        dict(cfg.get("policy_kwargs") or {}),
        policy_cls.__init__,
        exclude={"observation_space", "action_space", "lr_schedule", "use_sde"},
        what=policy_cls.__name__,
    )


def normalize_kwargs(cfg: dict[str, Any]) -> dict[str, Any] | None:
    """VecNormalize keyword arguments, or None when not normalising."""
    from stable_baselines3.common.vec_env import VecNormalize

    norm = cfg.get("normalize", False)
    if norm is False or norm is None:
        return None
    if norm is True:
        return {}
    return _check_kwargs(
        "normalize", dict(norm), VecNormalize.__init__, exclude={"venv", "training"}, what="VecNormalize"
    )


# ---------------------------------------------------------------------------------------------
# loading and overrides


def find_config(name: str | Path) -> Path:
    """A config path: as given, or ``<name>(.yaml)`` in ``./configs/`` or in the shipped configs
    (``abd_gym.configs``: the repository's ``configs/``, installed with the package)."""
    path = Path(name)
    if path.is_file():
        return path
    for base in (Path.cwd() / "configs", CONFIG_DIR):
        for cand in (base / path, base / f"{path}.yaml", base / f"{path}.yml"):
            if cand.is_file():
                return cand
    known = config_names()
    close = difflib.get_close_matches(str(path.with_suffix("")) if path.suffix in (".yaml", ".yml") else str(path),
                                      known, n=3, cutoff=0.6)  # fmt: skip
    hint = f" (did you mean {', '.join(close)}?)" if close else ""
    raise FileNotFoundError(
        f"no config {str(name)!r}{hint}: no such file, and none of that name in ./configs/ or {CONFIG_DIR}, "
        f"which hold: {', '.join(known)}"
    )


def config_names() -> list[str]:
    """The names :func:`find_config` resolves in ``./configs/`` and in the shipped configs
    (``cartpole_ppo``, ``gpu/cartpole_ppo``), sorted, each once."""
    names = set()
    for base in (Path.cwd() / "configs", CONFIG_DIR):
        if base.is_dir():
            for p in (*base.rglob("*.yaml"), *base.rglob("*.yml")):
                names.add(p.relative_to(base).with_suffix("").as_posix())
    return sorted(names)


def config_name(path: str | Path) -> str:
    """A config's name in run folders and summaries: its file's stem, after the folders it sits in
    below a configs folder, so ``configs/gpu/cartpole_ppo.yaml`` is ``gpu_cartpole_ppo`` and not
    the CPU config's ``cartpole_ppo``."""
    path = Path(path).resolve()
    for base in (Path.cwd() / "configs", CONFIG_DIR):
        try:
            return "_".join(path.relative_to(base.resolve()).with_suffix("").parts)
        except ValueError:
            continue
    return path.stem


def apply_overrides(raw: dict[str, Any], overrides: list[str] | dict[str, Any]) -> dict[str, Any]:
    """``key=value`` overrides (dotted keys reach into mappings; values parsed as YAML)."""
    out = copy.deepcopy(raw)
    items = overrides.items() if isinstance(overrides, dict) else [_split_override(o) for o in overrides]
    for key, value in items:
        parts = key.split(".")
        node = out
        for part in parts[:-1]:
            if part not in node or node[part] is None:
                node[part] = {}
            if not isinstance(node[part], dict):
                raise ConfigError(f"{key}: {part} is not a mapping")
            node = node[part]
        node[parts[-1]] = value
    return out


def _split_override(text: str) -> tuple[str, Any]:
    if "=" not in text:
        raise ConfigError(f"override {text!r}: expected key=value")
    key, value = text.split("=", 1)
    key = key.strip()
    if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*", key):
        raise ConfigError(f"override {text!r}: bad key {key!r}")
    return key, yaml_load(value) if value.strip() else None


def load_config(path: str | Path, overrides: list[str] | dict[str, Any] | None = None) -> dict[str, Any]:
    """Read, override and validate a config file."""
    path = find_config(path)
    raw = yaml_load(Path(path).read_text())
    if raw is None:
        raw = {}
    if overrides:
        raw = apply_overrides(raw, overrides)
    return validate_config(raw)
