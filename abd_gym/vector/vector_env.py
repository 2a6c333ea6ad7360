"""Native batched Gymnasium environments: ``num_envs`` worlds of one task in one ``Simulator``.

:class:`ABDVectorEnv` is a ``gymnasium.vector.VectorEnv`` (not N single envs behind a loop): one
scene stepped in ``num_envs`` worlds, batched observation / reward / termination arrays computed
from the simulator's arrays in one go, and the Gymnasium 1.x vector API on top:

* spaces: ``single_observation_space`` / ``single_action_space`` (``Box``, float32) and their
  batched versions ``observation_space`` / ``action_space`` (leading ``num_envs`` axis).  Actions
  are normalised to ``[-1, 1]`` per drive (``[-b, b]`` for a task's ``action_bound`` b) and
  scaled by the drive's ``max_effort`` / b.
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
  episodes start from ``initial_state`` and its ``task_state`` values (``draw_task``: a
  Reacher's target) alone (no ``reset_task`` of its own) and while no parameters are
  randomised, each world's next initial states and task values are drawn ahead into a queue on
  the device
  (:mod:`abd_gym.vector.autoreset`; from a generator spawned from ``np_random`` at each full reset, so
  the same seed gives the same episodes on every backend and device) and the autoreset is device
  work only.  With the Torch backend on a GPU the whole step (action check, controls, physics,
  autoreset, observation, reward, flags) is then captured once as one CUDA graph (the Warp part,
  with the Torch graph of what follows nested in it as a child graph) and replayed, two such
  graphs in turn.  Where the simulator's step is one launch (``Solver.holds``: the lane-split
  step, by default up to ~4,000 worlds), the physics and the autoreset run at once on two streams
  of the graph: the step holds (does not touch) the worlds whose autoreset restarts them, and
  both skip a refused batch themselves; elsewhere they run in turn inside a conditional node on
  the check's go flag.  The graph reads the
  caller's action batch and writes the step's outputs to a fresh buffer (the caller's to keep) by
  pointers the host leaves in page-locked memory, and writes the done mask there for the host,
  so a step is one graph launch and no copy.  The env's own bookkeeping runs there as a few Warp kernels
  (:mod:`abd_gym.vector.kernels`) after the task's Torch code, which torch.compile fuses into a few
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
  the batch raises before anything is stepped.  A world whose step was rejected
  (``Simulator.failed_worlds``, or a non-finite observation) is terminated, reported in
  ``info["sim_failed"]`` (a bool per world, in every step's info) with the simulator's cause in
  ``info["sim_status"]`` (an int32 ``abd_gym.WorldStatus`` code per world) and gets a zero
  observation and reward; the autoreset (or your masked reset) brings it back.  A step that
  failed is first taken again as 2, then 4 substeps (``Simulator.substeps``; not in a GPU's
  device step): ``info["sim_substeps"]`` (int32 per world) is the substeps of the env step's last
  physics step.  So is one that gained energy in a conservative world (no drive pushing:
  ``Simulator(energy_gain=...)``, here by default at large steps only:
  ``conditioning.task_energy_gain``; ``simulator_options`` to set it);
  ``info["sim_energy_gained"]`` (bool per world) marks a last physics step that still gained at 4
  substeps and was kept.
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
  else the first 16), drawn headless by :mod:`abd_gym.vector.render`.

Simulator options: ``device`` ("cpu", "cuda:0"; default ``$ABD_GYM_DEVICE`` or "cpu"), ``dtype``
("float32" or "float64") and ``integrator`` (the simulator's default, BDF2, unless given);
the tasks' rewards and thresholds are calibrated with the defaults.  ``simulator_options``: more
Simulator keyword arguments, e.g. ``{"tol": 1e-4}``, or ``{"plan": {"scratch": "global"}}`` (an
``ExecutionPlan`` or a dict of its fields: how the step runs on the device); an unknown name or a
bad value is the Simulator's error.

A task subclasses :class:`ABDVectorEnv` and fills in its hooks (listed, with shapes and units, in
the class docstring; docs/custom_task.md walks through a new task from scene to training).
:class:`ABDEnv` turns a task into a single-world ``gymnasium.Env``.
"""
from __future__ import annotations

