"""The base of the tasks built from Gymnasium's bundled MuJoCo model files.

The files are read where the installed ``gymnasium`` package keeps them
(``gymnasium/envs/mujoco/assets/``) and imported by ``Scene.from_mjcf`` (MuJoCo's compiler; the
``mujoco`` package is needed): joint k is the file's joint k, its coordinate MuJoCo's ``qpos``
value; drive k is actuator k, its input u = gear · ctrl [N or N·m].  Actions are the actuators'
controls in their control range, as in Gymnasium (``Box(lo, hi)``; the ranges of the classics
are symmetric and equal across actuators, so the range's bound is the task's ``action_bound``
and the drives' max effort gear · bound maps it to u = gear · ctrl).
"""
from __future__ import annotations

from pathlib import Path

import gymnasium
import numpy as np

import abd_gym as ag
from abd_gym.vector.vector_env import ABDVectorEnv


def asset_path(name: str) -> Path:
    """Path of Gymnasium's bundled MuJoCo model file ``name`` (e.g. ``"reacher.xml"``)."""
    path = Path(gymnasium.__file__).parent / "envs" / "mujoco" / "assets" / name
    if not path.is_file():
        raise FileNotFoundError(f"{path}: Gymnasium's MuJoCo assets are not installed with gymnasium "
                                f"{gymnasium.__version__}")  # fmt: skip
    return path


class GymnasiumMjcfEnv(ABDVectorEnv):
    """A task on one of Gymnasium's MuJoCo model files: ``asset`` (file name), ``exclude`` (bodies
    of the file left out of the scene, kept by the task as its own state).  ``dt`` must be the
    file's timestep and ``frame_skip`` Gymnasium's (tests/test_classics.py checks both)."""

    asset: str = ""
    exclude: tuple = ()

    def build_scene(self):
        scene = ag.Scene.from_mjcf(asset_path(self.asset), exclude=self.exclude)
        self.imported = scene.imported
        self.action_bound = control_bound(scene)
        self._points = {}  # frame_point's (abd body, backend local position) by name
        return scene

    def frame_point(self, name: str, site: bool = False):
        """(N, 3) world position [m] of the MuJoCo body frame ``name`` (or of the site ``name``):
        its abd body's pose applied to the point's position in that body."""
        key = (name, site)
        if key not in self._points:  # uploaded once (the first steps run before a step graph's capture)
            body, local = self.imported.sites[name] if site else self.imported.frames[name][:2]
            self._points[key] = (body, self.asarray(np.asarray(local, dtype=np.float64).reshape(3)))
        body, local = self._points[key]
        p, A = self.body_positions()[:, body], self.body_rotations()[:, body]
        return p + (A * local).sum(axis=-1)


def control_bound(scene) -> float:
    """The bound b of the scene's actuators' control range [−b, b] (one for all), checked
    against the drives' max effort gear · b."""
    imp = scene.imported
    ranges = np.asarray(imp.ctrlrange, dtype=np.float64).reshape(-1, 2)
    bound = float(ranges[0, 1])
    if not (np.allclose(ranges[:, 1], bound) and np.allclose(ranges[:, 0], -bound) and bound > 0):
        raise ValueError(f"{imp.model_name}: the actuators' control ranges {ranges.tolist()} are not one symmetric "
                         "range (actions share one bound)")  # fmt: skip
    gear = np.asarray(imp.gear, dtype=np.float64).reshape(-1)
    effort = np.array([d.max_effort for d in scene.drives])
    if not (np.all(gear > 0) and np.allclose(effort, gear * bound, rtol=1e-6)):
        raise ValueError(f"{imp.model_name}: drive max efforts {effort.tolist()} are not gear · {bound} with a "
                         f"positive gear (gear {gear.tolist()})")  # fmt: skip
    return bound
