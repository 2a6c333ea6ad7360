"""Each world's episode bookkeeping in backend arrays: its clock and its task values.

``elapsed`` (N,) int64: env steps in the current episode.  ``task`` (N, width) float32: the
task's per-episode values (``task_state``: (attribute, width) pairs, e.g. a Reacher's target),
one array whose columns the env's task attributes view, so that an autoreset on the device
writes them with the episode's initial state (:mod:`abd_gym.vector.autoreset`).
"""
from __future__ import annotations

import numpy as np

from .arrays import assign, host_copy


def check_task_state(task_state) -> int:
    """The total width of ``task_state``, whose entries must be (identifier, positive int width)."""
    for name, width in task_state:
        if not (isinstance(name, str) and name.isidentifier() and isinstance(width, (int, np.integer)) and width >= 1):
            raise ValueError(f"task_state entries must be (attribute name, positive int width), got {(name, width)!r}")
    return sum(int(w) for _, w in task_state)


class Episodes:
    """``elapsed``, ``task`` (module docstring) and ``no_flags``, an all-False (N,) bool array made
    once: building one each step would be a host-to-device copy (on a GPU, from pageable memory,
    which waits for the stream) in every step of every task without terminations."""

    def __init__(self, arrays, num_envs: int, task_state: tuple):
        self.arrays, self.task_state = arrays, tuple(task_state)
        self.task_width = check_task_state(self.task_state)
        self.elapsed = arrays.zeros(num_envs, dtype="int")
        self.task = arrays.zeros(num_envs, self.task_width)
        self.no_flags = arrays.zeros(num_envs, dtype="bool")

    def task_views(self) -> dict:
        """{attribute: view of its columns of ``task``} ((N,) for width 1, else (N, width))."""
        views, col = {}, 0
        for name, width in self.task_state:
            views[name] = self.task[:, col] if width == 1 else self.task[:, col : col + width]
            col += width
        return views

    def task_matrix(self, values: dict, n: int) -> np.ndarray:
        """``draw_task``'s values as one (n, width) array, columns in ``task_state`` order."""
        missing = [name for name, _ in self.task_state if name not in values]
        if missing or len(values) != len(self.task_state):
            raise ValueError(f"draw_task must return exactly the task_state values {[k for k, _ in self.task_state]}, "
                             f"got {sorted(values)}")  # fmt: skip
        return np.concatenate([np.asarray(values[name], dtype=np.float64).reshape(n, int(w))
                               for name, w in self.task_state], axis=1)  # fmt: skip

    def all_false(self):
        """A new all-False (N,) bool array."""
        return self.arrays.copy(self.no_flags)

    def snapshot(self) -> dict:
        return {"elapsed": host_copy(self.elapsed), "task": host_copy(self.task)}

    def restore(self, snap: dict):
        """In place: the task attributes view ``task``'s columns."""
        assign(self.elapsed, snap["elapsed"])
        assign(self.task, snap["task"])
