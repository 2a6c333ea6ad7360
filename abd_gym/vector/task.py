"""What a task subclasses: the hooks of :class:`~abd_gym.vector.vector_env.ABDVectorEnv` with their
defaults, and what hooks read (the simulator's joint and body arrays, the episode clocks, the
array helpers of the env's backend).  The hooks, their shapes and units are listed in
``ABDVectorEnv``'s docstring; the env wires the layers that call them.
"""
from __future__ import annotations

import numpy as np

from ..sim.scene import Scene


class Task:
    """The task hooks and their reads; mixed into ABDVectorEnv, whose constructor sets what they
    read: ``scene``, ``sim``, ``arrays`` (vector.arrays.Backend), ``xp``, ``backend``, ``episodes``
    (episodes.Episodes), ``num_envs`` and ``step_dt``."""

    def _init_task_arrays(self, observation_high: np.ndarray):
        """The backend arrays of the hooks' defaults, made once by the env's constructor: the drives'
        max efforts (``max_effort``), the efforts per unit of action (``action_scale``) and the
        observation bounds (``observation``; the low bound kept: negating the high one in each
        step is a launch)."""
        self._max_effort = np.array([d.max_effort for d in self.scene.drives], dtype=np.float32)
        if len(self.scene.drives) and not np.all(np.isfinite(self._max_effort)):
            raise ValueError("every drive of a task needs a finite max_effort (actions are scaled by it)")
        if not (np.isfinite(self.action_bound) and self.action_bound > 0):
            raise ValueError(f"action_bound must be positive and finite, got {self.action_bound!r}")
        has_drives = len(self.scene.drives) > 0
        self._effort = self.asarray(self._max_effort) if has_drives else None
        self._action_scale = self.asarray(self._max_effort / np.float32(self.action_bound)) if has_drives else None
        self._obs_high = self.asarray(observation_high)
        self._obs_low = -self._obs_high

    # ================================================================== hooks
    def build_scene(self) -> Scene:
        """The task's mechanism in its zero pose."""
        raise NotImplementedError

    def observation_high(self) -> np.ndarray:
        """Upper bounds of one observation (the space is symmetric: low = -high; finite: observations
        are clipped to them, so choose bounds the task does not reach, ``velocity_bound`` for rates)."""
        raise NotImplementedError

    @property
    def action_dim(self) -> int:
        """Actions per world: by default one per drive."""
        return len(self.scene.drives)

    # actions lie in Box(−action_bound, action_bound) per entry (a task imported from MJCF: the
    # actuators' control range, whose bound the drives' max_effort = gear · bound matches)
    action_bound: float = 1.0

    @property
    def max_effort(self):
        """(num_drives,) each drive's ``max_effort`` [N or N·m] as a float32 backend array."""
        return self._effort

    @property
    def action_scale(self):
        """(num_drives,) drive input per unit of action, max_effort / action_bound [N or N·m]."""
        return self._action_scale

    def controls(self, actions):
        """Drive inputs (N, num_drives) from clipped actions (N, action_dim): a × max_effort / action_bound."""
        return actions * self._action_scale

    def observe(self):
        """(N, obs_dim) observation of every world (backend array)."""
        raise NotImplementedError

    def reward(self, obs, actions):
        """(N,) reward of the step to ``obs`` (N, obs_dim) with clipped ``actions`` (N, action_dim)."""
        raise NotImplementedError

    def terminated(self, obs):
        """(N,) bool: the worlds whose episode ends at ``obs``; by default none."""
        return self.episodes.no_flags  # read only: step combines it into a new array

    def initial_state(self, n: int, rng: np.random.Generator, options: dict):
        """Joint coordinates and velocities (n, num_joints) of n fresh episodes (host NumPy)."""
        nj = self.scene.num_joints
        return np.zeros((n, nj)), np.zeros((n, nj))

    def draw_task(self, n: int, rng: np.random.Generator, options: dict) -> dict:
        """The ``task_state`` values of n new episodes: {attribute: (n,) or (n, width) host array}."""
        return {}

    def reset_task(self, idx: np.ndarray, rng: np.random.Generator, options: dict):
        """Task state of the worlds ``idx`` for a new episode: by default the ``task_state`` values
        ``draw_task`` draws.  A task that overrides this resets on the host (no autoresets on the
        device, no step graph); it runs after the reset's other writes, and an exception it raises
        puts them back (the env's arrays, ``task_state`` values included; attributes of the task's
        own are its own to keep)."""
        if self.episodes.task_width:
            self.put(self.episodes.task, idx, self.task_values(len(idx), rng, options))

    def task_values(self, n: int, rng: np.random.Generator, options: dict) -> np.ndarray:
        """The (n, task width) task state of n new episodes: ``draw_task``'s values as one matrix."""
        return self.episodes.task_matrix(self.draw_task(n, rng, options), n)

    def info(self, obs) -> dict:
        """Per-step info: a dict of batched arrays (each gets an all-True ``"_key"`` mask)."""
        return {}

    def render_extras(self, canvas, world: int):
        """Draw task-specific marks (targets, end stops) on a render canvas, over the bodies."""

    # ================================================================== one world on the host
    # Optional: ``observe``, ``reward`` and ``terminated`` of one world in plain Python floats,
    # which ABDEnv's CPU step (single_step.HostStep) calls instead of the batched hooks, whose
    # NumPy calls on arrays of one row cost more than the physics.  A task gives all three or
    # none; each must give what its batched hook gives for that world, value for value
    # (tests/test_single_env.py checks every task that has them).  Thresholds compare as NumPy
    # compares a float32 observation with a Python number: against the number rounded to float32
    # (``float32_of``).
    world_observation = None  # (q, v: lists of the joint coordinates and rates) -> list: observe()'s row
    world_reward = None  # (obs, action: lists of float32 values, clipped) -> float: reward()'s value as float32
    world_terminated = None  # (obs: list of float32 values, clipped) -> bool: terminated()'s value

    # ================================================================== array helpers
    def asarray(self, values, dtype="float"):
        """Host values as a backend array (on the simulator's device for torch); ``dtype`` "float"
        (float32), "int" (int64) or "bool"."""
        return self.arrays.asarray(values, dtype)

    def zeros(self, *shape, dtype="float"):
        """A backend array of zeros of ``shape`` (``dtype`` as ``asarray``)."""
        return self.arrays.zeros(*shape, dtype=dtype)

    def put(self, array, idx: np.ndarray, values):
        """array[idx] = values (host values into a backend array of the same dtype)."""
        self.arrays.put(array, idx, values)

    def f32(self, x):
        """``x`` (a backend array) as float32."""
        return x.astype(np.float32, copy=False) if self.xp is np else x.to(self.xp.float32)

    # ================================================================== what hooks read
    def coords(self):
        """(N, num_joints) joint coordinates [rad, m] as a backend array."""
        return self.sim.joint_coordinates(backend=self.backend)

    def velocities(self):
        """(N, num_joints) joint rates [rad/s, m/s]."""
        return self.sim.joint_velocities(backend=self.backend)

    def unwrapped_coords(self):
        """(N, num_joints) multi-turn revolute angles [rad] (displacement for sliders)."""
        return self.sim.joint_angles_unwrapped(backend=self.backend)

    def body_positions(self):
        """(N, num_bodies, 3) body origins [m]."""
        return self.sim.body_positions(backend=self.backend)

    def body_rotations(self):
        """(N, num_bodies, 3, 3) body rotations A."""
        return self.sim.body_rotations(backend=self.backend)

    def episode_time(self):
        """(N,) time since each world's reset [s]."""
        return self.f32(self.episodes.elapsed) * self.step_dt

    def observation(self):
        """The observation as the env returns it: ``observe()`` as float32, clipped to the
        observation space."""
        obs = self.f32(self.observe())
        if self.xp is np:  # np.clip's arithmetic (NaN kept) without its Python wrapper
            return np.minimum(np.maximum(obs, self._obs_low), self._obs_high)
        return self.xp.clip(obs, self._obs_low, self._obs_high)


class Float32Values(dict):
    """``{x: x rounded to float32, as a Python float}``, each made on its first look-up (a dict's
    look-up: the one-world hooks read it every step): ``float32_of[x]`` is the number a float32
    array is compared with where NumPy compares it with the Python number ``x`` (NEP 50)."""

    def __missing__(self, x):
        if len(self) >= 1024:  # thresholds set anew without end: kept bounded
            self.clear()
        value = self[x] = float(np.float32(x))
        return value


float32_of = Float32Values()
