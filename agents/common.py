"""Pieces shared by ``abd_gym.agents.train`` and ``abd_gym.agents.evaluate``: envs, models, evaluation, summaries."""
from __future__ import annotations

import json
import os
import platform
from pathlib import Path
from typing import Any, Callable

import numpy as np

from abd_gym.agents.config import algorithm_class, algorithm_kwargs, normalize_kwargs, policy_kwargs
from abd_gym.agents.sb3_vec_env import make_vec_env

MODEL_FILE = "model.zip"
VECNORM_FILE = "vecnormalize.pkl"
BEST_MODEL_FILE = "best_model.zip"  # SB3 EvalCallback's name for the best periodic evaluation's model
BEST_VECNORM_FILE = "best_vecnormalize.pkl"  # the statistics best_model.zip was evaluated with
CONFIG_FILE = "config.yaml"
SUMMARY_FILE = "summary.json"
EVAL_SEED_OFFSET = 10_000  # evaluation worlds are seeded apart from the training worlds


def build_train_env(cfg: dict[str, Any], *, device: str | None = None, rollout: str = "sb3"):
    """VecMonitor(adapter) wrapped in VecNormalize when the config asks for it.

    ``rollout="device"`` (see :func:`~abd_gym.agents.device_rollout.rollout_path`) builds the env
    with the Torch backend, whose tensors the device rollout reads as they are, autoresetting in
    NEXT_STEP mode (so that its step runs as one CUDA graph on a GPU); SB3's rollout gets a
    SAME_STEP env (:func:`train_autoreset_mode`).
    """
    from stable_baselines3.common.vec_env import VecMonitor, VecNormalize

    venv = make_vec_env(
        cfg["env_id"],
        cfg["n_envs"],
        device=device or cfg["device"],
        seed=cfg["seed"],
        env_kwargs=cfg["env_kwargs"],
        backend="torch" if rollout == "device" else None,
        autoreset_mode=train_autoreset_mode(rollout),
    )
    venv = VecMonitor(venv)
    norm = normalize_kwargs(cfg)
    if norm is not None:
        norm = dict(norm)
        norm.setdefault("gamma", (cfg.get("hyperparams") or {}).get("gamma", 0.99))
        venv = VecNormalize(venv, **norm)
    return venv


def train_autoreset_mode(rollout: str):
    """The autoreset mode of the training env for a rollout path: NEXT_STEP for the device
    rollout, SAME_STEP (SB3's convention) for SB3's."""
    from gymnasium.vector import AutoresetMode

    return AutoresetMode.NEXT_STEP if rollout == "device" else AutoresetMode.SAME_STEP


def build_eval_env(
    cfg: dict[str, Any],
    *,
    num_envs: int,
    seed: int,
    vecnormalize: Any = None,
    device: str | None = None,
    render_mode: str | None = None,
    on_device: bool | None = None,
):
    """Evaluation env: raw returns (VecMonitor inside), observations normalised with frozen stats.

    ``vecnormalize`` is a path to saved statistics, a training ``VecNormalize`` to copy them
    from, or None.  ``on_device`` (default: :func:`evaluates_on_device`, and never when
    rendering): the env has the Torch backend and autoresets in NEXT_STEP mode, for
    :class:`~.device_eval.DeviceEvaluator`; otherwise it is SB3's (NumPy, SAME_STEP).
    """
    from gymnasium.vector import AutoresetMode
    from stable_baselines3.common.vec_env import VecMonitor, VecNormalize

    device = device or cfg["device"]
    if on_device is None:
        on_device = render_mode is None and evaluates_on_device(cfg["env_id"], device)
    venv = make_vec_env(
        cfg["env_id"],
        num_envs,
        device=device,
        seed=seed,
        render_mode=render_mode,
        env_kwargs=cfg["env_kwargs"],
        backend="torch" if on_device else None,
        autoreset_mode=AutoresetMode.NEXT_STEP if on_device else AutoresetMode.SAME_STEP,
    )
    venv = VecMonitor(venv)
    if vecnormalize is None:
        return venv
    if isinstance(vecnormalize, (str, os.PathLike)):
        venv = VecNormalize.load(str(vecnormalize), venv)
    else:
        stats = vecnormalize
        venv = VecNormalize(
            venv,
            norm_obs=stats.norm_obs,
            norm_reward=stats.norm_reward,
            clip_obs=stats.clip_obs,
            clip_reward=stats.clip_reward,
            gamma=stats.gamma,
            epsilon=stats.epsilon,
            norm_obs_keys=stats.norm_obs_keys,
        )
        venv.obs_rms = stats.obs_rms.copy() if hasattr(stats.obs_rms, "copy") else stats.obs_rms
        venv.ret_rms = stats.ret_rms.copy() if hasattr(stats.ret_rms, "copy") else stats.ret_rms
    venv.training = False
    venv.norm_reward = False
    return venv


def _action_noise(spec: dict[str, Any], action_space) -> Any:
    from stable_baselines3.common.noise import NormalActionNoise, OrnsteinUhlenbeckActionNoise

    n = int(np.prod(action_space.shape))
    mean, sigma = np.zeros(n), spec["noise_std"] * np.ones(n)
    if spec["noise_type"] == "normal":
        return NormalActionNoise(mean, sigma)
    return OrnsteinUhlenbeckActionNoise(mean, sigma)


