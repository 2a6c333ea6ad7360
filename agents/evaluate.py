"""Evaluate a saved run, and optionally record a video of it.

    python -m abd_gym.agents.evaluate RUN_DIR [--episodes N] [--device cpu|cuda:0] [--seed S]
        [--stochastic] [--model PATH] [--json PATH] [--video out.gif|out.mp4] [--video-episodes K]

(also ``abd-gym-evaluate``).  Loads ``RUN_DIR/config.yaml``, the model and the observation
statistics it was saved with (if the run normalised observations), prints which model it
evaluates and the mean and std return of the deterministic policy, and with ``--video`` records
``--video-episodes`` episodes of one world through the env's ``rgb_array`` renderer: a GIF
(Pillow) or, for ``.mp4``, an MP4 (needs ``imageio[ffmpeg]``; checked before the evaluation runs).

The model: ``--model PATH`` (e.g. a checkpoint); ``--final`` for ``model.zip``; by default the
one the run's ``summary.json`` names in ``use_model``: ``best_model.zip`` where training found the
final policy worse than its best, else ``model.zip`` (see :func:`default_model`).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from abd_gym.agents.common import (BEST_MODEL_FILE, BEST_VECNORM_FILE, CONFIG_FILE, EVAL_SEED_OFFSET, MODEL_FILE,
    SUMMARY_FILE, VECNORM_FILE, build_eval_env, eval_env_count, evaluate, reward_threshold, write_json)
from abd_gym.agents.config import algorithm_class, validate_config, yaml_load
from abd_gym.core.devices import resolve_device

__all__ = ["load_run", "vecnormalize_for", "default_model", "video_backend_error", "evaluate_run", "record_video", "main"]


def load_run(run_dir: str | Path, *, device: str | None = None, model_path: str | Path | None = None):
    """(config, model, vecnormalize path or None) of a saved run."""
    run_dir = Path(run_dir)
    cfg = validate_config(yaml_load((run_dir / CONFIG_FILE).read_text()))
    if device is not None:
        cfg["device"] = device
    algo_cls = algorithm_class(cfg["algo"])
    from abd_gym.agents.common import model_device

    model = algo_cls.load(str(model_path or run_dir / MODEL_FILE), device=model_device(cfg["device"]))
    return cfg, model, vecnormalize_for(run_dir, model_path)


def vecnormalize_for(run_dir: str | Path, model_path: str | Path | None = None) -> Path | None:
    """The observation statistics a model was saved with, or None where the run does not normalise:
    ``best_model.zip`` → ``best_vecnormalize.pkl``, a checkpoint ``model_<N>_steps.zip`` →
    ``model_vecnormalize_<N>_steps.pkl`` beside it, else the run's final ``vecnormalize.pkl``."""
    run_dir = Path(run_dir)
    candidates = [run_dir / VECNORM_FILE]
    if model_path is not None:
        model_path = Path(model_path)
        if model_path.name == BEST_MODEL_FILE:
            candidates.insert(0, model_path.with_name(BEST_VECNORM_FILE))
        elif model_path.name.startswith("model_") and model_path.name.endswith("_steps.zip"):
            candidates.insert(0, model_path.with_name("model_vecnormalize_" + model_path.name[len("model_"):-4] + ".pkl"))
    return next((c for c in candidates if c.is_file()), None)


def default_model(run_dir: str | Path) -> tuple[Path, str]:
    """(the model ``abd-gym-evaluate`` evaluates without ``--model``, why in words).

    ``best_model.zip`` where the run's ``summary.json`` says the final policy scored below it
    (``use_model``) and the file is there; else ``model.zip``."""
    run_dir = Path(run_dir)
    summary_path = run_dir / SUMMARY_FILE
    summary = {}
    if summary_path.is_file():
        try:
            summary = json.loads(summary_path.read_text())
        except (OSError, ValueError):
            summary = {}
    best = summary.get("best_model") or {}
    if summary.get("use_model") == BEST_MODEL_FILE and (run_dir / BEST_MODEL_FILE).is_file():
        why = (f"the final {MODEL_FILE} scored {summary['mean_return']:.2f}, below {BEST_MODEL_FILE}'s "
               f"{best.get('mean_return', float('nan')):.2f} after training; --final evaluates {MODEL_FILE}")  # fmt: skip
        return run_dir / BEST_MODEL_FILE, why
    return run_dir / MODEL_FILE, "the final policy"


