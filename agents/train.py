"""Train an SB3 agent from a YAML config.

    python -m abd_gym.agents.train configs/cartpole_ppo.yaml [--seed S] [--device cpu|cuda:0]
        [--num-envs N] [--total-timesteps T] [--run-dir DIR] [--eval-episodes E] [--eval-freq N]
        [--no-progress] [key=value ...]

(also ``abd-gym-train``).  A bare name (``cartpole_ppo``) is looked up in ``configs/``.
``key=value`` overrides reach into mappings with dots (``hyperparams.learning_rate=1e-3``,
``policy_kwargs.net_arch=[64,64]``); values are YAML.

The run directory (default ``runs/<config>-<seed>-<YYYYmmdd-HHMMSS>/``) receives
``config.yaml`` (the config as run), ``tensorboard/`` (event files), ``checkpoints/`` (model and
normalisation statistics every ``checkpoint_freq`` steps), ``model.zip``,
``vecnormalize.pkl`` (when normalising) and ``summary.json``: config, timesteps, wall time,
device, the deterministic policy's mean and std return over ``eval_episodes`` episodes, the
task's ``reward_threshold`` from the Gymnasium registry and whether it was reached.

With ``eval_freq`` N > 0, SB3's ``EvalCallback`` evaluates the deterministic policy every N
total env steps on ``eval_episodes`` episodes of separate worlds (observation statistics synced
from training), writes ``evaluations.npz`` and ``best_model.zip`` (with
``best_vecnormalize.pkl`` when normalising) into the run directory, and the summary's
``threshold_step`` / ``threshold_time_s`` give the first env step and wall time at which an
evaluation reached the task's threshold (null if none did).  With ``stop_when_solved`` N,
training ends once N evaluations in a row are solved with a standard error to spare
(``stopped_step`` in the summary; see ``abd_gym.agents.progress.ThresholdEval``).

After training, ``best_model.zip`` (when there is one and it is not the final policy) is scored
on the final evaluation's episodes too (``best_model`` in the summary).  A final policy whose
mean return falls below the best model's by more than the final evaluation's standard error is
named in the summary (``final_below_best``, ``use_model: best_model.zip``) and in the run's last
line; ``abd-gym-evaluate`` then evaluates ``best_model.zip`` by default.

PPO's rollout stays on the policy's device where it can (``abd_gym.agents.device_rollout``);
the path taken is printed after the run directory and recorded in the summary (``rollout``,
``rollout_reason``), with the training env's autoreset mode (``autoreset_mode``: NEXT_STEP on the
device path, whose env step then runs as one CUDA graph on a GPU; SAME_STEP on SB3's).

Progress: the run directory is printed first.  On a terminal SB3's progress bar shows; without
one (or with ``--no-progress``) one plain line every tenth of the run gives steps, env steps/s
and the mean return of recent episodes (see ``abd_gym.agents.progress``).
"""
from __future__ import annotations

import argparse
import sys
import time
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml

from abd_gym.agents.common import (BEST_MODEL_FILE, BEST_VECNORM_FILE, CONFIG_FILE, EVAL_SEED_OFFSET, MODEL_FILE,
    SUMMARY_FILE, VECNORM_FILE, build_eval_env, build_model, build_train_env, compare_to_best, device_description,
    eval_env_count, evaluate, model_device, reward_threshold, train_autoreset_mode, versions, write_json)
from abd_gym.agents.config import (algorithm_class, apply_overrides, config_name, find_config, validate_config,
    yaml_load)
from abd_gym.core.devices import resolve_device

if TYPE_CHECKING:  # progress imports SB3, which training loads only when it runs
    from abd_gym.agents.progress import ThresholdEval

__all__ = ["train", "main", "parse_args", "config_from_args"]


def default_run_dir(config_name: str, seed: int, root: str | Path = "runs") -> Path:
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    return Path(root) / f"{config_name}-{seed}-{stamp}"