import copy
from typing import Any, NamedTuple

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv

from .autoreset import NextEpisodes
from .device_step import DeviceStep
from .arrays import BACKENDS, Backend, to_numpy
from .spaces import autoreset_mode as autoreset_mode_of, make_spaces, prepare_actions
from .episodes import Episodes
from .outcome import batch_info, outcome
from .pending import PendingMask
from .randomize import RANDOMIZE_KEYS, Parameters  # noqa: F401 (RANDOMIZE_KEYS: the randomize option's keys)
from ..sim import conditioning, inputs
from ..sim.simulator import Simulator
from .single_env import ABDEnv  # noqa: F401 (re-exported: a task module imports both classes from here)
from .task import Task

__all__ = ["ABDVectorEnv", "ABDEnv", "AutoresetMode"]

MAX_DEFAULT_RENDER_WORLDS = 16


class _Reset(NamedTuple):
    """What a reset writes into its worlds, drawn and checked (ABDVectorEnv._draw_reset):
    Parameters.draw's values (None: none), the initial joint coordinates and rates (n, joints),
    the task values (n, task width; None: none, or the task's own reset_task draws them)."""

    params: dict | None
    coordinates: np.ndarray
    velocities: np.ndarray
    task: np.ndarray | None


def _render_worlds(render_worlds, num_envs: int) -> list:
    """The worlds ``render()`` draws: default every world up to MAX_DEFAULT_RENDER_WORLDS, an int
    the first that many, else the indices given."""
    if render_worlds is None:
        render_worlds = range(min(num_envs, MAX_DEFAULT_RENDER_WORLDS))
    elif isinstance(render_worlds, (int, np.integer)):
        render_worlds = range(min(num_envs, int(render_worlds)))
    worlds = [int(w) for w in render_worlds]
    if any(not 0 <= w < num_envs for w in worlds):
        raise ValueError(f"render_worlds must index worlds in [0, {num_envs}), got {worlds}")
    return worlds


