"""Training progress for ``abd-gym-train``: plain log lines and periodic evaluation.

Without a terminal (CI, nohup, Ray) a progress bar writes nothing readable, so the trainer prints
one line every tenth of the run instead::

    cartpole_ppo: 60,000/100,000 steps (60%)  4,131 steps/s  return 436.3 (last 100 episodes)

``steps/s`` is env steps (all worlds) per second of wall time since training started; the return
is the mean raw return of the last episodes SB3 keeps (``ep_info_buffer``, up to 100).
Periodic evaluations (``eval_freq``) print one line each and record the first env step and wall
time at which the evaluation's mean return reached the task's reward threshold; with
``stop_after`` they end training once that many evaluations in a row are solved with a standard
error to spare (see :class:`ThresholdEval`).
"""
from __future__ import annotations

import os
import sys
import time
from typing import Any, Callable

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback, EvalCallback
from stable_baselines3.common.vec_env import sync_envs_normalization

__all__ = ["ProgressLines", "SaveVecNormalize", "ThresholdEval", "evaluations_in_a_row", "mean_episode_return",
           "stdout_is_terminal"]


def stdout_is_terminal() -> bool:
    try:
        return bool(sys.stdout.isatty())
    except (AttributeError, ValueError):
        return False


def mean_episode_return(model) -> tuple[float | None, int]:
    """(mean raw return of the episodes in ``model.ep_info_buffer`` or None, how many)."""
    buf = getattr(model, "ep_info_buffer", None) or []
    returns = [float(info["r"]) for info in buf if "r" in info]
    return (float(np.mean(returns)) if returns else None, len(returns))


