"""Native batched Gymnasium environments: ``num_envs`` worlds of one task in one ``Simulator``.

:class:`ABDVectorEnv` is a ``gymnasium.vector.VectorEnv`` (not N single envs behind a loop): one
scene stepped in ``num_envs`` worlds, batched observation / reward / termination arrays computed
from the simulator's arrays in one go, and the Gymnasium 1.x vector API on top:

* spaces: ``single_observation_space`` / ``single_action_space`` (``Box``, float32) and their
  batched versions ``observation_space`` / ``action_space`` (leading ``num_envs`` axis).  Actions
  are normalised to ``[-1, 1]`` per drive and scaled by the drive's ``max_effort``.
* ``reset(seed=None, options=None)`` -> ``(obs, info)``; ``step(actions)`` ->
  ``(obs, reward, terminated, truncated, info)``, all batched (reward float32, flags bool).
* autoreset (``metadata["autoreset_mode"]``, set by the ``autoreset_mode`` argument):

  - ``AutoresetMode.NEXT_STEP`` (default): a world that ends in step t is reset in step t+1;
    that step ignores its action and returns its first observation with reward 0 and both flags
    False.
  - ``AutoresetMode.SAME_STEP``: a world that ends is reset within the step; ``obs`` holds its
    first observation of the next episode, ``info["final_obs"]`` the last one of the finished
    episode and ``info["final_info"]`` that step's info.  ``info["final_obs"]`` is a batch of the
    same type and shape as ``obs`` whose rows are valid where the bool mask
    ``info["_final_obs"]`` is True (other rows equal ``obs``); ``final_info`` holds per-world
    arrays with their own ``"_key"`` masks, as Gymnasium's ``SyncVectorEnv`` reports them, and the
    top-level entries of the reset worlds are masked out (their reset info is empty).
  - ``AutoresetMode.DISABLED``: nothing is reset automatically; call
    ``reset(options={"reset_mask": mask})`` with a NumPy bool mask of shape ``(num_envs,)``.
    Worlds outside the mask are left untouched (their state, step count and parameters).

  ``reset_mask`` works in every mode.
* time limit: ``max_episode_steps`` (set by ``gym.make_vec`` from the registration) truncates a
  world after that many steps of its episode; ``None`` disables truncation.
* seeding: ``reset(seed=s)`` seeds one NumPy generator from which every initial state, target and
  randomised parameter is drawn (in world order), so the same seed and the same actions give the
  same trajectories.  The physics itself is deterministic.
* backends: ``backend="numpy"`` (default) returns NumPy arrays; ``backend="torch"`` returns Torch
  tensors on the simulator's device, computed from zero-copy views of the simulator's arrays, and
  takes actions as tensors (or arrays).  Only the NaN check (one bool), the done mask and, when
  worlds are done, their reset states cross between host and device.  The done mask reaches the
  host by an asynchronous copy that the next step reads after queuing its own physics, so the
  host's work on a step's results runs while the device steps (SAME_STEP resets must wait for it).
  Op by op on a GPU, a step waits for the device once more, at the NaN check, before its physics
  is queued; the step graph (below) checks on the device and never waits for the step it queues.
* autoresets on the device and the step as one graph: in NEXT_STEP mode, for a task whose
  episodes start from ``_initial_state`` and its ``task_state`` values (``_draw_task``: a
  Reacher's target) alone (no ``_reset_task`` of its own) and while no parameters are
  randomised, each world's next initial states and task values are drawn ahead into a queue on
  the device
  (:mod:`abd_gym.autoreset`; from a generator spawned from ``np_random`` at each full reset, so
  the same seed gives the same episodes on every backend and device) and the autoreset is device
  work only.  With the Torch backend on a GPU the whole step (action check, controls, physics,
  autoreset, observation, reward, flags) is then captured once as one CUDA graph (the Warp part,
  with the Torch graph of what follows nested in it as a child graph) and replayed, two such
  graphs in turn.  Where the simulator's step is one launch (``Solver.holds``: the lane-split
  step, by default up to ~4,000 worlds), the physics and the autoreset run at once on two streams
  of the graph: the step holds (does not touch) the worlds whose autoreset restarts them, and
  both skip a refused batch themselves; elsewhere they run in turn inside a conditional node on
  the check's go flag.  (On an H100 this took 1,024 CartPole-v0 worlds' step graph from 142 to
  118 µs of device time, about 102 of them physics.)  The graph reads the
  caller's action batch and writes the step's outputs to a fresh buffer (the caller's to keep) by
  pointers the host leaves in page-locked memory, and writes the done mask there for the host,
  so a step is one graph launch and no copy.  The env's own bookkeeping runs there as a few Warp kernels
  (:mod:`abd_gym.env_kernels`) after the task's Torch code, which torch.compile fuses into a few
  kernels where Triton is installed (``compile_outcome``, default on with the step graph; the
  first step then takes seconds more).
  The graphs hold the task's Python constants (thresholds, ``max_episode_steps``, reward weights)
  as they were when captured, at the env's second step: set them before stepping.
  ``graph=False`` launches the same work op by op (the default elsewhere); ``graph=True`` where it
  cannot apply raises ``ValueError``.
* bad actions: actions are clipped to the action space (so out-of-range values and ±inf act as
  ±1).  An action batch containing NaN raises ``ValueError`` naming the worlds, and no world
  changes state.  With the step graph (Torch on a GPU) the check runs on the device, so it is
  reported one call late: the call given the batch returns (its outputs are those of worlds that
  did not move), the device refuses that step and every step after it, and the next ``step`` or
  ``reset`` raises, having taken back the host's bookkeeping of both calls (clocks, autoreset
  queues); the env then goes on as if the batch had never been passed.  Elsewhere the call given
  the batch raises before anything is stepped.  A world whose solve fails
  (``Simulator.failed_worlds``, or a non-finite observation) is terminated, reported in
  ``info["sim_failed"]`` (a bool per world, in every step's info) and gets a zero observation and
  reward; the autoreset (or your masked reset) brings it back.
* observations are float32 and clipped to ``single_observation_space``, whose bounds are finite
  and chosen above what the task reaches (rates: ``velocity_bound`` = 100 rad/s or m/s).
* per-world physical parameters: ``randomize={...}`` (constructor or ``reset`` option, sticky:
  it applies to every later reset of a world, autoresets included, until a reset passes a new
  ``"randomize"``; ``None`` restores the nominal values)::

      {"mass_scale": (lo, hi),              # every free body's mass × U(lo, hi) (per body)
       "strength_ratio": (lo, hi),          # every joint's strength ratio ~ U(lo, hi)
       "limit_scale": (lo, hi),             # every limit's lower and upper × U(lo, hi)
       "limit_strength_scale": (lo, hi)}    # every limit's strength × U(lo, hi)

  Each value may also be a dict ``{body or joint name: (lo, hi)}`` to randomise only some of them.
  The values in force are in ``body_mass``, ``strength_ratio`` and ``limits`` (host arrays).
* rendering: ``render_mode="rgb_array"``; ``render()`` returns a tuple of uint8 ``(H, W, 3)``
  frames, one per world in ``render_worlds`` (default: every world when ``num_envs <= 16``,
  else the first 16), drawn headless by :mod:`abd_gym.render`.

Simulator options: ``device`` ("cpu", "cuda:0"; default ``$ABD_GYM_DEVICE`` or "cpu"), ``dtype``
("float32" or "float64") and ``integrator`` (the simulator's default, implicit Euler, unless given);
the tasks' rewards and thresholds are calibrated with the defaults.  ``simulator_options``: more
Simulator keyword arguments, e.g. ``{"tol": 1e-4}``, or ``{"plan": {"scratch": "global"}}`` (an
``ExecutionPlan`` or a dict of its fields: how the step runs on the device); an unknown name or a
bad value is the Simulator's error.

A task subclasses :class:`ABDVectorEnv` and defines the class attributes ``dt``, ``frame_skip``
and the methods ``build_scene``, ``observation_high`` (bounds), ``_observe``, ``_reward`` and
optionally ``_terminated``, ``_initial_state``, ``task_state`` with ``_draw_task`` (per-episode
task values, e.g. a target: drawn on the device's autoreset path too), ``_reset_task`` (a task's
own reset on the host, which keeps it off the device path), ``_info``, ``_controls`` and
``_render_extras``.  :class:`ABDEnv` turns a task into a single-world ``gymnasium.Env``.
"""
from __future__ import annotations