def build_model(
    cfg: dict[str, Any], env, *, tensorboard_log: str | None = None, verbose: int = 0, rollout: str = "sb3"
):
    """The config's algorithm on ``env``.  PPO is :class:`~abd_gym.agents.device_rollout.DevicePPO`
    with ``rollout="device"`` (its rollout on the policy's device), else
    :class:`~abd_gym.agents.graphed_update.GraphedPPO` (SB3's rollout; its update a CUDA graph on
    a GPU, SB3's own elsewhere)."""
    algo_cls = algorithm_class(cfg["algo"])
    if rollout == "device":
        from abd_gym.agents.device_rollout import DevicePPO

        algo_cls = DevicePPO
    elif cfg["algo"].lower() == "ppo":
        from abd_gym.agents.graphed_update import GraphedPPO

        algo_cls = GraphedPPO
    kwargs = algorithm_kwargs(cfg)
    if isinstance(kwargs.get("action_noise"), dict):
        kwargs["action_noise"] = _action_noise(kwargs["action_noise"], env.action_space)
    kwargs.setdefault("device", model_device(cfg["device"]))
    kwargs.setdefault("verbose", verbose)
    return algo_cls(
        cfg["policy"],
        env,
        seed=cfg["seed"],
        tensorboard_log=tensorboard_log,
        policy_kwargs=policy_kwargs(cfg) or None,
        **kwargs,
    )


def model_device(device: str) -> str:
    """Torch device for the policy: the env's device ("cpu", "cuda:0"; "cuda" means cuda:0)."""
    return "cuda:0" if device == "cuda" else device


def eval_env_count(cfg: dict[str, Any], episodes: int) -> int:
    return int(cfg.get("n_eval_envs") or min(episodes, cfg["n_envs"]))


def evaluates_on_device(env_id: str, device: str) -> bool:
    """Whether evaluation runs on the device (:class:`~.device_eval.DeviceEvaluator`): on a GPU, for
    an env with the Torch backend.  On the CPU SB3's ``evaluate_policy`` runs: NumPy is the
    device there."""
    from abd_gym.agents.device_rollout import _takes_torch_backend

    return str(device).startswith("cuda") and _takes_torch_backend(env_id)


def episode_evaluator(env) -> Callable[..., tuple[list[float], list[int]]]:
    """``(model, episodes, deterministic=...) -> (returns, lengths)`` for ``env``: a
    :class:`~.device_eval.DeviceEvaluator` where the env was built for one, else SB3's
    ``evaluate_policy``."""
    from abd_gym.agents.device_eval import DeviceEvaluator

    if DeviceEvaluator.refusal(env) is None:
        return DeviceEvaluator(env)

    def sb3(model, episodes: int, *, deterministic: bool = True) -> tuple[list[float], list[int]]:
        from stable_baselines3.common.evaluation import evaluate_policy

        return evaluate_policy(model, env, n_eval_episodes=episodes, deterministic=deterministic,
                               return_episode_rewards=True, warn=False)  # fmt: skip

    return sb3


def evaluate(model, env, episodes: int, *, deterministic: bool = True) -> dict[str, Any]:
    """Mean and std of the (raw) return over ``episodes`` episodes (:func:`episode_evaluator`);
    ``evaluator``: "device" (:class:`~.device_eval.DeviceEvaluator`) or "sb3" (``evaluate_policy``)."""
    from abd_gym.agents.device_eval import DeviceEvaluator

    evaluator = episode_evaluator(env)
    returns, lengths = evaluator(model, episodes, deterministic=deterministic)
    returns = np.asarray(returns, dtype=float)
    lengths = np.asarray(lengths, dtype=float)
    return {
        "eval_episodes": int(len(returns)),
        "mean_return": float(returns.mean()),
        "std_return": float(returns.std()),
        "mean_episode_length": float(lengths.mean()),
        "episode_returns": [float(r) for r in returns],
        "deterministic": bool(deterministic),
        "evaluator": "device" if isinstance(evaluator, DeviceEvaluator) else "sb3",
    }


def compare_to_best(final: dict[str, Any], best: dict[str, Any] | None) -> tuple[bool, str]:
    """(whether the final policy's mean return is below the best model's by more than the final
    evaluation's standard error, std / sqrt(episodes); the model file to use).  ``final`` and
    ``best`` hold ``mean_return``, ``std_return`` and ``eval_episodes`` of evaluations on the
    same episodes; a best model without its own evaluation (None, or the final policy itself)
    is never better."""
    if best is None or "mean_return" not in best:
        return False, MODEL_FILE
    standard_error = final["std_return"] / np.sqrt(max(final["eval_episodes"], 1))
    below = bool(best["mean_return"] - final["mean_return"] > standard_error)
    return below, (best["file"] if below else MODEL_FILE)


def reward_threshold(env_id: str) -> float | None:
    import gymnasium as gym

    import abd_gym  # noqa: F401

    threshold = gym.spec(env_id).reward_threshold
    return None if threshold is None else float(threshold)


def device_description(device: str) -> str:
    """The device in words: "cpu (AMD EPYC ..., 2 cores)" or "cuda:0 (NVIDIA H100 ...)"."""
    if device.startswith("cuda"):
        try:
            import torch

            index = int(device.split(":")[1]) if ":" in device else 0
            return f"{device} ({torch.cuda.get_device_name(index)})"
        except Exception:  # noqa: BLE001
            return device
    name = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    name = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return f"{device} ({name}, {os.cpu_count()} cores)"


def versions() -> dict[str, str]:
    import gymnasium
    import stable_baselines3
    import torch

    out = {
        "python": platform.python_version(),
        "gymnasium": gymnasium.__version__,
        "stable_baselines3": stable_baselines3.__version__,
        "torch": torch.__version__,
    }
    try:
        import warp

        out["warp"] = warp.config.version
    except Exception:  # noqa: BLE001
        pass
    return out


def write_json(path: Path, data: dict[str, Any]) -> None:
    path.write_text(json.dumps(data, indent=2, sort_keys=False, default=str) + "\n")