class ProgressLines(BaseCallback):
    """One line at every ``1/parts`` of ``total_timesteps`` and at the end of training.

    ``write`` receives each line (default: ``print`` with flush, so the line reaches a log file
    at once).
    """

    def __init__(self, total_timesteps: int, *, name: str = "", parts: int = 10, write: Callable[[str], None] | None = None):
        super().__init__()
        self.total = max(int(total_timesteps), 1)
        self.step = max(self.total // max(int(parts), 1), 1)
        self.name = name
        self.write = write or (lambda line: print(line, flush=True))
        self.t0 = time.perf_counter()
        self.next_mark = self.step
        self.last_line_at = -1

    def _on_training_start(self) -> None:
        self.t0 = time.perf_counter()
        self.next_mark = self.model.num_timesteps + self.step

    def _on_step(self) -> bool:
        if self.num_timesteps >= self.next_mark:
            self.write(self.line())
            self.last_line_at = self.num_timesteps
            while self.next_mark <= self.num_timesteps:
                self.next_mark += self.step
        return True

    def _on_training_end(self) -> None:
        # the run's last line, unless one was printed at the requested total already (SB3 ends its
        # last rollout past it)
        if self.last_line_at < min(self.num_timesteps, self.total):
            self.write(self.line())
            self.last_line_at = self.num_timesteps

    def line(self) -> str:
        elapsed = time.perf_counter() - self.t0
        rate = self.num_timesteps / elapsed if elapsed > 0 else float("nan")
        mean, count = mean_episode_return(self.model)
        ret = f"return {mean:.1f} (last {count} episodes)" if mean is not None else "return n/a (no episode ended yet)"
        pct = 100.0 * self.num_timesteps / self.total
        prefix = f"{self.name}: " if self.name else ""
        return f"{prefix}{self.num_timesteps:,}/{self.total:,} steps ({pct:.0f}%)  {rate:,.0f} steps/s  {ret}"


class ThresholdEval(EvalCallback):
    """SB3's ``EvalCallback`` that evaluates with :func:`~.common.episode_evaluator` (on the device
    where the eval env was built for it) and records when the evaluation first reached ``threshold``.

    ``threshold_step``: ``model.num_timesteps`` (env steps, all worlds) at the first evaluation
    whose mean return is at least ``threshold``; ``threshold_time_s``: wall seconds from the start
    of training to the end of that evaluation (the periodic evaluations' own time included).
    Both stay None while it has not happened, or when ``threshold`` is None.  ``eval_time_s``: the
    evaluations' wall time so far.  ``write`` (if given) receives one line per evaluation.

    ``stop_after`` N > 0 ends training (``_on_step`` returns False) after N evaluations in a row
    whose mean return minus its standard error (std / sqrt(episodes)) is at least ``threshold``:
    a policy that has been measured solved N times, each time by more than its evaluation's
    noise, is kept as it is rather than trained on at a learning rate that can still move it off
    the solution.  ``solved_streak``: such evaluations in a row so far; ``stopped_step``: the
    env step at which training was ended (None while it goes on).  ``best_step``: the env step
    of the evaluation that saved ``best_model.zip``.

    Each evaluation does what ``EvalCallback`` does (statistics synced, ``evaluations.npz``,
    ``eval/mean_reward`` and ``eval/mean_ep_length`` logged, ``best_model.zip`` and
    ``callback_on_new_best`` on a new best, ``callback`` after each) but neither renders nor
    reads ``is_success``.
    """

    def __init__(self, eval_env, *, threshold: float | None, name: str = "",
                 write: Callable[[str], None] | None = None, stop_after: int = 0, **kwargs: Any):
        from abd_gym.agents.common import episode_evaluator

        if stop_after < 0:
            raise ValueError(f"stop_after must be 0 (off) or at least 1, got {stop_after}")
        if stop_after and threshold is None:
            raise ValueError("stop_after needs a threshold: the task has no reward_threshold")
        super().__init__(eval_env, **kwargs)
        self.evaluate = episode_evaluator(self.eval_env)
        self.threshold = threshold
        self.stop_after = int(stop_after)
        self.solved_streak = 0
        self.stopped_step: int | None = None
        self.best_step: int | None = None
        self.name = name
        self.write = write
        self.threshold_step: int | None = None
        self.threshold_time_s: float | None = None
        self.n_evaluations = 0
        self.eval_time_s = 0.0
        self.t0 = time.perf_counter()

    def _on_training_start(self) -> None:
        super()._on_training_start()
        self.t0 = time.perf_counter()

    def _on_step(self) -> bool:
        if not (self.eval_freq > 0 and self.n_calls % self.eval_freq == 0):
            return True
        if self.model.get_vec_normalize_env() is not None:
            sync_envs_normalization(self.training_env, self.eval_env)
        started = time.perf_counter()
        returns, lengths = self.evaluate(self.model, self.n_eval_episodes, deterministic=self.deterministic)
        self.eval_time_s += time.perf_counter() - started
        self.n_evaluations += 1
        if self.log_path is not None:
            self.evaluations_timesteps.append(self.num_timesteps)
            self.evaluations_results.append(returns)
            self.evaluations_length.append(lengths)
            np.savez(self.log_path, timesteps=self.evaluations_timesteps, results=self.evaluations_results,
                     ep_lengths=self.evaluations_length)  # fmt: skip
        mean = float(np.mean(returns))
        self.last_mean_reward = mean
        self.logger.record("eval/mean_reward", mean)
        self.logger.record("eval/mean_ep_length", float(np.mean(lengths)))
        self.logger.record("time/total_timesteps", self.num_timesteps, exclude="tensorboard")
        self.logger.dump(self.num_timesteps)
        keep_going = True
        if mean > self.best_mean_reward:
            if self.best_model_save_path is not None:
                self.model.save(os.path.join(self.best_model_save_path, "best_model"))
            self.best_mean_reward = mean
            self.best_step = int(self.num_timesteps)
            if self.callback_on_new_best is not None:
                keep_going = self.callback_on_new_best.on_step()
        self._after_evaluation(returns)
        if self.callback is not None:
            keep_going = keep_going and self._on_event()
        if self.stop_after and self.solved_streak >= self.stop_after:
            self.stopped_step = int(self.num_timesteps)
            if self.write is not None:
                prefix = f"{self.name}: " if self.name else ""
                self.write(f"{prefix}stopping at {self.num_timesteps:,} steps: solved in "
                           f"{evaluations_in_a_row(self.solved_streak)} (stop_when_solved)")  # fmt: skip
            keep_going = False
        return keep_going

    def solved_with_margin(self, returns: list[float]) -> bool:
        """Whether the mean of ``returns`` minus its standard error reaches the threshold."""
        if self.threshold is None or len(returns) == 0:
            return False
        return float(np.mean(returns)) - float(np.std(returns)) / np.sqrt(len(returns)) >= self.threshold

    def _after_evaluation(self, returns: list[float]) -> None:
        mean = self.last_mean_reward
        reached = self.threshold is not None and mean >= self.threshold
        if reached and self.threshold_step is None:
            self.threshold_step = int(self.num_timesteps)
            self.threshold_time_s = round(time.perf_counter() - self.t0, 2)
        self.solved_streak = self.solved_streak + 1 if self.solved_with_margin(returns) else 0
        if self.write is not None:
            thr = ""
            if self.threshold is not None:
                thr = f" (threshold {self.threshold:g}: {'reached' if reached else 'not reached'})"
            prefix = f"{self.name}: " if self.name else ""
            self.write(
                f"{prefix}eval at {self.num_timesteps:,} steps: return {mean:.1f} ± {np.std(returns):.1f} "
                f"over {len(returns)} episodes{thr}"
            )


def evaluations_in_a_row(n: int) -> str:
    """``1 evaluation`` or ``N evaluations in a row``: how many solved evaluations stopped a run."""
    return "1 evaluation" if n == 1 else f"{n} evaluations in a row"


class SaveVecNormalize(BaseCallback):
    """Saves the training env's observation statistics to ``path`` (for ``best_model.zip``: the
    statistics it was evaluated with)."""

    def __init__(self, path: str):
        super().__init__()
        self.path = path

    def _on_step(self) -> bool:
        vecnorm = self.model.get_vec_normalize_env()
        if vecnorm is not None:
            vecnorm.save(self.path)
        return True