class ABDVectorEnv(Task, VectorEnv):
    """Batched task base: a task is a subclass that fills in the hooks below (the module docstring
    describes the env API they serve).  N is ``num_envs``; "backend array" means a NumPy array, or
    a Torch tensor on the simulator's device with ``backend="torch"`` (write hooks with ``self.xp``,
    ``numpy`` or ``torch``, and both work); coordinates are radians for revolute joints and metres
    for sliders, rates rad/s or m/s.

    Class attributes: ``dt`` (simulator step [s]), ``frame_skip`` (simulator steps per env step),
    ``action_bound`` (actions lie in [−b, b], 1 by default),
    ``task_state`` ((attribute, width) pairs of per-episode task values, see ``draw_task``),
    ``reset_option_keys`` (the task's own ``reset(options=...)`` keys), ``velocity_bound``
    (observation bound for rates) and ``render_plane`` / ``render_center`` / ``render_width`` /
    ``render_size``.  A task's own constructor arguments are attributes set before
    ``super().__init__(num_envs, **kwargs)``, which calls ``build_scene``.

    Hooks (required first):

    * ``build_scene() -> Scene``: the mechanism in its zero pose (bodies [kg, m], joints, limits,
      drives, each drive with a finite ``max_effort`` [N or N·m]).
    * ``observation_high() -> (obs_dim,)``: positive finite bounds of one observation; the space is
      ``Box(-high, high)`` (float32) and observations are clipped to it.
    * ``observe() -> (N, obs_dim)``: the observation of every world (backend array).
    * ``reward(obs, actions) -> (N,)``: the reward of the step that led to ``obs`` (N, obs_dim),
      with the clipped actions (N, action_dim) in [-1, 1] (``[-b, b]`` for ``action_bound`` b).
    * ``terminated(obs) -> (N,) bool``: default never (failed worlds are terminated by the env).
    * ``action_dim`` (property): default one action per drive of the scene.
    * ``controls(actions) -> (N, num_drives)``: drive inputs from clipped actions; default
      ``actions * max_effort / action_bound`` (efforts [N or N·m]); override it when
      ``action_dim`` differs.
    * ``initial_state(n, rng, options) -> (coordinates, rates)``: host NumPy arrays (n, num_joints)
      of n fresh episodes drawn from ``rng`` (``options``: the reset options); default all zero.
    * ``draw_task(n, rng, options) -> {attribute: (n,) or (n, width)}``: the ``task_state`` values
      of n new episodes (host NumPy; e.g. a target [m]).  The env keeps them in backend arrays
      named by the attributes ((N,) for width 1, else (N, width)); they are drawn ahead on the
      device's autoreset path too.
    * ``reset_task(idx, rng, options)``: task state of the worlds ``idx`` (host int array) at a
      reset; default: write ``draw_task``'s values.  A task that overrides it resets on the host;
      its ``reset_task`` runs after the reset has written the worlds (it reads their new state),
      and where it raises, the reset's writes are put back before the exception goes on (in an
      autoreset within ``step``, whose physics has then run: the worlds have moved).
    * ``info(obs) -> {key: (N,) array}``: per-step info values; default none.
    * ``world_observation(q, v)``, ``world_reward(obs, action)``, ``world_terminated(obs)``:
      optional, all three or none: one world's observe / reward / terminated in plain Python
      floats, which the single env's CPU step calls instead (``Task``; the same values).
    * ``render_extras(canvas, world)``: marks (targets, end stops) drawn over the bodies.

    What hooks read: ``coords()`` / ``velocities()`` (N, num_joints) joint coordinates and rates,
    ``unwrapped_coords()`` (multi-turn angles [rad]), ``body_positions()`` (N, num_bodies, 3) [m],
    ``body_rotations()`` (N, num_bodies, 3, 3), ``episode_time()`` (N,) [s], ``max_effort``
    (num_drives,) [N or N·m], ``xp`` (``numpy`` or ``torch``), ``num_envs``, ``step_dt`` [s] and
    the array helpers ``asarray(values, dtype)``, ``zeros(*shape, dtype)``, ``put(array, idx,
    values)`` and ``f32(x)`` (dtype "float" float32, "int" int64, "bool").
    """

    metadata: dict[str, Any] = {"render_modes": ["rgb_array"], "render_fps": 50,
                                "autoreset_mode": AutoresetMode.NEXT_STEP}  # fmt: skip

    # ---- what a task sets
    dt: float = 0.02  # simulator time step [s]
    frame_skip: int = 1  # simulator steps per env step
    reset_option_keys: tuple = ()  # task-specific reset options (besides reset_mask and randomize)
    # per-episode task values that each new episode draws (``draw_task``): (attribute, width)
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
        self._check_arguments(num_envs, backend, render_mode, max_episode_steps)
        self.autoreset_mode = autoreset_mode_of(autoreset_mode)
        self.metadata = dict(type(self).metadata, autoreset_mode=self.autoreset_mode)
        self.num_envs = N = int(num_envs)
        self.backend = backend
        self.render_mode = render_mode
        self.max_episode_steps = None if max_episode_steps is None else int(max_episode_steps)

        self.scene = self.build_scene()
        extra = {} if integrator is None else {"integrator": integrator}  # None: the simulator's default
        options = dict(simulator_options or {})
        fixed = {"scene", "num_worlds", "dt", "device", "dtype", "integrator"} & set(options)
        if fixed:
            raise ValueError(f"simulator_options may not set {sorted(fixed)}: the task sets dt and the number of "
                             "worlds; device, dtype and integrator are arguments of the env")  # fmt: skip
        # the energy test only at large steps: under a policy every drive pushes, and the test never runs
        options.setdefault("energy_gain", conditioning.task_energy_gain(self.scene, self.dt))
        self.sim = Simulator(self.scene, num_worlds=N, dt=self.dt, device=device, dtype=dtype, **extra, **options)
        self.device = self.sim.device
        self.step_dt = self.dt * self.frame_skip  # env step [s]
        self.arrays = Backend(backend, self.device)  # the backend's array helpers
        self.xp = self.arrays.xp

        # ---- spaces
        (self.single_action_space, self.single_observation_space,
         self.action_space, self.observation_space) = make_spaces(self.action_dim, self.observation_high(), N,
                                                                     self.action_bound)
        self._init_task_arrays(self.single_observation_space.high)
        # the controls hook is the default (actions × action_scale), which the device's check applies
        self.default_controls = type(self).controls is ABDVectorEnv.controls

        # ---- per-world bookkeeping: episode clocks and task values, the pending autoresets
        self.episodes = Episodes(self.arrays, N, self.task_state)
        for name, view in self.episodes.task_views().items():
            setattr(self, name, view)
        self.pending = PendingMask(N, backend == "torch" and self.device.is_cuda)
        self._has_reset = False
        self._next_rng = None  # the generator of the next episodes' draws (spawned at each full reset)
        # NEXT_STEP autoresets on the device (autoreset.py), for tasks whose episodes start from
        # initial_state and draw_task alone (no reset_task of their own); not while parameters
        # are randomised
        own_reset = type(self).reset_task is not ABDVectorEnv.reset_task
        self.next_episodes = None
        if self.autoreset_mode == AutoresetMode.NEXT_STEP and not own_reset:
            self.next_episodes = NextEpisodes(self.sim, self._draw_episodes, task_width=self.episodes.task_width,
                                              host_task=backend == "numpy",
                                              generator=lambda: self._next_rng)  # fmt: skip
        self.device_step = DeviceStep(self, graph, compile_outcome)

        # ---- per-world physical parameters (host copies of what the simulator holds)
        self.parameters = Parameters(self.scene, self.sim)
        self.parameters.set_spec(randomize)

        # ---- rendering
        self.render_worlds = _render_worlds(render_worlds, N)
        self._renderer = None

    def _check_arguments(self, num_envs, backend, render_mode, max_episode_steps):
        inputs.count("num_envs", num_envs, minimum=1)
        if backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']} or None, got {render_mode!r}")
        if max_episode_steps is not None:
            inputs.count("max_episode_steps", max_episode_steps, minimum=1)

    # ---- the per-world physical parameters in force (host arrays; randomize.Parameters)
    @property
    def body_mass(self) -> np.ndarray:
        """(N, num_bodies) body masses [kg]."""
        return self.parameters.body_mass

    @property
    def strength_ratio(self) -> np.ndarray:
        """(N, num_joints) joint strength ratios."""
        return self.parameters.strength_ratio

    @property
    def limits(self) -> dict:
        """{limited joint index: (N, 3) lower, upper [rad or m], strength [J]}."""
        return self.parameters.limits

    # ================================================================== pickle / deepcopy
    def __new__(cls, *args, **kwargs):
        env = super().__new__(cls)
        env._init_args = (args, kwargs)  # what a copy is rebuilt from (__getstate__)
        return env

    def __getstate__(self):
        """The constructor arguments (the device as resolved) and the env's state (``_snapshot``):
        a copy is built anew from them (a fresh simulator, kernels from Warp's cache) and then
        steps as this env does, bit for bit.  Device-side machinery (captured graphs, pinned
        buffers, compiled outcome) is rebuilt on use: on a GPU with Torch the copy's first steps
        run before its step graph is captured, with the task's outcome eager where this env's is
        compiled, so observations and rewards may then differ from this env's by float32 rounding
        (the physics does not)."""
        args, kwargs = self._init_args
        return {"args": args, "kwargs": dict(kwargs, device=str(self.device)), "snapshot": self._snapshot()}

    def __setstate__(self, state):
        self._init_args = (state["args"], state["kwargs"])
        self.__init__(*state["args"], **state["kwargs"])
        self._restore(state["snapshot"])

    def get_state(self) -> dict:
        """The whole env's state as host values: the simulator's (Simulator.get_state), each
        world's episode clock and task values (``task_state``), the parameters in force, the
        autoreset queues, the pending resets and copies of the random generators.  ``set_state``
        puts it back into this env (or another built with the same arguments), which then steps
        as this one did from here, bit for bit."""
        return copy.deepcopy(self._snapshot())

    def set_state(self, state: dict):
        """Restore ``get_state``'s values (see there; the state can be restored again later).  The
        simulator's part is checked as Simulator.set_state checks it; where it is refused the env
        is left as it was."""
        keys = {"sim", "episodes", "parameters", "pending", "rng", "has_reset"}
        if self.next_episodes is not None:
            keys.add("queue")
        if not isinstance(state, dict) or set(state) != keys:
            raise ValueError(f"state must be a dict from this env's get_state, with entries {sorted(keys)}")
        if self.pending.unread or self.pending.in_flight:
            self._pending_now()
        state = copy.deepcopy(state)
        self._check_snapshot(state)  # every part, before any is written
        self._restore(state)

    def _check_snapshot(self, snap: dict):
        """Refuse (TypeError or ValueError, naming the entry) a snapshot that ``_restore`` could not
        restore whole: each part of this env's shapes, the simulator's state as Simulator.set_state
        checks it against the snapshot's limits."""
        self.parameters.check_snapshot(snap["parameters"])
        W = self.num_envs
        mine = self._snapshot_shapes()
        for part in ("episodes", "queue"):
            if part not in snap:
                continue
            if not isinstance(snap[part], dict) or set(snap[part]) != set(mine[part]):
                raise ValueError(f"state[{part!r}] must hold this env's entries {sorted(mine[part])}")
            for name, (shape, dtype) in mine[part].items():
                v = snap[part][name]
                if not isinstance(v, np.ndarray) or v.shape != shape or v.dtype != dtype:
                    raise ValueError(f"state[{part!r}][{name!r}] must be {dtype} of shape {shape}, got "
                                     f"{getattr(v, 'dtype', type(v).__name__)} {getattr(v, 'shape', '')}")  # fmt: skip
        pend = snap["pending"]
        if not (isinstance(pend, np.ndarray) and pend.dtype == np.bool_ and pend.shape == (W,)):
            raise ValueError(f"state['pending'] must be a bool array of shape ({W},)")
        rng = snap["rng"]
        if not (isinstance(rng, tuple) and len(rng) == 3
                and all(g is None or isinstance(g, np.random.Generator) for g in (rng[0], rng[2]))):  # fmt: skip
            raise ValueError("state['rng'] must be get_state's (generator, seed, generator) tuple")
        limits = {k: (v[:, 0], v[:, 1]) for k, v in snap["parameters"]["limits"].items()}
        self.sim.check_state(snap["sim"], limits=limits)

    def _snapshot_shapes(self) -> dict:
        """{part: {entry: (shape, dtype)}} of this env's snapshot's array parts."""
        ep = self.episodes.snapshot()
        out = {"episodes": {k: (v.shape, v.dtype) for k, v in ep.items()}}
        if self.next_episodes is not None:
            out["queue"] = {k: (v.shape, v.dtype) for k, v in self.next_episodes.snapshot().items()}
        return out

    def _snapshot(self) -> dict:
        """Host values of the simulator's state, the episodes, the parameters in force, the
        autoreset queues, the pending mask and the random generators."""
        if self.pending.unread or self.pending.in_flight:
            self._pending_now()  # the last GPU step's done mask on the host (raises if it refused NaN actions)
        snap = {"sim": self.sim.get_state(), "episodes": self.episodes.snapshot(),
                "parameters": self.parameters.snapshot(), "pending": self.pending.mask,
                "rng": (self._np_random, self._np_random_seed, self._next_rng),
                "has_reset": self._has_reset}  # fmt: skip
        if self.next_episodes is not None:
            snap["queue"] = self.next_episodes.snapshot()
        return snap

    def _restore(self, snap: dict):
        """``_snapshot``'s values put back into this env, built with the same arguments."""
        self.parameters.restore(snap["parameters"])  # the limits in force, against which the state is checked
        self.sim.set_state(snap["sim"])
        self.episodes.restore(snap["episodes"])
        self.pending.mask = snap["pending"]
        self._np_random, self._np_random_seed, self._next_rng = snap["rng"]
        self._has_reset = snap["has_reset"]
        if "queue" in snap:
            self.next_episodes.restore(snap["queue"])

    # ================================================================== reset
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Reset every world, or those in ``options["reset_mask"]``; returns ``(obs, info)``.

        ``options``: ``reset_mask`` (bool array (num_envs,)), ``randomize`` (see the module
        docstring) and the task's own keys (``reset_option_keys``).
        """
        if self.pending.unread:
            self._pending_now()  # raises, having taken it back, if the device refused the last step
        seed = inputs.seed(seed)
        options = dict(options or {})
        mask = options.pop("reset_mask", None)
        unknown = set(options) - set(self.reset_option_keys) - {"randomize"}
        if unknown:
            raise ValueError(f"unknown reset options {sorted(unknown)}; this task takes "
                             f"{['reset_mask', 'randomize', *self.reset_option_keys]}")  # fmt: skip
        if mask is None:
            idx = np.arange(self.num_envs)
        else:
            mask = to_numpy(mask)
            if mask.dtype != np.bool_ or mask.shape != (self.num_envs,):
                raise ValueError(f"options['reset_mask'] must be a bool array of shape ({self.num_envs},), "
                                 f"got {mask.dtype} {mask.shape}")  # fmt: skip
            idx = np.flatnonzero(mask)
        # a refused reset leaves the env as it was: the spec, the generator and every world
        spec, rng = self.parameters.spec, self._rng_state()
        try:
            if "randomize" in options:
                self.parameters.set_spec(options.pop("randomize"))
            super().reset(seed=seed)
            # everything the reset writes, drawn and checked before any of it is written: the
            # worlds' parameters, states and task values, and after a full reset every world's
            # next episodes (against the limits the reset writes)
            drawn = self._draw_reset(idx, options) if len(idx) else None
            queues = None
            if mask is None and self.next_episodes is not None:
                limits = None if drawn is None or drawn.params is None else \
                    {k: v[:2] for k, v in drawn.params["limits"].items()}
                queues = self._draw_next_episodes(limits)
            if drawn is not None:  # (set_joint_state, its first write, checks a state no parameter was drawn for)
                self._write_reset(idx, drawn, options)
        except Exception:  # a refusal, or a task's own reset_task raising (_write_reset undid its writes)
            self.parameters.spec = spec
            self._set_rng_state(rng)
            raise
        if len(idx) and self.next_episodes is not None:
            self.next_episodes.clear(idx)
        if queues is not None:
            # every world's next episodes: the same seed gives the same resets in every mode
            self._restart_next_episodes(queues)
        self._has_reset = True
        return self.observation(), {}

    def _reset_worlds(self, idx: np.ndarray, options: dict | None = None):
        """Reset the worlds idx; returns idx as a backend index array (uploaded once, for the
        caller's own fills)."""
        options = options or {}
        return self._write_reset(idx, self._draw_reset(idx, options), options)

    def _draw_reset(self, idx: np.ndarray, options: dict) -> _Reset:
        """Everything a reset of the worlds idx writes, drawn and checked (in the generator's
        order: the parameters, the state, the task values), written nowhere: a refusal raises
        having written nothing (the generator is the caller's to put back).  Where no parameter
        is drawn, the state is checked by ``_write_reset``'s first write, set_joint_state."""
        rng = self.np_random
        params = self.parameters.draw(idx, rng)
        self.parameters.check(idx, params)
        coords, vels = self.initial_state(len(idx), rng, options)
        if params is not None:  # against the limits the reset writes (else set_joint_state checks first)
            limits = {k: v[:2] for k, v in params["limits"].items()}
            coords, vels = self.sim.check_joint_state(coords, vels, worlds=idx, limits=limits)
        task = None
        if self._default_task_reset and self.episodes.task_width:
            task = self.task_values(len(idx), rng, options)
            if not np.all(np.isfinite(task)):
                raise ValueError(f"the task's initial task values must be finite, got {task}")
        return _Reset(params, coords, vels, task)

    def _write_reset(self, idx: np.ndarray, drawn: _Reset, options: dict):
        """``_draw_reset``'s values into the worlds idx; returns idx as a backend index array.
        A task's own ``reset_task`` runs last (it may read the state just written) and may raise:
        what the reset wrote is then put back (``_undo_reset``) before the exception goes on."""
        saved = None if self._default_task_reset else self._reset_undo(idx, drawn)
        self.parameters.write(idx, drawn.params)
        self.sim.set_joint_state(drawn.coordinates, drawn.velocities, worlds=idx)
        idx_b = self.arrays.index(idx)
        self.arrays.fill(self.episodes.elapsed, idx_b, 0)  # no value array
        if drawn.task is not None:
            self.put(self.episodes.task, idx, drawn.task)
        elif saved is not None:
            try:
                self.reset_task(idx, self.np_random, options)
            except Exception:
                self._undo_reset(idx, saved)
                raise
        self._pending_now()[idx] = False
        return idx_b

    def _reset_undo(self, idx: np.ndarray, drawn: _Reset):
        """What a reset of the worlds idx overwrites, as host copies: the parameters in force
        (None where the reset draws none), the worlds' simulator state, the episodes' clocks and
        task values."""
        params = None if drawn.params is None else self.parameters.snapshot()
        return params, self.sim.get_state(idx), self.episodes.snapshot()

    def _undo_reset(self, idx: np.ndarray, saved):
        """``_reset_undo``'s values written back, bit for bit (the parameters first: the state is
        checked against the limits they hold).  A task's own attributes outside ``task_state``
        are its own to keep."""
        params, state, episodes = saved
        if params is not None:
            self.parameters.restore(params)
        self.sim.set_state(state, worlds=idx)
        self.episodes.restore(episodes)

    @property
    def _default_task_reset(self) -> bool:
        """Whether the task's state is drawn by Task.reset_task (task_values), not a reset_task of its own."""
        return type(self).reset_task is Task.reset_task

    def _rng_state(self):
        """The env's generators as they are (``_set_rng_state`` puts them back)."""
        gen = self._np_random
        return gen, self._np_random_seed, None if gen is None else gen.bit_generator.state  # (a new dict)

    def _set_rng_state(self, saved):
        gen, seed, state = saved
        self._np_random, self._np_random_seed = gen, seed
        if gen is not None:
            gen.bit_generator.state = state

    def _draw_next_episodes(self, limits: dict | None = None):
        """(the generator, its rows): every world's next episodes for fresh autoreset queues, drawn
        and checked (NextEpisodes.draw_rows; ``limits``: a reset's, written after) from the
        generator that np_random's next spawn gives, which is not spawned yet: a refusal leaves
        np_random's spawns as they were (a spawn does not advance its draws either: explicit resets
        draw what they would without autoresets)."""
        seq = self.np_random.bit_generator.seed_seq
        # the child SeedSequence.spawn(1) makes next (its entropy, the spawn key extended by the count)
        child = np.random.SeedSequence(seq.entropy, spawn_key=(*seq.spawn_key, seq.n_children_spawned),
                                       pool_size=seq.pool_size)  # fmt: skip
        gen = np.random.Generator(type(self.np_random.bit_generator)(child))
        return gen, self.next_episodes.draw_rows(gen, fresh=True, limits=limits)

    def _restart_next_episodes(self, drawn):
        """Fresh autoreset queues from ``_draw_next_episodes``' (generator, rows), whose spawn from
        np_random is counted now."""
        self.np_random.bit_generator.spawn(1)
        self._next_rng, rows = drawn
        self.next_episodes.restart(rows)

    def _draw_episodes(self, n: int, rng: np.random.Generator):
        """n next episodes for the autoreset queues (autoreset.py), from ``rng`` (the generator
        spawned at the last full reset): initial coordinates, rates and (with ``task_state``) task
        values."""
        x, xd = self.initial_state(n, rng, {})
        if not self.episodes.task_width:
            return x, xd
        return x, xd, self.task_values(n, rng, {})

    def fixed_outputs(self):
        """Views (obs, reward, terminated, truncated) of one buffer that every later ``step`` on the
        device (NEXT_STEP autoresets with the Torch backend; :mod:`abd_gym.vector.device_step`) writes its
        outputs into and returns, instead of fresh tensors each step (its info values are then not
        copied either); None where this env's steps do not run there.  For a caller that reads
        each step's outputs before it calls ``step`` again (a training rollout on the same CUDA
        stream): it saves a copy of each output a step.
        A caller that keeps outputs across steps must copy them."""
        if self.next_episodes is None or self.xp is np:
            return None
        return self.device_step.fixed_outputs()

    def _pending_now(self) -> np.ndarray:
        """NEXT_STEP: the worlds that ended in the last step (host bool mask; pending.py), after the
        verdict of a step checked on the device (raises if the device refused it)."""
        return self.device_step.pending_now()

    # ================================================================== step
    def step(self, actions):
        """One env step of every world: ``(obs, reward, terminated, truncated, info)`` (module docstring)."""
        if not self._has_reset:
            raise RuntimeError("call reset() before step()")
        # autoresets on the device (device_step.py) while nothing needs the host's resets
        on_device = self.next_episodes is not None and not self.parameters.active
        if self.pending.unread and not on_device:
            self._pending_now()  # the verdict of the last step, checked on the device, before this one
        check = not (on_device and self.device_step.check_on_device)
        a = prepare_actions(actions, self.arrays, self.num_envs, self.action_dim, check, self.action_bound)
        if on_device:
            if self._next_rng is None:  # no full reset yet (only masked ones): the queues start now
                self._restart_next_episodes(self._draw_next_episodes())
            else:  # the rows the last steps' autoresets took, drawn before anything of this step is written
                self.next_episodes.top_up()
            return self.device_step.step(a)

        self.sim.set_controls(self.controls(a))
        self.sim.step(self.frame_skip)  # on a GPU: queued; the host goes on while it runs
        self.episodes.elapsed += 1
        # NEXT_STEP: the worlds that ended last step; this step only resets them (read after the
        # physics launch: on a GPU that read waits for the last step's flags, not for this step)
        pend, has_info = self._reset_pending()
        obs, reward, terminated, truncated, failed, info_values = outcome(self, a, pend)
        info_values = dict(info_values, sim_failed=failed)
        if self.autoreset_mode == AutoresetMode.SAME_STEP:
            done = to_numpy(terminated | truncated)  # the host resets now: it waits for the step here
            return self._reset_done(obs, reward, terminated, truncated, info_values, has_info, done)
        if self.autoreset_mode == AutoresetMode.NEXT_STEP:
            self.pending.defer(terminated | truncated, device=self.device, stream=self.device_step.torch_stream)
            if self.next_episodes is not None:  # kept for a later step on the device path
                self.next_episodes.set_pending(terminated | truncated)
        return obs, reward, terminated, truncated, batch_info(info_values, has_info)

    def _reset_pending(self):
        """NEXT_STEP: reset the worlds that ended in the last step.  Returns (a backend bool mask of
        them, or None where none is; the host bool mask of the worlds whose info entries are this
        step's, not a reset's)."""
        has_info = np.ones(self.num_envs, dtype=bool)
        if self.autoreset_mode != AutoresetMode.NEXT_STEP:
            return None, has_info
        pending = np.flatnonzero(self._pending_now())
        if not len(pending):
            return None, has_info
        pend = self.episodes.all_false()
        self.arrays.fill(pend, self._reset_worlds(pending), True)
        has_info[pending] = False
        return pend, has_info

    def _reset_done(self, obs, reward, terminated, truncated, info_values, has_info, done):
        """SAME_STEP: the worlds ``done`` (host bool mask; the host waits for the step to read it)
        reset now, as SyncVectorEnv does: the finished episode's last obs and info under final_obs
        / final_info, the new episode's first obs in obs (and its reset info, empty here, at the
        top level)."""
        if not done.any():
            return obs, reward, terminated, truncated, batch_info(info_values, has_info)
        final_info = batch_info(info_values, done)
        final_obs = obs
        self._reset_worlds(np.flatnonzero(done))
        obs = self.observation()
        info = batch_info(info_values, has_info & ~done)
        info.update(final_obs=final_obs, _final_obs=done.copy(), final_info=final_info, _final_info=done.copy())
        return obs, reward, terminated, truncated, info

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
        return self._renderer.frames(self.sim.body_positions(), self.sim.body_rotations(), self.render_worlds,
                                     self.render_extras)  # fmt: skip

    def close_extras(self, **kwargs):
        self._renderer = None