import ctypes
import math
import types
from typing import Any

import gymnasium as gym
import numpy as np
import warp as wp
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from . import env_kernels
from .autoreset import NextEpisodes
from .scene import REVOLUTE, Scene
from .simulator import Simulator

__all__ = ["ABDVectorEnv", "ABDEnv", "AutoresetMode"]

BACKENDS = ("numpy", "torch")
RANDOMIZE_KEYS = ("mass_scale", "strength_ratio", "limit_scale", "limit_strength_scale")
MAX_DEFAULT_RENDER_WORLDS = 16


def _is_torch(x) -> bool:
    return type(x).__module__.startswith("torch")


def _to_numpy(x) -> np.ndarray:
    if _is_torch(x):
        return x.detach().cpu().numpy()
    return np.asarray(x)


def _insert_child_graph(device, raw) -> bool:
    """Add the CUDA graph ``raw`` (a cudaGraph_t) as a child node of the capture under way on the
    device's current stream, by the call Warp's own capture_if makes for a Graph branch (internal
    to Warp: False where this Warp lacks it or it fails)."""
    try:
        from warp._src.context import runtime

        insert = runtime.core.wp_cuda_graph_insert_child_graph
    except (ImportError, AttributeError):
        return False
    return bool(insert(device.context, device.stream.cuda_stream, ctypes.c_void_p(raw)))


def _own_code(method):
    """The bound ``method`` on a copy of its function's code object.  torch.compile keeps a
    function's compiled versions on its code object, which every env (every task, every size)
    would share, up to ``torch._dynamo.config.recompile_limit`` (8), after which new ones run
    uncompiled: on an H100 a later env of one bench process, FourBar-v0 at 1,024 envs after the
    cart-pole's and Reacher's, fell back to its eager outcome (0.71 of its physics against 0.95
    with its own copy)."""
    f = method.__func__
    g = types.FunctionType(f.__code__.replace(), f.__globals__, f.__name__, f.__defaults__, f.__closure__)
    return types.MethodType(g, method.__self__)


def _can_compile() -> bool:
    """Whether torch.compile can make GPU kernels here (Inductor's Triton backend)."""
    try:
        from torch.utils._triton import has_triton

        return bool(has_triton())
    except ImportError:
        return False


def _autoreset_mode(mode) -> AutoresetMode:
    if isinstance(mode, AutoresetMode):
        return mode
    for m in AutoresetMode:
        if str(mode) in (m.value, m.name):
            return m
    raise ValueError(f"autoreset_mode must be one of {[m.name for m in AutoresetMode]}, got {mode!r}")


def _range(name, value):
    lo, hi = (float(v) for v in value)
    if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
        raise ValueError(f"randomize[{name!r}] must be a (low, high) pair with low <= high, got {value!r}")
    return lo, hi