def video_backend_error(path: str | Path) -> str | None:
    """Why a video cannot be written to ``path`` (its format, or a missing writer), or None.

    ``.gif`` needs Pillow; ``.mp4`` needs imageio with a backend that writes it: PyAV, or
    imageio-ffmpeg with its ffmpeg binary."""
    import importlib.util

    suffix = Path(path).suffix.lower()
    if suffix == ".gif":
        return None if importlib.util.find_spec("PIL") else "writing GIF needs Pillow (pip install pillow)"
    if suffix != ".mp4":
        return f"--video {path}: unsupported video format {suffix or '(none)'!r}; use .gif or .mp4"
    fix = "pip install 'imageio[ffmpeg]', or write a .gif"
    if importlib.util.find_spec("imageio") is None:
        return f"writing MP4 needs imageio with ffmpeg: {fix}"
    if importlib.util.find_spec("av") is not None:
        return None
    try:
        import imageio_ffmpeg

        imageio_ffmpeg.get_ffmpeg_exe()
    except ImportError:
        return f"writing MP4 needs ffmpeg for imageio (imageio is installed, imageio-ffmpeg is not): {fix}"
    except RuntimeError as exc:  # imageio-ffmpeg without its binary
        return f"writing MP4 needs an ffmpeg binary ({exc}): {fix}"
    return None


def evaluate_run(
    run_dir: str | Path,
    *,
    episodes: int | None = None,
    device: str | None = None,
    seed: int | None = None,
    deterministic: bool = True,
    model_path: str | Path | None = None,
) -> dict[str, Any]:
    if episodes is not None and episodes < 1:
        raise ValueError(f"episodes must be at least 1, got {episodes}")
    cfg, model, vecnorm = load_run(run_dir, device=device, model_path=model_path)
    episodes = cfg["eval_episodes"] if episodes is None else episodes
    env = build_eval_env(
        cfg,
        num_envs=eval_env_count(cfg, episodes),
        seed=cfg["seed"] + EVAL_SEED_OFFSET if seed is None else seed,
        vecnormalize=vecnorm,
    )
    try:
        result = evaluate(model, env, episodes, deterministic=deterministic)
    finally:
        env.close()
    threshold = reward_threshold(cfg["env_id"])
    result.update(
        env_id=cfg["env_id"],
        algo=cfg["algo"],
        device=cfg["device"],
        reward_threshold=threshold,
        solved=bool(threshold is not None and result["mean_return"] >= threshold),
        run_dir=str(run_dir),
        model=str(model_path or Path(run_dir) / MODEL_FILE),
    )
    return result


def record_video(
    run_dir: str | Path,
    path: str | Path,
    *,
    episodes: int = 3,
    device: str | None = None,
    seed: int | None = None,
    deterministic: bool = True,
    max_steps_per_episode: int = 2000,
    fps: float | None = None,
    model_path: str | Path | None = None,
) -> dict[str, Any]:
    """Roll out ``episodes`` episodes of one world and write the rgb_array frames to ``path``.

    A format other than .gif/.mp4 (ValueError) or a missing writer for it (RuntimeError) fails
    before anything is loaded or rolled out."""
    problem = video_backend_error(path)
    if problem is not None:
        raise (ValueError if Path(path).suffix.lower() not in (".gif", ".mp4") else RuntimeError)(problem)
    cfg, model, vecnorm = load_run(run_dir, device=device, model_path=model_path)
    env = build_eval_env(
        cfg,
        num_envs=1,
        seed=cfg["seed"] + EVAL_SEED_OFFSET if seed is None else seed,
        vecnormalize=vecnorm,
        render_mode="rgb_array",
    )
    frames: list[np.ndarray] = []
    returns: list[float | None] = []  # None: an episode cut at max_steps_per_episode
    try:
        obs = env.reset()
        for _ in range(episodes):
            frames.append(_frame(env))  # the episode's first state
            ret = None
            for _step in range(max_steps_per_episode):
                action, _ = model.predict(obs, deterministic=deterministic)
                obs, _, dones, infos = env.step(action)
                if dones[0]:  # the env has already reset: the frame would show the next episode
                    ret = float(infos[0]["episode"]["r"])
                    break
                frames.append(_frame(env))
            else:
                obs = env.reset()
            returns.append(ret)
        if fps is None:
            fps = float(_render_fps(env) or 30)
    finally:
        env.close()
    write_frames(path, frames, fps)
    return {"video": str(path), "frames": len(frames), "fps": fps, "episode_returns": returns}


def _frame(env) -> np.ndarray:
    images = env.get_images()
    frame = images[0] if images else None
    if frame is None:
        raise RuntimeError("the env returned no rgb_array frame (does it support render_mode='rgb_array'?)")
    frame = np.asarray(frame)
    if frame.dtype != np.uint8:
        frame = np.clip(frame * (255.0 if frame.max() <= 1.0 else 1.0), 0, 255).astype(np.uint8)
    return frame[..., :3]