def train(
    cfg: dict[str, Any],
    *,
    config_name: str,
    run_dir: str | Path | None = None,
    progress_bar: bool = True,
    verbose: int = 0,
    command: str | None = None,
    return_model: bool = False,
    torch_threads: int | None = 1,
) -> dict[str, Any] | tuple[dict[str, Any], Any]:
    """Train, save, evaluate; return the summary (also written to ``run_dir/summary.json``).

    ``progress_bar``: SB3's progress bar when stdout is a terminal; without a terminal, or with
    ``progress_bar=False``, plain progress lines instead (``abd_gym.agents.progress``).

    With ``return_model`` the trained model comes back too: ``(summary, model)``.
    ``torch_threads``: CPU threads for torch (None: torch's default).  One thread is the default,
    as in the zoo: the policies are small MLPs, too small to split across threads, and a second
    thread contends with the env for a busy machine's cores (results/solver_notes.md).
    """
    if torch_threads is not None:
        import torch

        torch.set_num_threads(max(int(torch_threads), 1))
    from stable_baselines3.common.vec_env import VecNormalize

    from abd_gym.agents.progress import stdout_is_terminal

    cfg = validate_config(cfg)
    resolve_device(cfg["device"])  # ValueError naming the devices there are, before the run folder is made
    run_dir = Path(run_dir) if run_dir is not None else default_run_dir(config_name, cfg["seed"])
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / CONFIG_FILE).write_text(yaml.safe_dump(cfg, sort_keys=False))
    print(f"run directory: {run_dir}", flush=True)

    from abd_gym.agents.device_rollout import rollout_path

    rollout, rollout_reason = rollout_path(cfg)
    autoreset = train_autoreset_mode(rollout).name
    print(f"rollout: {rollout} ({rollout_reason}); autoreset: {autoreset}", flush=True)
    env = build_train_env(cfg, rollout=rollout)
    import importlib.util

    # TensorBoard event files when tensorboard is installed (the [train] extra has it); without it
    # SB3 would refuse to start, so train on and say so
    tb = str(run_dir / "tensorboard") if importlib.util.find_spec("tensorboard") else None
    if tb is None:
        print("abd-gym-train: tensorboard is not installed; no TensorBoard logs", file=sys.stderr)
    model = build_model(cfg, env, tensorboard_log=tb, verbose=verbose, rollout=rollout)
    n_envs = cfg["n_envs"]
    threshold = reward_threshold(cfg["env_id"])
    bar = bool(progress_bar) and stdout_is_terminal()
    periodic = _periodic_eval(cfg, env, run_dir, threshold, config_name) if cfg["eval_freq"] > 0 else None
    callbacks = _callbacks(cfg, run_dir, config_name, bar, periodic)

    started = datetime.now().isoformat(timespec="seconds")
    t0 = time.perf_counter()
    model.learn(
        total_timesteps=cfg["n_timesteps"], callback=callbacks, progress_bar=bar, tb_log_name=cfg["algo"]
    )
    wall = time.perf_counter() - t0

    model.save(run_dir / MODEL_FILE)
    vecnorm = env if isinstance(env, VecNormalize) else None
    if vecnorm is not None:
        vecnorm.save(str(run_dir / VECNORM_FILE))

    # Evaluation: fresh worlds seeded apart from training, observations normalised with the saved stats.
    episodes = cfg["eval_episodes"]
    eval_env = build_eval_env(
        cfg,
        num_envs=eval_env_count(cfg, episodes),
        seed=cfg["seed"] + EVAL_SEED_OFFSET,
        vecnormalize=(run_dir / VECNORM_FILE) if vecnorm is not None else None,
    )
    t1 = time.perf_counter()
    result = evaluate(model, eval_env, episodes)
    eval_wall = time.perf_counter() - t1
    eval_env.close()
    if periodic is not None:
        periodic.eval_env.close()
    best = _evaluate_best(cfg, run_dir, periodic, normalised=vecnorm is not None)
    below, use_model = compare_to_best(result, best)
    summary = {
        "config_name": config_name,
        "env_id": cfg["env_id"],
        "algo": cfg["algo"],
        "seed": cfg["seed"],
        "n_envs": n_envs,
        "timesteps": int(model.num_timesteps),
        "wall_time_s": round(wall, 2),
        "fps": round(model.num_timesteps / wall, 1) if wall > 0 else None,
        "device": cfg["device"],
        "device_description": device_description(cfg["device"]),
        "rollout": rollout,
        "rollout_reason": rollout_reason,
        "autoreset_mode": autoreset,
        **{k: result[k] for k in ("mean_return", "std_return", "eval_episodes", "mean_episode_length")},
        "reward_threshold": threshold,
        "solved": bool(threshold is not None and result["mean_return"] >= threshold),
        "episode_returns": result["episode_returns"],
        "eval_deterministic": result["deterministic"],
        "evaluator": result["evaluator"],
        "eval_wall_time_s": round(eval_wall, 2),
        "eval_freq": cfg["eval_freq"],
        **_periodic_summary(periodic),
        "stop_when_solved": cfg["stop_when_solved"],
        "best_model": best,
        "final_below_best": below,
        "use_model": use_model,
        "started": started,
        "run_dir": str(run_dir),
        "command": command,
        "versions": versions(),
        "config": cfg,
    }
    write_json(run_dir / SUMMARY_FILE, summary)
    try:
        model.logger.record("eval/mean_return", summary["mean_return"])
        model.logger.record("eval/std_return", summary["std_return"])
        model.logger.dump(model.num_timesteps)
        model.logger.close()
    except Exception:  # noqa: BLE001 -- the summary is what matters
        pass
    env.close()
    return (summary, model) if return_model else summary