class ABDVectorEnv(VectorEnv):
    """Batched task base (see the module docstring for the API)."""

    metadata: dict[str, Any] = {"render_modes": ["rgb_array"], "render_fps": 50,
                                "autoreset_mode": AutoresetMode.NEXT_STEP}  # fmt: skip

    # ---- what a task sets
    dt: float = 0.02  # simulator time step [s]
    frame_skip: int = 1  # simulator steps per env step
    reset_option_keys: tuple = ()  # task-specific reset options (besides reset_mask and randomize)
    # per-episode task values that each new episode draws (``_draw_task``): (attribute, width)
    # pairs.  The env keeps them in one float32 array (N, total width) whose columns the
    # attributes view ((N,) for width 1, else (N, width)), so that an autoreset on the device
    # writes them with the episode's initial state (autoreset.py)
    task_state: tuple = ()
    # rendering: plane of the view ("xz": x right, z up; "xy": x right, y up), centre [m], width [m]
    render_plane: str = "xz"
    render_center: tuple = (0.0, 0.0)
    render_width: float = 2.0
    render_size: tuple = (480, 360)  # (width, height) [px]
    velocity_bound: float = 100.0  # bound of velocity entries of observations [rad/s or m/s]

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        cls.metadata = dict(cls.metadata, render_fps=int(round(1.0 / (cls.dt * cls.frame_skip))))

    def __init__(self, num_envs: int = 1, *, device=None, backend: str = "numpy",
                 autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP, max_episode_steps: int | None = None,
                 render_mode: str | None = None, render_worlds=None, randomize: dict | None = None,
                 dtype: str = "float32", integrator: str | None = None, graph: bool | None = None,
                 compile_outcome: bool | None = None, simulator_options: dict | None = None):  # fmt: skip
        if not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        if backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']} or None, got {render_mode!r}")
        if max_episode_steps is not None and int(max_episode_steps) < 1:
            raise ValueError(f"max_episode_steps must be a positive integer or None, got {max_episode_steps!r}")
        self.autoreset_mode = _autoreset_mode(autoreset_mode)
        self.metadata = dict(type(self).metadata, autoreset_mode=self.autoreset_mode)
        self.num_envs = N = int(num_envs)
        self.backend = backend
        self.render_mode = render_mode
        self.max_episode_steps = None if max_episode_steps is None else int(max_episode_steps)

        self.scene: Scene = self.build_scene()
        extra = {} if integrator is None else {"integrator": integrator}  # None: the simulator's default
        options = dict(simulator_options or {})
        fixed = {"scene", "num_worlds", "dt", "device", "dtype", "integrator"} & set(options)
        if fixed:
            raise ValueError(f"simulator_options may not set {sorted(fixed)}: the task sets dt and the number of "
                             "worlds; device, dtype and integrator are arguments of the env")  # fmt: skip
        self.sim = Simulator(self.scene, num_worlds=N, dt=self.dt, device=device, dtype=dtype, **extra, **options)
        self.device = self.sim.device
        self.step_dt = self.dt * self.frame_skip  # env step [s]
        if backend == "torch":
            import torch

            self.xp = torch
            self._torch_device = torch.device(wp.device_to_torch(self.device))
        else:
            self.xp = np
            self._torch_device = None

        # ---- spaces
        nd = len(self.scene.drives)
        self.single_action_space = spaces.Box(-1.0, 1.0, shape=(self.action_dim,), dtype=np.float32)
        high = np.asarray(self.observation_high(), dtype=np.float32)
        if not np.all(np.isfinite(high)) or np.any(high <= 0):
            raise ValueError(f"observation bounds must be positive and finite, got {high}")
        self.single_observation_space = spaces.Box(-high, high, dtype=np.float32)
        self._obs_high = self._asarray(high)
        self._obs_low = -self._obs_high  # kept: negating it in each step is a launch
        self.action_space = batch_space(self.single_action_space, N)
        self.observation_space = batch_space(self.single_observation_space, N)
        self._max_effort = np.array([d.max_effort for d in self.scene.drives], dtype=np.float32)
        if nd and not np.all(np.isfinite(self._max_effort)):
            raise ValueError("every drive of a task needs a finite max_effort (actions are scaled by it)")
        self._effort = self._asarray(self._max_effort) if nd else None

        # ---- per-world bookkeeping
        self._elapsed = self._zeros(N, dtype="int")  # env steps in the current episode
        for name, width in self.task_state:
            if not (isinstance(name, str) and name.isidentifier() and isinstance(width, (int, np.integer)) and width >= 1):
                raise ValueError(f"task_state entries must be (attribute name, positive int width), got {(name, width)!r}")
        self._task_width = sum(int(w) for _, w in self.task_state)
        self._task = self._zeros(N, self._task_width)  # the task_state values, views of its columns
        col = 0
        for name, width in self.task_state:
            setattr(self, name, self._task[:, col] if width == 1 else self._task[:, col : col + width])
            col += width
        # all-False flags made once: building them each step was a host-to-device copy (on a GPU, a
        # copy from pageable memory, which waits for the stream) in every step of every task
        # without terminations
        self._no_flags = self._zeros(N, dtype="bool")
        self._pending = np.zeros(N, dtype=bool)  # NEXT_STEP: worlds to reset at the next step
        self._pinned = None  # GPU: (pinned host flags' slots, event) the next pending mask comes through
        self._pinned_slot = 2  # the slot of those flags that the event's step writes
        self._pending_in_flight = False
        self._has_reset = False
        # NEXT_STEP autoresets on the device (autoreset.py), for tasks whose episodes start from
        # _initial_state and _draw_task alone (no _reset_task of their own); not while parameters
        # are randomised
        own_reset = type(self)._reset_task is not ABDVectorEnv._reset_task
        self._next = None
        if self.autoreset_mode == AutoresetMode.NEXT_STEP and not own_reset:
            self._next = NextEpisodes(self.sim, self._draw_episodes, task_width=self._task_width,
                                      host_task=backend == "numpy")  # fmt: skip
        self._next_rng = None  # the generator of the next episodes' draws (spawned at each full reset)
        cuda_torch = backend == "torch" and self.device.is_cuda
        if graph and not (cuda_torch and self._next is not None):
            raise ValueError("graph=True needs the Torch backend on a CUDA device and NEXT_STEP autoresets of a task "
                             "without _reset_task")  # fmt: skip
        self._use_graph = cuda_torch and self._next is not None if graph is None else bool(graph)
        self._graph = None  # ((pre, physics graphs, post graphs), post outputs, mailed): _capture
        self._device_warm = False
        # the step graph runs the autoreset beside the physics, which then holds the pending worlds
        # (_physics): where the step is one launch, its kernel is built with that check
        if self._use_graph:
            self.sim.solver.enable_hold()
        # the step graph checks its actions for NaN on the device (a refused batch steps nothing,
        # and the next call raises): a host check would make the host wait for the device each step
        self._check_on_device = self._use_graph and wp.is_conditional_graph_supported()
        # the task's observation, reward and termination (a dozen one-line Torch operations, each a
        # kernel of the step graph) compiled by torch.compile into a few fused kernels; by default
        # with the step graph only (the compile takes seconds; op by op the host's launches, not
        # the device's kernels, are what a step waits for)
        if compile_outcome and backend != "torch":
            raise ValueError("compile_outcome=True needs the Torch backend")
        self._compile_outcome = self._use_graph and _can_compile() if compile_outcome is None else bool(compile_outcome)
        self._outcome_fn = None
        self._go = None  # device int32 flag: 1 steps, 0 refuses (sticky until the host reads why)
        self._unread = False  # a step checked on the device whose verdict the host has not read
        self._refused = np.zeros(0, dtype=np.int64)  # the worlds with NaN actions in the last such step
        self._undo = None  # that step's host bookkeeping before it: (clock, rows taken, pending mask)
        self._replay_stream = None  # Warp's handle of the Torch stream the step graphs are replayed on
        self._stream_id = self._torch_stream = None  # that stream's id and Torch object
        self._post_graphs = []  # the Torch graphs nested in the step graphs (kept: their memory)
        self._slot = 0  # the step graph (and mailbox and host flags slot) replayed next
        self._side_stream = None  # the step graph's second stream (the autoreset beside the physics)
        self._mailed = None  # the action batch the last step graph reads (kept until it has)

        # ---- per-world physical parameters (host copies of what the simulator holds)
        scene = self.scene
        self._free_bodies = [k for k, b in enumerate(scene.bodies) if not b.fixed]
        self._nominal_mass = np.array([b.mass for b in scene.bodies])
        self._nominal_ratio = np.array([j.strength_ratio for j in scene.joints])
        self._limited = [k for k, j in enumerate(scene.joints) if j.has_limit]
        self.body_mass = np.broadcast_to(self._nominal_mass, (N, scene.num_bodies)).copy()
        self.strength_ratio = np.broadcast_to(self._nominal_ratio, (N, scene.num_joints)).copy()
        # limits[joint index]: (N, 3) lower, upper, strength of each limited joint
        attrs = ("limit/lower", "limit/upper", "limit/strength")
        self.limits = {k: np.broadcast_to([scene.joints[k].attributes[a] for a in attrs], (N, 3)).copy()
                       for k in self._limited}  # fmt: skip
        self._randomize = None
        self._randomized = False
        self._set_randomize(randomize)

        # ---- rendering
        if render_worlds is None:
            render_worlds = range(min(N, MAX_DEFAULT_RENDER_WORLDS))
        elif isinstance(render_worlds, (int, np.integer)):
            render_worlds = range(min(N, int(render_worlds)))
        self.render_worlds = [int(w) for w in render_worlds]
        if any(not 0 <= w < N for w in self.render_worlds):
            raise ValueError(f"render_worlds must index worlds in [0, {N}), got {self.render_worlds}")
        self._renderer = None

    # ================================================================== task interface
    def build_scene(self) -> Scene:
        """The task's mechanism in its zero pose."""
        raise NotImplementedError

    def observation_high(self) -> np.ndarray:
        """Upper bounds of one observation (the space is symmetric: low = -high; finite: observations
        are clipped to them, so choose bounds the task does not reach, ``velocity_bound`` for rates)."""
        raise NotImplementedError

    @property
    def action_dim(self) -> int:
        return len(self.scene.drives)

    def _controls(self, actions):
        """Drive inputs (N, num_drives) from clipped actions (N, action_dim): a × max_effort."""
        return actions * self._effort

    def _observe(self):
        raise NotImplementedError

    def _reward(self, obs, actions):
        raise NotImplementedError

    def _terminated(self, obs):
        return self._no_flags  # read only: step combines it into a new array

    def _initial_state(self, n: int, rng: np.random.Generator, options: dict):
        """Joint coordinates and velocities (n, num_joints) of n fresh episodes (host NumPy)."""
        nj = self.scene.num_joints
        return np.zeros((n, nj)), np.zeros((n, nj))

    def _draw_task(self, n: int, rng: np.random.Generator, options: dict) -> dict:
        """The ``task_state`` values of n new episodes: {attribute: (n,) or (n, width) host array}."""
        return {}

    def _reset_task(self, idx: np.ndarray, rng: np.random.Generator, options: dict):
        """Task state of the worlds ``idx`` for a new episode: by default the ``task_state`` values
        ``_draw_task`` draws.  A task that overrides this resets on the host (no autoresets on the
        device, no step graph)."""
        if self._task_width:
            self._put(self._task, idx, self._task_matrix(self._draw_task(len(idx), rng, options), len(idx)))

    def _task_matrix(self, values: dict, n: int) -> np.ndarray:
        """``_draw_task``'s values as one (n, total width) array, columns in ``task_state`` order."""
        missing = [name for name, _ in self.task_state if name not in values]
        if missing or len(values) != len(self.task_state):
            raise ValueError(f"_draw_task must return exactly the task_state values {[k for k, _ in self.task_state]}, "
                             f"got {sorted(values)}")  # fmt: skip
        return np.concatenate([np.asarray(values[name], dtype=np.float64).reshape(n, int(w))
                               for name, w in self.task_state], axis=1)  # fmt: skip

    def _draw_episodes(self, n: int):
        """n next episodes for the autoreset queues (autoreset.py), from the generator spawned at
        the last full reset: initial coordinates, rates and (with ``task_state``) task values."""
        x, xd = self._initial_state(n, self._next_rng, {})
        if not self._task_width:
            return x, xd
        return x, xd, self._task_matrix(self._draw_task(n, self._next_rng, {}), n)

    def _info(self, obs) -> dict:
        """Per-step info: a dict of batched arrays (each gets an all-True ``"_key"`` mask)."""
        return {}

    def _render_extras(self, canvas, world: int):
        """Draw task-specific marks (targets, end stops) on a render canvas, over the bodies."""

    # ================================================================== array helpers
    def _asarray(self, values, dtype="float"):
        """Host values as a backend array (on the simulator's device for torch)."""
        if self.xp is np:
            return np.asarray(values, dtype={"float": np.float32, "int": np.int64, "bool": bool}[dtype])
        import torch

        dt = {"float": torch.float32, "int": torch.int64, "bool": torch.bool}[dtype]
        return torch.as_tensor(np.asarray(values), dtype=dt, device=self._torch_device)

    def _zeros(self, *shape, dtype="float"):
        return self._asarray(np.zeros(shape), dtype)

    def _upload(self, values: np.ndarray):
        """Host values as a tensor on the env's device.  To a GPU through pinned memory and a
        non-blocking copy: a copy from pageable memory makes the host wait for the device's queue
        (the step's physics), which is what a reset in every step would then cost."""
        t = self.xp.from_numpy(np.ascontiguousarray(values))
        if self._torch_device.type == "cuda":
            return t.pin_memory().to(self._torch_device, non_blocking=True)
        return t

    def _index(self, idx: np.ndarray):
        return idx if self.xp is np else self._upload(np.asarray(idx, dtype=np.int64))

    def _fill(self, array, idx, value):
        """array[idx] = value (a Python scalar).  Torch's ``index_fill_``: ``t[i] = 0.0`` makes a
        host tensor of the scalar and copies it, which waits for the device."""
        if self.xp is np:
            array[idx] = value
        else:
            array.index_fill_(0, idx, value)

    def _put(self, array, idx: np.ndarray, values):
        """array[idx] = values (host values into a backend array of the same dtype)."""
        if self.xp is np:
            array[idx] = values
        else:
            array[self._index(idx)] = self._upload(np.asarray(values)).to(array.dtype)

    def _false(self):
        """A new all-False flag array (N,)."""
        return self._no_flags.copy() if self.xp is np else self._no_flags.clone()

    def _f32(self, x):
        return x.astype(np.float32, copy=False) if self.xp is np else x.to(self.xp.float32)

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
        return self._f32(self._elapsed) * self.step_dt

    def _failed(self):
        if self.xp is np:
            mask = np.zeros(self.num_envs, dtype=bool)
            mask[self.sim.failed_worlds()] = True
            return mask
        return self.sim._out(self.sim.state.status, "torch") != 0

    # ================================================================== actions
    def _prepare_actions(self, actions, check: bool = True):
        """The action batch as a clipped float32 backend array (N, action_dim); with ``check``, a
        batch with NaN raises here (which, for a Torch tensor on a GPU, waits for the device)."""
        N, d = self.num_envs, self.action_dim
        xp = self.xp
        if xp is np:
            a = np.array(_to_numpy(actions), dtype=np.float32)
        else:
            a = actions if _is_torch(actions) else xp.as_tensor(np.asarray(actions, dtype=np.float32))
            a = a.to(device=self._torch_device, dtype=xp.float32)
        if tuple(a.shape) != (N, d):
            if a.ndim == 1 and d == 1 and a.shape[0] == N:
                a = a.reshape(N, 1)
            else:
                raise ValueError(f"actions must have shape ({N}, {d}), got {tuple(a.shape)}")
        if not check:
            return a  # checked and clipped on the device
        nan = xp.isnan(a)
        if bool(nan.any()):
            worlds = np.flatnonzero(_to_numpy(nan).any(axis=1))
            raise ValueError(f"actions contain NaN in worlds {worlds.tolist()[:10]}; nothing was stepped "
                             "(replace or mask NaN actions before calling step)")  # fmt: skip
        return xp.clip(a, -1.0, 1.0)

    # ================================================================== reset
    def _set_randomize(self, spec):
        if spec is None or spec == {}:
            self._randomize = None
            return
        if not isinstance(spec, dict):
            raise ValueError(f"randomize must be a dict or None, got {spec!r}")
        unknown = set(spec) - set(RANDOMIZE_KEYS)
        if unknown:
            raise ValueError(f"unknown randomize keys {sorted(unknown)}; known: {list(RANDOMIZE_KEYS)}")
        scene, out = self.scene, {}
        for key, value in spec.items():
            if key == "mass_scale":
                names = self._free_bodies
                to_index = scene.body_index
            elif key == "strength_ratio":
                names = list(range(scene.num_joints))
                to_index = scene.joint_index
            else:
                names = self._limited
                to_index = scene.joint_index
            if isinstance(value, dict):
                ranges = {}
                for name, r in value.items():
                    k = to_index(name)
                    if k not in names:
                        raise ValueError(f"randomize[{key!r}]: {name!r} cannot be randomised (fixed body or no limit)")
                    ranges[k] = _range(key, r)
            else:
                r = _range(key, value)
                ranges = {k: r for k in names}
            if key != "limit_scale" and any(lo <= 0 for lo, _ in ranges.values()):
                raise ValueError(f"randomize[{key!r}] ranges must be positive, got {value!r}")
            out[key] = ranges
        self._randomize = out

    def _apply_parameters(self, idx: np.ndarray, rng: np.random.Generator):
        """Draw (or restore) the physical parameters of the worlds ``idx``."""
        spec = self._randomize
        if spec is None and not self._randomized:
            return
        self._randomized = True
        spec = spec or {}
        n, sim, scene = len(idx), self.sim, self.scene

        def draw(key, k, nominal):
            r = spec.get(key, {}).get(k)
            return np.full(n, nominal) if r is None else rng.uniform(r[0], r[1], size=n)

        free = self._free_bodies
        mass = np.stack([self._nominal_mass[k] * draw("mass_scale", k, 1.0) for k in free], axis=1)
        self.body_mass[np.ix_(idx, free)] = mass
        sim.set_body_mass(mass, bodies=free, worlds=idx)
        if scene.num_joints:
            ratio = np.stack([draw("strength_ratio", k, r) for k, r in enumerate(self._nominal_ratio)], axis=1)
            self.strength_ratio[idx] = ratio
            sim.set_joint_strength(ratio, worlds=idx)
        for k in self._limited:
            j = scene.joints[k]
            lo, up, st = (j.attributes[f"limit/{a}"] for a in ("lower", "upper", "strength"))
            f = draw("limit_scale", k, 1.0)
            lo_k, up_k = np.minimum(lo * f, up * f), np.maximum(lo * f, up * f)
            if j.kind == REVOLUTE:
                lo_k, up_k = np.clip(lo_k, -math.pi, math.pi), np.clip(up_k, -math.pi, math.pi)
            st_k = st * draw("limit_strength_scale", k, 1.0)
            self.limits[k][idx] = np.stack([lo_k, up_k, st_k], axis=1)
            sim.set_limit(k, lower=lo_k, upper=up_k, strength=st_k, worlds=idx)

    def _reset_worlds(self, idx: np.ndarray, options: dict | None = None):
        """Reset the worlds idx; returns idx as a backend index array (uploaded once, for the
        caller's own fills)."""
        options = options or {}
        rng = self.np_random
        self._apply_parameters(idx, rng)
        coords, vels = self._initial_state(len(idx), rng, options)
        self.sim.set_joint_state(coords, vels, worlds=idx)
        idx_b = self._index(idx)
        self._fill(self._elapsed, idx_b, 0)  # no value array
        self._reset_task(idx, rng, options)
        self._pending_now()[idx] = False
        return idx_b

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Reset every world, or those in ``options["reset_mask"]``; returns ``(obs, info)``.

        ``options``: ``reset_mask`` (bool array (num_envs,)), ``randomize`` (see the module
        docstring) and the task's own keys (``reset_option_keys``).
        """
        if self._unread:
            self._pending_now()  # raises, having taken it back, if the device refused the last step
        super().reset(seed=seed)
        options = dict(options or {})
        mask = options.pop("reset_mask", None)
        if "randomize" in options:
            self._set_randomize(options.pop("randomize"))
        unknown = set(options) - set(self.reset_option_keys)
        if unknown:
            raise ValueError(f"unknown reset options {sorted(unknown)}; this task takes "
                             f"{['reset_mask', 'randomize', *self.reset_option_keys]}")  # fmt: skip
        if mask is None:
            idx = np.arange(self.num_envs)
        else:
            mask = _to_numpy(mask)
            if mask.dtype != np.bool_ or mask.shape != (self.num_envs,):
                raise ValueError(f"options['reset_mask'] must be a bool array of shape ({self.num_envs},), "
                                 f"got {mask.dtype} {mask.shape}")  # fmt: skip
            idx = np.flatnonzero(mask)
        if len(idx):
            self._reset_worlds(idx, options)
            if self._next is not None:
                self._next.clear(idx)
                if mask is None:
                    # every world's next episodes: the same seed gives the same resets in every mode
                    self._restart_next_episodes()
        self._has_reset = True
        return self._observe_safe(), {}

    # ================================================================== step
    def _observe_safe(self):
        """The task's observation as float32, clipped to the observation space."""
        obs = self._f32(self._observe())
        return self.xp.clip(obs, self._obs_low, self._obs_high)

    @staticmethod
    def _batch_info(values: dict, mask: np.ndarray) -> dict:
        """Gymnasium's vector info layout: each per-world array ``key`` with a bool mask ``_key``."""
        info = {}
        for key, v in values.items():
            info[key] = v
            info["_" + key] = mask.copy()
        return info

    def _restart_next_episodes(self):
        """Fresh autoreset queues from a generator spawned from np_random (which a spawn does not
        advance: explicit resets draw what they would without autoresets)."""
        self._next_rng = np.random.Generator(self.np_random.bit_generator.spawn(1)[0])
        self._next.restart()

    def _pending_now(self) -> np.ndarray:
        """NEXT_STEP: the worlds that ended in the last step (host bool mask).  On a GPU the mask of
        the last step arrives by an asynchronous copy; this waits for that copy only, which the
        stream finishes before the physics step launched after it."""
        if self._pending_in_flight:
            host, event = self._pinned
            event.synchronize()
            rows = host[self._pinned_slot]
            self._pending = rows[0].copy()
            if self._unread and rows[1].any():
                self._refused = np.flatnonzero(rows[1])
            self._pending_in_flight = False
        if self._unread:  # the verdict of a step checked on the device
            self._unread = False
            if len(self._refused):
                self._take_back()
        return self._pending

    def _defer_pending(self, flags, checked: bool = False, slot: int | None = None):
        """Keep the done mask ``flags`` (with ``checked``, the rows done and bad: the worlds whose NaN
        actions made the device refuse the step) as the next step's pending mask without waiting for
        the device: a non-blocking copy to pinned host memory and an event the next step waits on
        after it has launched its physics (so the host's work on this step's results overlaps the
        device's work on the next one).  ``slot``: the step graph of that slot writes both rows to
        the pinned memory itself (``flags`` unused); the copy goes to slot 2, which no graph writes
        (the first graph step is queued before the host reads the copy of the step before it)."""
        if self.xp is np or self._torch_device.type != "cuda":
            rows = _to_numpy(flags)
            self._pending = (rows[0] if checked else rows).copy()
            if checked:
                self._refused = np.flatnonzero(rows[1])
            return
        self._host_buffers()
        event = self._pinned[1]
        if slot is None:
            slot = 2
            rows = self._host_flags_t[slot]
            (rows if checked else rows[0]).copy_(flags, non_blocking=True)
        event.record(self._torch_stream)  # (None: the current stream, which record looks up)
        self._pinned_slot = slot
        self._pending_in_flight = True

    def _host_buffers(self):
        """The page-locked host memory a GPU step talks to the host through, made once (Torch's
        pinned tensors, each with a NumPy view and a Warp array on the GPU over the same memory:
        under CUDA's unified addressing a kernel reads and writes page-locked host memory by its
        host pointer): the flags' slots (3, 2, N), rows done and bad of a step, slots 0 and 1 written
        by the step graphs (env_kernels' mailed finish_step), slot 2 by a copy; and the mailbox
        (2, 2) of the graphs' slots: the device pointers of the actions and of the fresh outputs."""
        if self._pinned is not None:
            return
        import torch

        N, dev = self.num_envs, self.device
        flags = torch.zeros((3, 2, N), dtype=torch.bool, pin_memory=True)
        mail = torch.zeros((2, 2), dtype=torch.int64, pin_memory=True)
        self._pinned = (flags.numpy(), torch.cuda.Event())
        self._host_flags_t = flags
        self._mail_np = mail.numpy().view(np.uint64)
        self._mail_t = mail  # (the owner of the memory the mailbox views alias)
        self._host_flags_dev = wp.array(ptr=flags.data_ptr(), dtype=wp.bool, shape=tuple(flags.shape), device=dev)
        self._mail_dev = wp.array(ptr=mail.data_ptr(), dtype=wp.uint64, shape=tuple(mail.shape), device=dev)

    def step(self, actions):
        if not self._has_reset:
            raise RuntimeError("call reset() before step()")
        xp, N = self.xp, self.num_envs
        on_device = self._next is not None and self._randomize is None and not self._randomized
        if self._unread and not on_device:
            self._pending_now()  # the verdict of the last step, checked on the device, before this one
        a = self._prepare_actions(actions, check=not (on_device and self._check_on_device))
        if on_device:
            if self._next_rng is None:  # no full reset yet (only masked ones): the queues start now
                self._restart_next_episodes()
            return self._step_on_device(a)

        self.sim.set_controls(self._controls(a))
        self.sim.step(self.frame_skip)  # on a GPU: queued; the host goes on while it runs
        self._elapsed += 1
        # NEXT_STEP: the worlds that ended last step; this step only resets them (read after the
        # physics launch: on a GPU that read waits for the last step's flags, not for this step)
        pending = np.flatnonzero(self._pending_now()) if self.autoreset_mode == AutoresetMode.NEXT_STEP else np.zeros(0, int)
        pend = None
        has_info = np.ones(N, dtype=bool)  # worlds whose info entries are this step's (not a reset's)
        if len(pending):
            pend = self._false()
            self._fill(pend, self._reset_worlds(pending), True)
            has_info[pending] = False
        obs, reward, terminated, truncated, failed, info_values = self._outcome(a, pend)
        info_values = dict(info_values, sim_failed=failed)
        if self.autoreset_mode == AutoresetMode.SAME_STEP:
            done = _to_numpy(terminated | truncated)  # the host resets now: it waits for the step here
            if done.any():
                # as SyncVectorEnv: the finished episode's last obs and info under final_obs /
                # final_info, the new episode's first obs in obs (and its reset info, empty here, at
                # the top level)
                final_info = self._batch_info(info_values, done)
                final_obs = obs
                self._reset_worlds(np.flatnonzero(done))
                obs = self._observe_safe()
                info = self._batch_info(info_values, has_info & ~done)
                info.update(final_obs=final_obs, _final_obs=done.copy(), final_info=final_info,
                            _final_info=done.copy())  # fmt: skip
                return obs, reward, terminated, truncated, info
        elif self.autoreset_mode == AutoresetMode.NEXT_STEP:
            self._defer_pending(terminated | truncated)
            if self._next is not None:  # kept for a later step on the device path
                self._next.set_pending(terminated | truncated)
        return obs, reward, terminated, truncated, self._batch_info(info_values, has_info)

    def _outcome(self, a, pend=None):
        """Observation, reward, flags, failures and info values of the step just taken with the
        clipped actions ``a``; ``pend``: a backend bool mask of the worlds reset in this step
        (reward 0, neither flag), or None.  A broken world gets a zero observation and reward and is
        terminated (by mask, for every world: asking the device whether any world failed would make
        the host wait for it)."""
        xp = self.xp
        obs = self._observe_safe()
        failed = self._failed() | ~xp.isfinite(obs).all(axis=1)
        reward = self._f32(self._reward(obs, a))
        terminated = self._terminated(obs) | failed
        if self.max_episode_steps is not None:
            truncated = self._elapsed >= self.max_episode_steps
        else:
            truncated = self._false()
        info_values = self._info(obs)
        zero = failed
        if pend is not None:
            terminated, truncated, zero = terminated & ~pend, truncated & ~pend, failed | pend
        reward = xp.where(zero, 0.0, reward)
        obs = xp.where(failed[:, None], 0.0, obs)
        return obs, reward, terminated, truncated, failed, info_values

    # ================================================================== step with autoresets on the device
    def _device_buffers(self):
        """The Torch device path's arrays, made once (Torch tensors and Warp views of them): the go
        flag, the flag of any pending autoreset, and the step's outputs packed in one byte buffer:
        observations and rewards (float32, the observations' rows then the rewards), then the flags'
        rows terminated, truncated, failed, done and bad (a NaN action)."""
        if self._go is not None:
            return
        torch = self.xp
        N, d = self.num_envs, self.single_observation_space.shape[0]
        dev = self._torch_device
        self._go = wp.ones(1, dtype=wp.int32, device=self.device)
        self._go_t = wp.to_torch(self._go)
        # one buffer (float32 words: the observations' and rewards' type; the flags' bytes after them),
        # so that one clone of its head copies the observations, rewards and the three flags returned
        self._out_raw = torch.zeros(-(-(4 * N * (d + 1) + 5 * N) // 4), dtype=torch.float32, device=dev)
        self._out_head = -(-(4 * N * (d + 1) + 3 * N) // 4)
        obs, reward = self._unpack(self._out_raw, 0)
        F = 4 * N * (d + 1)
        self._out_b = self._out_raw.view(torch.uint8)[F: F + 5 * N].view(torch.bool).view(5, N)
        self._wp = dict(effort=wp.from_torch(self._effort), obs=wp.from_torch(obs), reward=wp.from_torch(reward),
                        flags=wp.from_torch(self._out_b), bad=wp.from_torch(self._out_b[4]),
                        elapsed=wp.from_torch(self._elapsed),
                        task=wp.from_torch(self._task) if self._task_width else None)  # fmt: skip

    def _unpack(self, raw, rows: int = 3):
        """Views of the packed outputs ``raw`` (float32 words, the buffer or a copy of its head, at
        storage offset 0): observations (N, d), rewards (N,), then the first ``rows`` flag rows
        (terminated, truncated, failed, done, bad: bytes after the rewards), each (N,).  Built by
        as_strided, one Torch call a view: slicing and retyping took 11 calls, ~15 µs of host time a
        step on the H100's host at 1,024 envs."""
        torch = self.xp
        N, d = self.num_envs, self.single_observation_space.shape[0]
        F = 4 * N * (d + 1)
        flags = raw.view(torch.bool) if rows else None
        return (raw.as_strided((N, d), (d, 1)), raw.as_strided((N,), (1,), N * d),
                *(flags.as_strided((N,), (1,), F + k * N) for k in range(rows)))  # fmt: skip

    def _pre(self, a, checked: bool, slot: int | None = None):
        """The controls of the actions ``a``.  ``checked`` (on the device; ``a`` not yet clipped, and
        clipped in place, NaN as 0): each world's NaN flag, and the go flag cleared by any of them
        (and left cleared, refusing every later step, until the host has read why: ``_take_back``).
        The controls are set either way: a refused batch's (NaN as 0) stay in the simulator's
        control array, an input that the next step sets again, not a world's state.  ``slot`` (a
        step graph's, checked): the actions are read from the batch mailed in that slot and
        clipped into ``a``."""
        if not checked:
            self.sim.set_controls(self._controls(a))
            return
        scaled = type(self)._controls is ABDVectorEnv._controls
        k = self._wp
        mailed = slot is not None
        wp.launch(env_kernels.check_actions(self.sim.model.dtype, scaled, mailed), dim=self.num_envs,
                  inputs=[wp.from_torch(a), k["effort"], k["bad"], self._go, self.sim.state.control,
                          self._mail_dev if mailed else None, slot or 0],
                  device=self.device)  # fmt: skip
        if not scaled:
            self.sim.set_controls(self._controls(a))

    def _physics(self, capturing: bool, checked: bool):
        """The simulator's step, then the autoreset of last step's ended worlds (autoreset.py);
        ``checked``: only where the go flag is set (a conditional node of the step graph, which the
        device decides).  Captured where the step can hold worlds: both at once (below)."""
        sim = self.sim
        if capturing and self.xp is not np and sim.solver.holds:
            # the physics and the autoreset at once, on two streams of the graph: the step holds the
            # pending worlds (it neither reads nor writes their rows) while the autoreset restarts
            # them, and both leave a refused batch (go cleared) alone themselves, with no
            # conditional node (on an H100 the node cost ~8 µs a step, and the autoreset's two
            # launches ~19 µs, at 1,024 CartPole-v0 worlds' ~100 µs physics)
            go = self._go if checked else None
            if self._side_stream is None:
                raise RuntimeError("the step's side stream is made before its capture (_capture)")
            with wp.ScopedStream(self._side_stream):  # waits for the stream's work so far (the check)
                self._next.apply(self._wp["elapsed"], self._wp["task"], go=go)
            sim.launch_step(self.frame_skip, hold=self._next.pending, go=go)
            wp.get_stream(self.device).wait_stream(self._side_stream)
            return

        def run():
            if capturing:
                sim.launch_step(self.frame_skip)  # the env's graph holds the step; the clock ticks at replay
            else:
                sim.step(self.frame_skip)
            # the autoreset: two launches for every world (no condition on whether any world is
            # pending: in a graph a conditional node cost more than the launches it spared), the
            # first of which ticks the episode clocks with Torch; with NumPy the host keeps the
            # clocks and, on the CPU, skips the launches when its mask has no pending world
            if self.xp is not np:
                self._next.apply(self._wp["elapsed"], self._wp["task"])
            elif capturing or not self.device.is_cpu or self._next.mask(np).any():
                self._next.apply()

        if checked:
            wp.capture_if(self._go, on_true=run)
        else:
            run()

    def _post(self, a, slot: int | None = None):
        """Observation, reward and flags of the step, those of the worlds reset in it replaced as in
        ``step`` (reward 0, both flags False), the ended worlds marked for the next step.  With
        Torch, in env_kernels' launch after the task's own operations (a step the device refused
        changes no pending mask), into the packed outputs; returns (the
        outputs, info values, the flags' rows done and bad).  ``slot`` (a step graph's): the
        outputs go to the buffer mailed in that slot and the rows done and bad to its pinned host
        flags (the packed outputs are not written)."""
        xp = self.xp
        if xp is np:
            pend = self._next.mask(xp)
            self._elapsed += 1
            self._elapsed[pend] = 0
            if self._task_width and pend.any():  # the rows the device's worlds took (host_task)
                self._task[pend] = self._next.task_rows(pend)
            obs, reward, terminated, truncated, failed, info_values = self._outcome(a, pend)
            done = terminated | truncated
            self._next.set_pending(done)
            return (obs, reward, terminated, truncated, failed), info_values, done
        k, dev, N = self._wp, self.device, self.num_envs
        pending = self._next.pending
        if self._outcome_fn is None:
            import torch

            fn = self._task_outcome
            self._outcome_fn = torch.compile(_own_code(fn), dynamic=False) if self._compile_outcome else fn
        obs, reward, term, info_values = self._outcome_fn(a)
        steps = -1 if self.max_episode_steps is None else self.max_episode_steps
        mailed = slot is not None
        wp.launch(env_kernels.finish_step(mailed), dim=N,
                  inputs=[wp.from_torch(obs), wp.from_torch(reward), wp.from_torch(term),
                          self.sim.state.status, self._go, pending, k["elapsed"], steps, k["obs"], k["reward"],
                          k["flags"], self._mail_dev if mailed else None, slot or 0,
                          self._host_flags_dev if mailed else None], device=dev)  # fmt: skip
        return self._unpack(self._out_raw), info_values, self._out_b[3:5]

    def _task_outcome(self, a):
        """The task's observation (float32, clipped to the space), reward (float32), termination and
        info values after a step with the clipped actions ``a`` (Torch; what torch.compile fuses)."""
        obs = self._observe_safe()
        reward = self._f32(self._reward(obs, a)).contiguous()
        return obs, reward, self._terminated(obs).contiguous(), self._info(obs)

    def _device_step(self, a):
        """One env step as device work only (no host reads, no host-dependent branches on a GPU), so
        that CUDA graphs can hold it: controls, physics with the autoreset, outcome."""
        checked = self._check_on_device
        self._pre(a, checked)
        self._physics(False, checked)
        return self._post(a)

    def _torch_graph(self, fn, keep: bool = False):
        """A CUDA graph of ``fn()`` and its outputs: Torch's capture on a side stream, Warp's launches
        on the same stream (told the capture is external).  ``keep``: the graph keeps its CUDA graph
        (``raw_cuda_graph``), for nesting in another, and is instantiated only if replayed."""
        import torch

        dev = self._torch_device
        graph = torch.cuda.CUDAGraph(keep_graph=True) if keep else torch.cuda.CUDAGraph()
        stream = torch.cuda.Stream(device=dev)
        stream.wait_stream(torch.cuda.current_stream(dev))
        ws = wp.stream_from_torch(stream)
        with torch.cuda.graph(graph, stream=stream, capture_error_mode="thread_local"):
            with wp.ScopedStream(ws, sync_enter=False):
                wp.capture_begin(stream=ws, external=True)
                try:
                    outputs = fn()
                finally:
                    wp.capture_end(stream=ws)
        torch.cuda.current_stream(dev).wait_stream(stream)
        return graph, outputs

    def _capture(self):
        """The step as graphs, two of them (slots 0 and 1, replayed in turn), each: the physics
        (Warp's own capture: its conditional node on the go flag must not end a Torch capture, whose
        allocations are tied to the capture's id) and, nested in it as a child graph, the Torch
        graph of what follows it (captured first), so that a step is one graph launch; where this
        Torch or Warp cannot nest it, that graph is replayed after the physics'.  A graph finds the
        caller's actions and its fresh outputs by pointers mailed in its slot, and writes its done
        and bad rows to its slot of pinned host memory (env_kernels): the host reads step t's rows
        while step t + 1 runs, which therefore writes elsewhere.  Returns
        ((pre graph or None, the slots' physics graphs, their post graphs where not nested), the
        slots' post outputs, whether the actions are mailed)."""
        import torch

        self._host_buffers()
        self._action_buf = torch.zeros((self.num_envs, self.action_dim), dtype=torch.float32, device=self._torch_device)
        checked = self._check_on_device
        # the check (one Warp launch, with the default controls) heads the physics' graph and reads
        # the mailed actions: one graph launch and one copy less; Torch operations (a task's own
        # controls, the host-checked path's copy) need Torch's capture, on the actions' copy
        warp_only = checked and type(self)._controls is ABDVectorEnv._controls
        pre = None
        if not warp_only:
            pre, _ = self._torch_graph(lambda: self._pre(self._action_buf, checked))
        # the mailed kernels, which no launched step has run, loaded before the capture (a module
        # load is no graph node)
        mailed = [env_kernels.finish_step(True)]
        if warp_only:
            mailed.append(env_kernels.check_actions(self.sim.model.dtype, True, True))
        for kernel in mailed:
            kernel.module.load(self.device)
        physics, posts, outputs = [], [], []
        if self.sim.solver.holds and self._side_stream is None:
            self._side_stream = wp.Stream(self.device)
        for slot in (0, 1):
            try:
                post, out = self._torch_graph(lambda: self._post(self._action_buf, slot), keep=True)
                raw = post.raw_cuda_graph()
            except (TypeError, AttributeError, RuntimeError):  # a Torch without keep_graph / raw_cuda_graph
                post, out = self._torch_graph(lambda: self._post(self._action_buf, slot))
                raw = None
            with wp.ScopedCapture(device=self.device, force_module_load=False) as capture:
                if warp_only:
                    self._pre(self._action_buf, checked, slot)
                self._physics(True, checked)
                nested = raw is not None and _insert_child_graph(self.device, raw)
            if raw is not None and not nested:
                post.instantiate()
            # the nested graph's memory (Torch's pool) lives as long as its Torch graph: kept
            self._post_graphs.append(post)
            physics.append(capture.graph)
            posts.append(None if nested else post)
            outputs.append(out)
        return (pre, physics, posts), outputs, warp_only

    def _replay(self, a):
        """The next slot's step graph replayed on Torch's current stream with the actions ``a``;
        returns (the step's fresh packed outputs, that slot's post outputs, the slot)."""
        import torch

        (pre, physics, posts), outputs, mailed = self._graph
        slot = self._slot
        self._slot ^= 1
        # the current stream's id by Torch's own query: torch.cuda.current_stream() builds a Stream
        # and resolves the device each call, which a step's host time notices
        sid = torch._C._cuda_getCurrentStream(self._torch_device.index or 0)[0]
        if self._replay_stream is None or self._stream_id != sid:
            ts = torch.cuda.current_stream(self._torch_device)
            self._replay_stream, self._stream_id, self._torch_stream = wp.stream_from_torch(ts), sid, ts
        # the outputs' buffer: fresh from Torch's allocator each step (stream-ordered, as a clone's
        # would be), which the caller keeps
        raw = torch.empty(self._out_head, dtype=torch.float32, device=self._torch_device)
        mail = self._mail_np[slot]
        mail[1] = raw.data_ptr()
        if mailed:
            # read by the graph's first kernel: the batch must live until then (kept one call)
            a = a.contiguous()
            mail[0] = a.data_ptr()
            self._mailed = a
        else:
            self._action_buf.copy_(a)
        if pre is not None:
            pre.replay()
        wp.capture_launch(physics[slot], stream=self._replay_stream)
        if posts[slot] is not None:
            posts[slot].replay()
        return raw, outputs[slot], slot

    def _step_on_device(self, a):
        """``step`` with NEXT_STEP autoresets on the device: on a GPU with Torch, graph replays (after one
        step of plain launches, which loads every kernel), else the same work launched.  With the
        check on the device, the host learns a call late whether a step ran, and keeps what it needs
        to take its bookkeeping of a refused one back (``_take_back``)."""
        checked = self._check_on_device
        if self.xp is not np:
            self._device_buffers()
        if checked:
            before = (self.sim.state.time.copy(), self._next._taken.copy())
        replayed = self._use_graph and self._device_warm
        slot = None
        if replayed:
            if self._graph is None:
                self._graph = self._capture()
            raw, (_, info_values, flags), slot = self._replay(a)
            out = self._unpack(raw)
        else:
            if checked:
                a = a.clone()  # clipped in place by the check
            out, info_values, flags = self._device_step(a)
            self._device_warm = True
            if self.xp is not np:
                # the step's outputs are rewritten by the next step: the caller gets its own copies
                # (one clone of the packed bytes)
                out = self._unpack(self._out_raw[: self._out_head].clone())
        if self.xp is not np:
            info_values = {k: v.clone() for k, v in info_values.items()}
        obs, reward, terminated, truncated, failed = out
        # the worlds the device just reset (last step's ended ones, known on the host now): their
        # info is a reset's (none), their clock restarts, they took a row of their queues; this
        # read raises if the device refused the last step
        # (whole-mask NumPy operations: a few calls a step, each cheaper on 1,024 worlds than the
        # index list and fancy indexing they replace)
        mask = self._pending_now()
        if replayed:
            self.sim.tick(self.frame_skip)
        if checked:
            self._undo = before + (mask.copy(),)
        has_info = ~mask
        if mask.any():
            self.sim.state.time[mask] = 0.0
            self._next.took(mask)
            mask[...] = False  # (self._pending: none left pending)
        if not checked and flags.ndim == 2:
            flags = flags[0]  # the done row
        self._defer_pending(flags, checked, slot)
        self._unread = checked
        info_values = dict(info_values, sim_failed=failed)
        return obs, reward, terminated, truncated, self._batch_info(info_values, has_info)

    def _take_back(self):
        """The device refused the last step (NaN actions) and every step since: the host's
        bookkeeping of that step is taken back (clocks, queue rows, pending mask), the go flag set
        again, and the refusal raised."""
        clock, taken, pending = self._undo
        self.sim.state.time[...] = clock
        self._next._taken[...] = taken
        self._pending = pending
        self._go.fill_(1)
        worlds, self._refused = self._refused, np.zeros(0, dtype=np.int64)
        raise ValueError(f"the actions of the last step contained NaN in worlds {worlds.tolist()[:10]}; no world "
                         "was stepped by that call or this one (on the device the check reports a call late; replace "
                         "or mask NaN actions before calling step)")  # fmt: skip

    # ================================================================== render / close
    def render(self):
        """One uint8 (H, W, 3) frame per world in ``render_worlds`` (a tuple), or None without a render mode."""
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; create the env with render_mode='rgb_array'")
            return None
        from .render import Renderer

        if self._renderer is None:
            self._renderer = Renderer(self.scene, plane=self.render_plane, center=self.render_center,
                                      width=self.render_width, size=self.render_size)  # fmt: skip
        pos, rot = self.sim.body_positions(), self.sim.body_rotations()
        frames = []
        for w in self.render_worlds:
            canvas = self._renderer.canvas()
            self._renderer.draw_bodies(canvas, pos[w], rot[w])
            self._render_extras(canvas, w)
            frames.append(canvas.image)
        return tuple(frames)

    def close_extras(self, **kwargs):
        self._renderer = None


class ABDEnv(gym.Env):
    """A task as a single-world ``gymnasium.Env`` (CPU by default): its vector env with one world,
    autoreset disabled and no internal time limit (``gym.make`` adds ``TimeLimit``).

    Same conventions as the vector env: actions clipped to the action space, a NaN action raises
    ``ValueError`` without stepping, ``reset(seed=...)`` seeds the initial-state draws,
    ``reset(options={"randomize": ...})`` randomises the physical parameters; ``env.sim`` is the
    simulator and ``env.vector_env`` the one-world batched env.
    """

    vector_class: type[ABDVectorEnv] = ABDVectorEnv
    metadata = {"render_modes": ["rgb_array"], "render_fps": 50}

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        cls.metadata = {"render_modes": ["rgb_array"], "render_fps": cls.vector_class.metadata["render_fps"]}

    def __init__(self, render_mode: str | None = None, device="cpu", **kwargs):
        self.vector_env = self.vector_class(num_envs=1, device=device, backend="numpy",
                                            autoreset_mode=AutoresetMode.DISABLED, max_episode_steps=None,
                                            render_mode=render_mode, **kwargs)  # fmt: skip
        self.observation_space = self.vector_env.single_observation_space
        self.action_space = self.vector_env.single_action_space
        self.render_mode = render_mode

    @property
    def sim(self) -> Simulator:
        return self.vector_env.sim

    @staticmethod
    def _unbatch(info: dict) -> dict:
        out = {}
        for key, value in info.items():
            if key.startswith("_"):
                continue
            if isinstance(value, dict):
                out[key] = ABDEnv._unbatch(value)
            else:
                v = np.asarray(value)[0]
                out[key] = v.item() if v.ndim == 0 else v
        return out

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self.vector_env._np_random = self.np_random  # one generator: seeding this env seeds its world
        obs, info = self.vector_env.reset(options=options)
        return obs[0], self._unbatch(info)

    def step(self, action):
        a = np.asarray(action, dtype=np.float32).reshape(1, -1)
        obs, reward, terminated, truncated, info = self.vector_env.step(a)
        return obs[0], float(reward[0]), bool(terminated[0]), bool(truncated[0]), self._unbatch(info)

    def render(self):
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; create the env with render_mode='rgb_array'")
            return None
        return self.vector_env.render()[0]

    def close(self):
        self.vector_env.close()