def _render_fps(env) -> float | None:
    try:
        return env.unwrapped.env.metadata.get("render_fps")
    except AttributeError:
        return None


def write_frames(path: str | Path, frames: list[np.ndarray], fps: float) -> None:
    """GIF through Pillow, MP4 through imageio (if installed)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not frames:
        raise ValueError("no frames to write")
    suffix = path.suffix.lower()
    if suffix == ".gif":
        from PIL import Image

        images = [Image.fromarray(f) for f in frames]
        images[0].save(
            path, save_all=True, append_images=images[1:], duration=max(int(round(1000 / fps)), 20), loop=0
        )
    elif suffix == ".mp4":
        try:
            import imageio.v2 as imageio
        except ImportError:
            raise RuntimeError("writing MP4 needs imageio with ffmpeg (pip install 'imageio[ffmpeg]'); use .gif") from None
        imageio.mimwrite(path, frames, fps=fps)
    else:
        raise ValueError(f"unsupported video format {suffix!r}: use .gif or .mp4")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="abd-gym-evaluate", description=__doc__.split("\n\n")[0])
    p.add_argument("run_dir")
    p.add_argument("--episodes", type=int, help="evaluation episodes, at least 1 (default: the config's eval_episodes)")
    p.add_argument("--device")
    p.add_argument("--seed", type=int)
    p.add_argument("--stochastic", action="store_true", help="sample actions instead of the deterministic policy")
    which = p.add_mutually_exclusive_group()
    which.add_argument("--model", help="model file to evaluate (e.g. a checkpoint; default: see --final)")
    which.add_argument("--final", action="store_true",
                       help="evaluate RUN_DIR/model.zip even where the run found best_model.zip better (the default then)")
    p.add_argument("--json", help="write the evaluation result to this JSON file")
    p.add_argument("--video", help="record a video (.gif or .mp4)")
    p.add_argument("--video-episodes", type=int, default=3)
    p.add_argument("--video-max-steps", type=int, default=2000, help="cut a recorded episode after this many steps")
    p.add_argument("--fps", type=float)
    return p.parse_args(argv)


def _argument_error(args: argparse.Namespace) -> str | None:
    """What is wrong with the arguments, found before anything is loaded or run, or None."""
    if args.episodes is not None and args.episodes < 1:
        return f"--episodes {args.episodes}: must be at least 1"
    if args.video_episodes < 1:
        return f"--video-episodes {args.video_episodes}: must be at least 1"
    if args.model is not None and not Path(args.model).is_file():
        return f"--model {args.model}: no such file"
    if args.final and not (Path(args.run_dir) / MODEL_FILE).is_file():
        return f"--final: {args.run_dir} has no {MODEL_FILE}"
    if args.video:
        problem = video_backend_error(args.video)
        if problem is not None:
            return problem
    if args.device is not None:
        try:
            resolve_device(args.device)
        except ValueError as exc:
            return str(exc)
    return None


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    import torch

    torch.set_num_threads(1)  # small MLPs: one thread is fastest (see abd_gym.agents.train)
    if not (Path(args.run_dir) / CONFIG_FILE).is_file():
        print(f"abd-gym-evaluate: error: {args.run_dir} has no {CONFIG_FILE} (not a run directory)", file=sys.stderr)
        return 2
    problem = _argument_error(args)
    if problem is not None:
        print(f"abd-gym-evaluate: error: {problem}", file=sys.stderr)
        return 2
    if args.model is not None:
        model_path, why = Path(args.model), "--model"
    elif args.final:
        model_path, why = Path(args.run_dir) / MODEL_FILE, "--final"
    else:
        model_path, why = default_model(args.run_dir)
    print(f"model: {model_path} ({why})", flush=True)
    result = evaluate_run(
        args.run_dir,
        episodes=args.episodes,
        device=args.device,
        seed=args.seed,
        deterministic=not args.stochastic,
        model_path=model_path,
    )
    thr = result["reward_threshold"]
    print(
        f"{result['env_id']} ({result['algo']}, {model_path.name}): return {result['mean_return']:.2f} ± {result['std_return']:.2f} "
        f"over {result['eval_episodes']} episodes"
        + (f" (threshold {thr:g}: {'solved' if result['solved'] else 'not solved'})" if thr is not None else "")
    )
    if args.video:
        video = record_video(
            args.run_dir,
            args.video,
            episodes=args.video_episodes,
            device=args.device,
            seed=args.seed,
            deterministic=not args.stochastic,
            fps=args.fps,
            model_path=model_path,
            max_steps_per_episode=args.video_max_steps,
        )
        result["video"] = video
        print(f"video: {video['video']} ({video['frames']} frames at {video['fps']:g} fps)")
    if args.json:
        write_json(Path(args.json), result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