def _callbacks(cfg: dict[str, Any], run_dir: Path, name: str, bar: bool, periodic: ThresholdEval | None) -> list:
    """The training's callbacks: checkpoints (a quarter of the run apart unless the config says),
    progress lines where SB3's bar is not shown (``bar``), and the periodic evaluation if any."""
    from stable_baselines3.common.callbacks import CheckpointCallback

    from abd_gym.agents.progress import ProgressLines

    checkpoint_freq = cfg["checkpoint_freq"] or max(cfg["n_timesteps"] // 4, 1)
    callbacks = [CheckpointCallback(save_freq=max(checkpoint_freq // cfg["n_envs"], 1),
                                    save_path=str(run_dir / "checkpoints"), name_prefix="model",
                                    save_vecnormalize=True)]  # fmt: skip
    if not bar:
        callbacks.append(ProgressLines(cfg["n_timesteps"], name=name))
    if periodic is not None:
        callbacks.append(periodic)
    return callbacks


def _periodic_summary(periodic: ThresholdEval | None) -> dict[str, Any]:
    """The summary's entries from the periodic evaluation, or their values without one."""
    if periodic is None:
        return {"periodic_evaluations": 0, "periodic_eval_time_s": 0.0, "best_periodic_return": None,
                "threshold_step": None, "threshold_time_s": None, "stopped_step": None}  # fmt: skip
    return {"periodic_evaluations": periodic.n_evaluations, "periodic_eval_time_s": round(periodic.eval_time_s, 2),
            "best_periodic_return": _finite_or_none(periodic.best_mean_reward),
            "threshold_step": periodic.threshold_step, "threshold_time_s": periodic.threshold_time_s,
            "stopped_step": periodic.stopped_step}  # fmt: skip


def _periodic_eval(cfg: dict[str, Any], env, run_dir: Path, threshold: float | None, name: str) -> ThresholdEval:
    """EvalCallback every ``eval_freq`` total env steps on worlds built like the final evaluation's."""
    from stable_baselines3.common.vec_env import VecNormalize

    from abd_gym.agents.progress import SaveVecNormalize, ThresholdEval

    vecnorm = env if isinstance(env, VecNormalize) else None
    episodes = cfg["eval_episodes"]
    eval_env = build_eval_env(
        cfg,
        num_envs=eval_env_count(cfg, episodes),
        seed=cfg["seed"] + EVAL_SEED_OFFSET,
        vecnormalize=vecnorm,  # statistics copied now; EvalCallback syncs them before each evaluation
    )
    on_new_best = SaveVecNormalize(str(run_dir / BEST_VECNORM_FILE)) if vecnorm is not None else None
    return ThresholdEval(
        eval_env,
        threshold=threshold,
        name=name,
        write=lambda line: print(line, flush=True),
        eval_freq=max(cfg["eval_freq"] // cfg["n_envs"], 1),
        n_eval_episodes=episodes,
        deterministic=True,
        best_model_save_path=str(run_dir),
        log_path=str(run_dir),
        callback_on_new_best=on_new_best,
        stop_after=cfg["stop_when_solved"],
        warn=False,
        verbose=0,  # ThresholdEval writes its own line per evaluation
    )


def _evaluate_best(cfg: dict[str, Any], run_dir: Path, periodic: ThresholdEval | None, *,
                   normalised: bool) -> dict[str, Any] | None:
    """``best_model.zip`` scored on the final evaluation's episodes (same seed, same count), or None
    where the run kept no best model.  A best model saved by the evaluation that stopped training
    (``stop_when_solved``) is the final policy: no update followed it, so its score is the final
    evaluation's and it is not evaluated again (``same_as_final``).  One saved at the last step of
    a run that was not stopped is not: the rollout's update came after it."""
    path = run_dir / BEST_MODEL_FILE
    if periodic is None or periodic.best_step is None or not path.is_file():
        return None
    best = {"file": BEST_MODEL_FILE, "step": periodic.best_step,
            "periodic_return": _finite_or_none(periodic.best_mean_reward),
            "same_as_final": periodic.stopped_step is not None and periodic.best_step == periodic.stopped_step}  # fmt: skip
    if best["same_as_final"]:
        return best
    model = algorithm_class(cfg["algo"]).load(str(path), device=model_device(cfg["device"]))
    episodes = cfg["eval_episodes"]
    env = build_eval_env(cfg, num_envs=eval_env_count(cfg, episodes), seed=cfg["seed"] + EVAL_SEED_OFFSET,
                         vecnormalize=(run_dir / BEST_VECNORM_FILE) if normalised else None)  # fmt: skip
    try:
        result = evaluate(model, env, episodes)
    finally:
        env.close()
    best.update({k: result[k] for k in ("mean_return", "std_return", "eval_episodes")})
    return best


def _finite_or_none(x: float) -> float | None:
    x = float(x)
    return x if np.isfinite(x) else None


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="abd-gym-train", description=__doc__.split("\n\n")[0])
    p.add_argument("config", help="config file, or a name in configs/ (cartpole_ppo)")
    p.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides (dotted keys, YAML values)")
    p.add_argument("--seed", type=int)
    p.add_argument("--device", help="cpu or cuda:N (env and policy)")
    p.add_argument("--num-envs", type=int, help="worlds in the training env (n_envs)")
    p.add_argument("--total-timesteps", type=float, help="environment steps (n_timesteps)")
    p.add_argument("--run-dir", help="output folder (default runs/<config>-<seed>-<timestamp>/)")
    p.add_argument("--eval-episodes", type=int)
    p.add_argument("--eval-freq", type=int, help="evaluate every N env steps, all worlds (eval_freq; 0: off)")
    p.add_argument("--no-progress", action="store_true", help="plain progress lines instead of the progress bar")
    p.add_argument("--torch-threads", type=int, default=1, help="CPU threads for torch (0: torch's default)")
    p.add_argument("-v", "--verbose", type=int, default=0, help="SB3 verbosity (0, 1, 2)")
    return p.parse_intermixed_args(argv)


def raw_config_from_args(args: argparse.Namespace) -> tuple[dict[str, Any], str]:
    """(the config file's values after the ``key=value`` overrides and the flags, unvalidated; the
    config's name).  The flags: ``--seed`` (where ``args`` has it), ``--device``, ``--num-envs``,
    ``--total-timesteps``, ``--eval-episodes``, ``--eval-freq`` (where ``args`` has it)."""
    path = find_config(args.config)
    raw = yaml_load(path.read_text()) or {}
    raw = apply_overrides(raw, list(args.overrides))
    flags = {
        "seed": getattr(args, "seed", None),
        "device": args.device,
        "n_envs": args.num_envs,
        "n_timesteps": int(args.total_timesteps) if args.total_timesteps is not None else None,
        "eval_episodes": args.eval_episodes,
        "eval_freq": getattr(args, "eval_freq", None),
    }
    raw = apply_overrides(raw, {k: v for k, v in flags.items() if v is not None})
    return raw, config_name(path)


def config_from_args(args: argparse.Namespace) -> tuple[dict[str, Any], str]:
    raw, name = raw_config_from_args(args)
    cfg = validate_config(raw)
    resolve_device(cfg["device"])  # an unavailable device: one line and exit 2 (main), before any run folder
    return cfg, name


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        cfg, name = config_from_args(args)
    except (ValueError, FileNotFoundError) as exc:
        print(f"abd-gym-train: error: {exc}", file=sys.stderr)
        return 2
    command = " ".join(["python -m abd_gym.agents.train", *(sys.argv[1:] if argv is None else argv)])
    summary = train(
        cfg,
        config_name=name,
        run_dir=args.run_dir,
        progress_bar=not args.no_progress,
        verbose=args.verbose,
        command=command,
        torch_threads=args.torch_threads or None,
    )
    thr = summary["reward_threshold"]
    print(
        f"{name}: {summary['timesteps']} steps in {summary['wall_time_s']:.1f} s on {summary['device']}; "
        f"return {summary['mean_return']:.2f} ± {summary['std_return']:.2f} over {summary['eval_episodes']} episodes"
        + (f" (threshold {thr:g}: {'solved' if summary['solved'] else 'not solved'})" if thr is not None else "")
    )
    if summary["threshold_step"] is not None:
        print(f"threshold first reached at {summary['threshold_step']:,} steps, {summary['threshold_time_s']:.1f} s")
    if summary["stopped_step"] is not None:
        from abd_gym.agents.progress import evaluations_in_a_row

        streak = evaluations_in_a_row(cfg["stop_when_solved"])
        print(f"stopped at {summary['stopped_step']:,} steps: solved in {streak}")
    print(f"run directory: {summary['run_dir']}")
    if summary["final_below_best"]:
        best = summary["best_model"]
        print(
            f"final policy worse than its best: {MODEL_FILE} {summary['mean_return']:.2f} ± {summary['std_return']:.2f}, "
            f"{best['file']} (saved at {best['step']:,} steps) {best['mean_return']:.2f} ± {best['std_return']:.2f} "
            f"on the same episodes; use {best['file']} (abd-gym-evaluate evaluates it by default)"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
