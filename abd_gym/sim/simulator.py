"""Simulator: the public face of one scene stepped in ``num_worlds`` parallel worlds.

Data flows one way: ``Scene`` → ``Model`` (static arrays) → ``State`` (per step) → ``Solver``.
Getters return NumPy by default; ``backend="warp"`` gives the device array itself and
``backend="torch"`` a zero-copy Torch view on the simulator's device.
"""
from __future__ import annotations

import dataclasses
import math
import os
import warnings

import numpy as np
import warp as wp

from . import conditioning, inputs, kinematics
from .loops import LoopCheck
from ..core import graphs, launches, rows
from .coordinates import FIXED_CODE
from .inputs import check_body_spin, check_joint_state, check_within_limits
from .inputs import finite_array as _finite_array
from .model import Model
from ..solver.plan import ExecutionPlan, as_plan
from ..solver.retry import SUBSTEPS
from .scene import REVOLUTE, Scene
from ..solver.solver import Solver, SolverSettings
from .state import State
from .status import WorldStatus


FLOAT64 = np.dtype(np.float64)  # (NumPy's one instance: an identity test)

# step counts whose graphs ``step`` keeps in a list to replay (an env's frame skip; a few are enough)
MAX_REPLAYS = 8


@dataclasses.dataclass
class _World0Restart:
    """What a one-world CPU simulator keeps for set_joint_state in plain Python (_restart_world0)."""

    shape: tuple  # the coordinates' and rates' shape, (1, joints)
    buffer: wp.array  # (1, 2, joints): the coordinates and rates the restart launch's graph reads
    values: np.ndarray  # a flat host view of buffer
    bounds: tuple | None = None  # the joint bounds (Simulator._joint_bounds) the checks were made from
    checks: list = dataclasses.field(default_factory=list)  # each joint's (low, high, turn, fixed)


def _skew(w):
    """[w]× (..., 3, 3) of vectors w (..., 3)."""
    out = np.zeros(w.shape + (3,))
    out[..., 0, 1], out[..., 0, 2], out[..., 1, 2] = -w[..., 2], w[..., 1], -w[..., 0]
    out[..., 1, 0], out[..., 2, 0], out[..., 2, 1] = w[..., 2], -w[..., 1], w[..., 0]
    return out


class Simulator:
    """Step ``num_worlds`` copies of ``scene`` by ``dt`` [s], each step a Newton solve of the
    incremental potential (docs/design.md §2)

        q^{n+1} = argmin_q ½(q − q̃)ᵀM(q − q̃) + h²(Σ V_orth + Σ E_drive) + Σ E_joint + Σ E_limit

    with q̃ the inertial prediction and h = dt (implicit Euler) or 2dt/3 (BDF2).

    The physics: ``integrator`` "bdf2" (the default: second order, far less numerical damping; a
    world takes implicit Euler steps where its state was just set or a limit acts, so that no
    impact gains energy) or "implicit_euler" (first order, dissipative: a free pendulum visibly
    loses its swing); ``dtype`` "float32" or "float64";
    ``device`` "cpu" or "cuda:N" (default: $ABD_GYM_DEVICE, else "cpu").  The Newton solve
    (SolverSettings): it stops a world once ‖Δq‖∞/h < ``tol`` [m/s], after at most
    ``max_iterations`` iterations (None: 50, more for a scene whose stiffest joint's K/m is past 1e4:
    conditioning.default_max_iterations) of at most ``max_line_search`` Armijo trials each;
    ``reuse_factor`` solves an iteration after a full step against the last Cholesky factor
    (off by default: it stops short of the solution, SolverSettings); ``quadratic_stop``: a
    Newton step from a fresh factor accepted whole (α = 1) under this many times q's rounding
    floor 4·eps·(1 + ‖q‖∞) ends the solve (float32 only in effect; 0: off); ``retry``: a world whose
    step fails (does not converge, breaks down) takes it again as 2, then 4 substeps before it is
    rejected (``substeps``; solver/retry.py); None: on the CPU, and on a GPU only where asked for
    (``retry=True``), whose branch in the step's graphs has not been timed or run there yet;
    ``energy_gain``: with the retry, a step that converged in a conservative world (no drive
    pushing, no position drive in the scene) but raised its total energy by more than this fraction
    of its swing energy is retried the same way, and if it still gains at 4 substeps it is kept
    and flagged (``energy_gained``; solver/energy_gain.py); 0: no energy test; None: 0.05 where a
    step turns the scene's fastest gravity mode past conditioning.ENERGY_TEST_TURN (the large
    steps where BDF2 gains energy in many worlds), else 0: the test computes every tested world's
    energy after each step and copies its state before it, which a healthy world would pay at
    every step (conditioning.task_energy_gain; docs/design.md §4.1).

    How the step runs on the device (kernels, memory layout, launches, graphs) is ``plan``, an
    ExecutionPlan (or a dict of its fields) whose None fields are derived from the device, the
    number of worlds and the scene by the rules of abd_gym.solver.plan (the measurement behind each:
    docs/performance.md); every plan gives the same step to rounding.  ``Simulator.plan`` is the resolved plan.
    """

    def __init__(self, scene: Scene, num_worlds: int = 1, dt: float = 0.01, *, integrator: str = "bdf2",
                 dtype="float32", device=None, tol: float = 1e-5, max_iterations: int | None = None,
                 max_line_search: int = 12, reuse_factor: bool = False, quadratic_stop: float = 100.0,
                 retry: bool | None = None, energy_gain: float | None = None,
                 plan: ExecutionPlan | dict | None = None):  # fmt: skip
        inputs.count("num_worlds", num_worlds, minimum=1)
        dt = inputs.real_number("dt", dt, positive=True)
        if max_iterations is None:
            max_iterations = conditioning.default_max_iterations(scene)
        if energy_gain is None:
            energy_gain = conditioning.task_energy_gain(scene, dt)
        settings = SolverSettings(tol=inputs.real_number("tol", tol, positive=True),
                                  max_iterations=inputs.count("max_iterations", max_iterations, minimum=1),
                                  max_line_search=inputs.count("max_line_search", max_line_search, minimum=1),
                                  integrator=integrator, reuse_factor=reuse_factor,
                                  retry=True if retry is None else retry,
                                  energy_gain=inputs.real_number("energy_gain", energy_gain, nonnegative=True),
                                  quadratic_stop=inputs.real_number("quadratic_stop", quadratic_stop, nonnegative=True))  # fmt: skip
        self.scene = scene
        device = device or os.environ.get("ABD_GYM_DEVICE", "cpu")
        plan = as_plan(plan)
        # the staged reference step (fused=False) solves 12 unknowns a body in every scene; the fused
        # step, a planar scene's 6 (sim/planar.py)
        self.model = Model(scene, num_worlds, dtype=dtype, device=device, reduce=plan.fused is not False)
        if retry is None and self.model.device.is_cuda:
            settings.retry = False  # on a GPU the retry is asked for (its branch in the step's graphs is unmeasured)
        dtype_name = "float32" if self.model.np_dtype == np.float32 else "float64"
        for message in conditioning.unsolvable(scene, dt, dtype_name) + conditioning.step_too_large(scene, dt):
            warnings.warn(message, RuntimeWarning, stacklevel=2)
        self.state = State(self.model)
        self.solver = Solver(self.model, dt, settings, plan)
        self.dt = float(dt)
        # the largest |value| the setters take: of a parameter, of a state (inputs)
        self._bound = inputs.magnitude_bound(self.model.np_dtype)
        self._state_bound = inputs.state_bound(self.model.np_dtype)
        self.num_worlds = self.model.num_worlds
        self.device = self.model.device
        m = self.model
        self._ratio = np.broadcast_to(scene.strength_ratios(), (self.num_worlds, m.num_joints)).copy()
        self._mass = np.broadcast_to(m.base_mass, (self.num_worlds, m.num_bodies)).copy()
        self._joint_bodies = (m.body_a.numpy()[: m.num_joints].copy(), m.body_b.numpy()[: m.num_joints].copy())
        # joint kind -> host copies of the limits' (lower, upper, strength), (W, limits)
        self._limits = {kind: [np.broadcast_to([scene.joints[k].attributes[f"limit/{a}"] for k in ids], (self.num_worlds, len(ids))).copy()
                               for a in ("lower", "upper", "strength")] for kind, ids in m.limit_joints.items()}  # fmt: skip
        self._set_mask = None
        self._world0 = None  # a one-world simulator's device indices [0] (_one_world)
        self._world0_restart = None  # a one-world CPU simulator's _World0Restart
        self._world0_graph = None  # (the restart launch's graph reading _World0Restart.buffer, its arguments)
        self._joints = None  # set_joint_state's joint names and revolute mask (_joint_names)
        self._joint_bounds = None  # set_joint_state's bounds (inputs.joint_state_bounds), until set_limit
        # a revolute rate's largest |rate|·dt: what a step, or the retry's finest substeps, produce
        settings = self.solver.settings
        self._turn = inputs.max_turn(settings.integrator, max(SUBSTEPS) if settings.retry else 1)
        self._tree_plan = None  # set_joint_state's forward-kinematics order (kinematics.tree_plan), built once
        self._loops = LoopCheck.for_scene(scene, self.model)  # the closing joints' gaps, or None: no loop
        self._torch_views = {}
        self._host_views = {}
        self._host_copies = {}  # view's NumPy copies on the CPU: id -> (array, host view, the copy's dtype)
        self._cmds = {}  # recorded launches of the reset path, replayed with changed arguments (_replay)
        self._stage = rows.Staging(self.device)  # host rows to the device without waiting for the device
        self._graph = {}  # steps a launch -> the captured step: [(phase, graph or None)]
        self._replays = {}  # steps a call -> its (phase, graph) pairs, once every launch of it is captured (step)
        self._warm = False
        if self.device.is_cpu and self.num_worlds == 1 and self.model.num_joints:
            buffer = wp.zeros((1, 2, self.model.num_joints), dtype=self.model.dtype, device=self.device)
            self._world0_restart = _World0Restart((1, self.model.num_joints), buffer, buffer.numpy().reshape(-1))
        self.reset()

    @property
    def loops(self):
        """The check of the coordinates of the scene's closed loops (sim.loops.LoopCheck: ``gaps``,
        ``check``), or None where no joint closes a loop."""
        return self._loops

    @property
    def plane(self):
        """The plane a planar scene is solved in (sim.planar.Plane: 6 unknowns a body, e.g. "xz"), or
        None (12 unknowns a body): Scene.planar, resolved when the simulator was built."""
        return self.model.plane

    def __repr__(self) -> str:
        m = self.model
        form = f"6 a body in the {m.plane} plane" if m.plane else "12 a body"
        return (f"Simulator({m.num_worlds} worlds, {m.num_bodies} bodies ({m.num_free} free), {m.num_dofs} unknowns a "
                f"world ({form}), dt {self.dt:g} s, {self.solver.settings.integrator}, "
                f"{np.dtype(m.np_dtype).name}, {self.device}, scratch {self.plan.scratch!r})")  # fmt: skip

    @property
    def plan(self) -> ExecutionPlan:
        """The execution plan the step runs (every field resolved)."""
        return self.solver.plan

    # ------------------------------------------------------------------ stepping
    def step(self, num_steps: int = 1):
        """Advance every world ``num_steps`` steps of ``dt`` (where a step is one launch, up to the
        solver's ``steps_per_launch`` a launch).  With ``retry`` (the default), a world whose step
        fails takes it again as 2, then 4 substeps (``substeps``) before it is rejected; a launch of
        several steps is not retried."""
        num_steps = inputs.count("num_steps", num_steps)
        replay = self._replays.get(num_steps)
        if replay is not None:  # every launch's phases captured: the graphs alone (a one-world step is a few us)
            state, launch = self.state, wp.capture_launch
            for phase, graph in replay[0]:
                if graph is None:
                    phase(state)  # a phase a graph cannot hold (the CPU's concurrent launches, its retry)
                else:
                    launch(graph)
            time = state.time
            for k in replay[1]:
                if self.num_worlds == 1:
                    time[0] += k * self.dt  # the same sum as the array's, without a ufunc call
                else:
                    time += k * self.dt
            return
        chunks = self.solver.launch_chunks(num_steps)
        for k in chunks:
            if self.plan.use_graph and self._warm:
                if k not in self._graph:
                    # capture after one plain step, so every kernel is compiled and loaded; with the
                    # CPU's concurrent Newton launches (which a graph cannot hold), the phases around them
                    self._graph[k] = [(phase, self._capture(phase) if capturable else None)
                                      for phase, capturable in self.solver.step_phases(k)]  # fmt: skip
                for phase, graph in self._graph[k]:
                    if graph is None:
                        phase(self.state)
                    else:
                        wp.capture_launch(graph)
            else:
                self.solver.step(self.state, k)
                self._warm = True
            self.state.time += k * self.dt
        if chunks and all(k in self._graph for k in chunks) and len(self._replays) < MAX_REPLAYS:
            self._replays[num_steps] = (tuple(pg for k in chunks for pg in self._graph[k]), chunks)

    def stepper(self, num_steps: int = 1):
        """A function of no arguments that does what ``step(num_steps)`` does, bit for bit: the
        replay of the graphs (and the phases a graph cannot hold) that ``step`` captured for it, and
        the clock, without ``step``'s check of its argument and lookup of the capture.  None until
        ``step(num_steps)`` has captured them (its second call, where ``plan.use_graph``); for a
        caller that steps by the same count every time (a single env's frame skip)."""
        replay = self._replays.get(num_steps)
        if replay is None:
            return None
        state, launch = self.state, wp.capture_launch
        calls = tuple((launch, graph) if graph is not None else (phase, state) for phase, graph in replay[0])
        increments = tuple(k * self.dt for k in replay[1])
        time, one = state.time, self.num_worlds == 1

        def step():
            for call, argument in calls:
                call(argument)
            for dt in increments:
                if one:
                    time[0] += dt
                else:
                    np.add(time, dt, out=time)  # step's time += dt

        return step

    def launch_step(self, num_steps: int = 1, hold: wp.array | None = None, go: wp.array | None = None):
        """``num_steps`` steps as direct launches of the step's kernels, without the simulator's own
        graphs and without advancing the host clock ``state.time``: for a caller that captures the
        step in a graph of its own (the vector env's), and advances the clock (``tick``) at each
        replay.  The same step as ``step`` (``num_steps`` at least 1).  ``hold`` (device int32
        (num_worlds,)) and ``go`` (device int32 (1,)), where the step is one launch (``holds``): the worlds with
        hold[w] != 0, and every world while go[0] == 0, are not stepped, and none of their rows is
        read or written, so that other launches may rewrite them at the same time.  A failed step is
        retried as in ``step`` on the CPU; on a GPU, where the caller's graph would hold the retry's
        conditional branch, it is not (the world is reported)."""
        self.solver.step(self.state, inputs.count("num_steps", num_steps, minimum=1), hold=hold, go=go,
                         retry=self.device.is_cpu)  # fmt: skip

    def tick(self, num_steps: int = 1):
        """Advance the host clock ``state.time`` by ``num_steps`` steps (see ``launch_step``)."""
        self.state.time += inputs.count("num_steps", num_steps) * self.dt

    # ------------------------------------------------------------------ a caller's own graphs
    # What a caller that steps the simulator inside CUDA graphs of its own (launch_step) reads and
    # writes there: device arrays a kernel or a graph node can take, where the getters and setters
    # are host calls that check their input.
    @property
    def time(self) -> np.ndarray:
        """(num_worlds,) seconds since each world's last reset: the host clock (NumPy, writable),
        which ``step`` and ``tick`` advance and the setters restart.  A caller that restarts worlds
        on the device (``set_joint_state_where``) restarts their clocks here itself."""
        return self.state.time

    @property
    def scalar(self):
        """The Warp scalar type of the simulator's arrays (wp.float32 or wp.float64)."""
        return self.model.dtype

    def controls(self, backend: str = "warp"):
        """The drive inputs the next step reads, (num_worlds, num_drives) of ``scalar``, as ``view``
        gives them: "warp" and "torch" are the array itself, which a caller's kernel may write on the
        device (in a graph, where ``set_controls`` is host work); such a write is not checked."""
        return self.view(self.state.control, backend)

    @property
    def holds(self) -> bool:
        """Whether ``launch_step`` can hold worlds (its ``hold`` and ``go``; Solver.holds)."""
        return self.solver.holds

    def enable_hold(self) -> bool:
        """Build the one-launch step so that ``launch_step`` can hold worlds (Solver.enable_hold);
        before the first step only.  Returns ``holds``."""
        return self.solver.enable_hold()

    def _capture(self, phase):
        """A graph of ``phase`` (a solver step's part)."""
        return graphs.capture(self.device, lambda: phase(self.state))[0]

    # ------------------------------------------------------------------ output
    def view(self, array: wp.array, backend: str = "numpy"):
        """``array`` (one of the simulator's device arrays, or a caller's array on its device) as
        ``backend``: "numpy" a host copy (float64, int32 for int32 arrays), "warp" the array itself,
        "torch" a zero-copy Torch view on the device (made once per array: the simulator's arrays
        are never reallocated, so the view stays valid and writes through it reach the array)."""
        if backend == "numpy":  # a copy: on the CPU .numpy() is a view of memory the next step overwrites
            copy = self._host_copies.get(id(array))
            if copy is not None and copy[0] is array:  # a CPU array seen before: its view and the copy's dtype
                return np.array(copy[1], dtype=copy[2])
            dtype = np.float64 if array.dtype != wp.int32 else np.int32
            if not self.device.is_cpu:
                return np.array(array.numpy(), dtype=dtype)
            self._host_copies[id(array)] = (array, self.host_view(array), dtype)
            return np.array(self.host_view(array), dtype=dtype)
        if backend == "warp":
            return array
        if backend == "torch":  # zero-copy views, made once: the state's arrays are never reallocated
            view = self._torch_views.get(id(array))
            if view is None:
                view = self._torch_views[id(array)] = wp.to_torch(array)
            return view
        raise ValueError(f"backend must be 'numpy', 'warp' or 'torch', got {backend!r}")

    def joint_coordinates(self, backend="numpy"):
        """(num_worlds, num_joints): revolute angle [rad] (the seed's x = θ0 + δ), slider displacement [m]."""
        return self.view(self.state.coord, backend)[:, : self.model.num_joints]

    def joint_velocities(self, backend="numpy"):
        """(num_worlds, num_joints): rates of the coordinates over the last step [rad/s, m/s]."""
        return self.view(self.state.coord_vel, backend)[:, : self.model.num_joints]

    def joint_angles_unwrapped(self, backend="numpy"):
        """(num_worlds, num_joints): multi-turn revolute angle [rad] (displacement for sliders)."""
        return self.view(self.state.unwrapped, backend)[:, : self.model.num_joints]

    def body_q(self, backend="numpy"):
        """(num_worlds, num_bodies, 12): affine coordinates (p, a1, a2, a3)."""
        if backend == "numpy":
            return self.state.q.numpy().astype(np.float64)
        return self.view(self.state.q, backend)

    def body_positions(self, backend="numpy"):
        """(num_worlds, num_bodies, 3): p of each body [m]."""
        return self.body_q(backend)[..., :3]

    def body_rotations(self, backend="numpy"):
        """(num_worlds, num_bodies, 3, 3): A of each body (rows a_k)."""
        q = self.body_q(backend)
        return q[..., 3:].reshape(q.shape[:-1] + (3, 3))

    def body_velocities(self):
        """(num_worlds, num_bodies, 12): q̇ over the last step."""
        return self.state.qd.numpy().astype(np.float64)

    def body_angular_velocities(self):
        """(num_worlds, num_bodies, 3): ω of each body [rad/s], the axial vector of the skew part of
        Ȧ Aᵀ (Ȧ = [ω]× A for a rotation A): what set_body_states takes as angular_velocities."""
        q, qd = self.body_q(), self.body_velocities()
        A, Ad = q[..., 3:].reshape(q.shape[:-1] + (3, 3)), qd[..., 3:].reshape(q.shape[:-1] + (3, 3))
        Wx = Ad @ np.swapaxes(A, -1, -2)
        Wx = 0.5 * (Wx - np.swapaxes(Wx, -1, -2))
        return np.stack([Wx[..., 2, 1], Wx[..., 0, 2], Wx[..., 1, 0]], axis=-1)

    def energies(self) -> dict:
        """Each term's own energy [J] per world: "kinetic" (the joints' armature's ½aẋ² included),
        "gravity", "orthogonality" and the joint, limit and drive terms the scene has.  A joint's is
        its physical energy K/(2ĥ₀²) Σ‖C‖²: the seed's K/2 Σ‖C‖² is a term of the incremental
        potential outside ĥ² (J·s²), so its stiffness is K/ĥ₀² with ĥ₀ the simulator's step (dt,
        2dt/3 under BDF2), which every step keeps (docs/design.md §2), and totals compare across
        dt.  A limit's is its physical energy E(x)/dt²: the seed's cubic E(x) sits outside ĥ² too, as
        it is in every step, and a world whose limit acts takes an implicit Euler step next (ĥ = dt)."""
        return self.solver.energies(self.state)

    def energy_allowance(self) -> np.ndarray:
        """(num_worlds,) [J]: how much of the total of ``energies()`` is rounding, as the energy
        test (``energy_gain``) allows it: the sums' rounding and each term's energy at its
        quantity's rounding (solver/energy_gain.py).  A change of the total between two states
        resolves a gain only beyond the sum of their allowances."""
        return self.solver.energy_allowance(self.state)

    def joint_violation(self, joints=None) -> np.ndarray:
        """(num_worlds,) largest joint position residual [m] over all joints, or over the indices
        ``joints`` (a loop's closing joints: how far the loop is open): ‖x_i(P) − x_j(P)‖ of revolute
        and fixed joint points, ‖C0‖ and ‖C1‖ of prismatic joints."""
        m = self.model
        out = np.zeros(self.num_worlds)
        if not m.num_joints or (joints is not None and not len(joints)):
            return out
        q = self.body_q()
        p, A = q[..., :3], q[..., 3:].reshape(q.shape[:-1] + (3, 3))
        ia, ib = m.body_a.numpy()[: m.num_joints], m.body_b.numpy()[: m.num_joints]
        pa, Aa, pb, Ab = p[:, ia], A[:, ia], p[:, ib], A[:, ib]
        pts_a, pts_b = m.pts_a.numpy().astype(np.float64), m.pts_b.numpy().astype(np.float64)
        xa = pa[:, :, None] + np.einsum("wjkl,wjpl->wjpk", Aa, pts_a[:, : m.num_joints])
        xb = pb[:, :, None] + np.einsum("wjkl,wjpl->wjpk", Ab, pts_b[:, : m.num_joints])
        res = np.linalg.norm(xa - xb, axis=-1)  # (W, nj, 4)
        kind = m.joint_kind_np
        res[:, kind == 0, 2:] = 0.0  # revolute joints use two points
        viol = res.max(axis=-1)
        pris = kind == 1
        if pris.any():
            f = {n: getattr(m, n).numpy().astype(np.float64)[:, : m.num_joints] for n in ("c_a", "c_b", "t_a", "t_b")}
            ca = pa + np.einsum("wjkl,wjl->wjk", Aa, f["c_a"])
            cb = pb + np.einsum("wjkl,wjl->wjk", Ab, f["c_b"])
            ta, tb = np.einsum("wjkl,wjl->wjk", Aa, f["t_a"]), np.einsum("wjkl,wjl->wjk", Ab, f["t_b"])
            c0 = np.linalg.norm(np.cross(cb - ca, ta), axis=-1)
            c1 = np.linalg.norm(np.cross(ca - cb, tb), axis=-1)
            viol[:, pris] = np.maximum(c0, c1)[:, pris]
        return (viol if joints is None else viol[:, list(joints)]).max(axis=1)

    def memory_bytes(self) -> dict:
        """Device memory [bytes] of the simulator's own arrays: "model", "state", "solver" and
        "total" (kernels' code and a captured graph not included)."""
        def size(obj):  # arrays that own their memory (views, such as the solver's flat scratch, do not)
            return sum(a.capacity for a in vars(obj).values() if isinstance(a, wp.array) and a.deleter is not None)

        out = {"model": size(self.model), "state": size(self.state), "solver": size(self.solver)}
        out["total"] = sum(out.values())
        return out

    def world_status(self, backend: str = "numpy"):
        """(num_worlds,) int32 status code of each world (abd_gym.WorldStatus: OK, NONFINITE,
        BREAKDOWN, UNCONVERGED), as ``view`` gives it ("numpy": a copy; "warp", "torch": the device
        array itself, to read only).  A world not OK kept the state it had before the step that set
        the code and is not stepped until reset, set_joint_state or set_body_states writes it."""
        return self.view(self.state.status, backend)

    def failed_worlds(self) -> np.ndarray:
        """Indices of the worlds whose status is not OK (world_status): their state went non-finite,
        their system broke down or their solve did not converge; reset or set them."""
        return np.flatnonzero(self.view(self.state.status, "numpy") != 0)

    def converged(self) -> np.ndarray:
        """(num_worlds,) bool: the last step's Newton solve met the tolerance (False for a world not
        OK)."""
        return self.state.converged.numpy().astype(bool)

    def newton_iterations(self) -> np.ndarray:
        """(num_worlds,) Newton iterations used in the last step."""
        return self.state.iterations.numpy().copy()

    def newton_retried(self) -> np.ndarray:
        """(num_worlds,) bool: the last step's solve, which reused the factor or (the fused step) ran
        in a scene with a stiff joint (Model.stiff), did not converge within its budget and was
        started again from the prediction q̃ with a fresh factor at every iteration
        (``newton_iterations`` counts both)."""
        return self.state.retried.numpy().astype(bool)

    def substeps(self, backend: str = "numpy"):
        """(num_worlds,) int32: the substeps of each world's last step: 1, or 2 or 4 where the step
        failed (did not converge, broke down) and was taken again as that many steps of dt/2 or
        dt/4 (``retry``); a world that failed at 4 too is rejected (world_status).  As ``view``
        gives it ("numpy": a copy; "warp", "torch": the device array itself, to read only)."""
        return self.view(self.state.substeps, backend)

    def energy_gained(self, backend: str = "numpy"):
        """(num_worlds,): the world's last step, in a conservative world (``energy_gain``), raised
        its total energy by more than the test allows at 4 substeps too, and was kept.  "numpy": a
        bool copy; "warp", "torch": the int32 device array itself (nonzero: gained), to read only."""
        if backend == "numpy":
            return np.array(self.view(self.state.gained, "numpy"), dtype=bool)
        return self.view(self.state.gained, backend)

    def newton_factorizations(self) -> np.ndarray:
        """(num_worlds,) Cholesky factorisations in the last step: the iterations less those that
        reused a factor (``reuse_factor``)."""
        return self.state.factorizations.numpy().copy()

    # ------------------------------------------------------------------ input
    def _worlds(self, worlds):
        """``worlds`` as checked indices (inputs.world_indices)."""
        return inputs.world_indices(worlds, self.num_worlds)

    def _replay(self, key, kernel, dim, inputs):
        """Launch ``kernel`` as a command recorded on the first call and replayed after, with only the
        arguments that changed (by identity; Python scalars by value) and the dim set again: packing
        a reset's ~40 unchanged arguments cost more than its kernels on the CPU."""
        launches.replay(self._cmds, key, kernel, dim, inputs, self.device)

    def _mask(self, idx_dev, n=None):
        """A device int32 mask (W,) of the worlds idx_dev[:n] (reused: valid until the next call)."""
        n = idx_dev.shape[0] if n is None else n
        if self._set_mask is None:
            self._set_mask = wp.zeros(self.num_worlds, dtype=wp.int32, device=self.device)
        self._set_mask.zero_()
        if n:
            self._replay("mask", rows.fill_int, n, [self._set_mask, idx_dev, 1])
        return self._set_mask

    def host_view(self, array: wp.array) -> np.ndarray:
        """A NumPy view of a CPU array's own memory (no copy; writes reach the array), cached per
        array.  CPU devices only: a GPU array's memory is not the host's."""
        view = self._host_views.get(id(array))
        if view is None or view[0] is not array:
            view = self._host_views[id(array)] = (array, array.numpy())
        return view[1]

    def _write_rows(self, array, idx, values):
        """array[idx] = values for a (W, C) device array; only those rows travel (rows.py)."""
        idx_dev = idx if isinstance(idx, wp.array) else rows.indices(idx, self._stage)
        rows.write(array, idx_dev, values, self.model.np_dtype, self._stage)

    def set_controls(self, values, worlds=None):
        """Drive inputs (num_worlds or len(worlds), num_drives): torque/force [N·m, N] of effort drives,
        target position [rad, m] of position drives, target velocity of velocity drives.  A Torch
        tensor of every world is copied on its device, its values unchecked (reading them would
        make the host wait for the device); anything else is checked (inputs.finite_array)."""
        nd = self.model.num_drives
        if nd == 0:
            raise ValueError("the scene has no drives")
        idx = self._worlds(worlds)
        if worlds is None and type(values).__module__.startswith("torch"):
            if tuple(values.shape) != (self.num_worlds, nd):
                raise ValueError(f"controls must have shape ({self.num_worlds}, {nd}), got {tuple(values.shape)}")
            if values.is_complex() or str(values.dtype) == "torch.bool":
                raise TypeError(f"controls must be real numbers (integer or float), got {values.dtype}")
            self.view(self.state.control, "torch").copy_(values)  # on the device, converting dtype
            return
        vals = _finite_array("controls", values, (len(idx), nd), idx, [d.name for d in self.scene.drives], "drive",
                             bound=self._bound)  # fmt: skip
        if worlds is None and self.device.is_cpu:
            self.host_view(self.state.control)[...] = vals  # the array's own memory: no temporary array
        elif worlds is None:
            self.state.control.assign(vals.astype(self.model.np_dtype))
        else:
            self._write_rows(self.state.control, idx, vals)

    def set_body_states(self, positions, rotations, linear_velocities=None, angular_velocities=None, worlds=None):
        """Set poses (N, bodies, 3) and (N, bodies, 3, 3) [and velocities] of the worlds listed (default all).

        Fixed bodies keep their scene pose.  The joint-angle history restarts: q^{t−1} = q.
        Refused with a ValueError naming the world and body (nothing is written): a non-finite or
        overflowing value (inputs.finite_array), a rotation part that is not a rotation
        (inputs.check_rotations), an angular velocity that turns a body by π or more in one step
        (|ω|·dt ≥ π), which neither a joint's incremental angle nor the step's rotation of A can
        represent, or a pose that puts a limited joint beyond its bounds by more than the limit
        holds (inputs.check_within_limits; the worlds are then put back as they were).
        """
        idx = self._worlds(worlds)
        nb = self.model.num_bodies
        names = [b.name for b in self.scene.bodies]
        at = dict(worlds=idx, items=names, item="body", bound=self._state_bound)
        p = _finite_array("positions", positions, (len(idx), nb, 3), **at)
        R = _finite_array("rotations", rotations, (len(idx), nb, 3, 3), **at)
        v = _finite_array("linear_velocities", 0.0 if linear_velocities is None else linear_velocities, (len(idx), nb, 3), **at)
        w = _finite_array("angular_velocities", 0.0 if angular_velocities is None else angular_velocities, (len(idx), nb, 3), **at)
        fixed = np.array([b.fixed for b in self.scene.bodies])
        inputs.check_rotations("rotations", R, idx, names, movable=~fixed)
        check_body_spin(self.scene, w, idx, self.dt, self._turn)
        q = np.concatenate([p, R.reshape(len(idx), nb, 9)], axis=-1)
        qd = np.concatenate([v, (_skew(w) @ R).reshape(len(idx), nb, 9)], axis=-1)
        q[:, fixed] = self.model.q0[fixed]
        qd[:, fixed] = 0.0
        self._check_in_plane(idx, poses={"positions, rotations": q}, rates={"linear_velocities, angular_velocities": qd})
        limits = self._limit_bounds()
        before = self.get_state(idx) if limits and len(idx) else None
        self._set_q(idx, q, qd)
        if before is not None:  # the joints' coordinates follow from the poses on the device
            try:
                check_within_limits("positions", self.joint_coordinates()[idx], idx, limits,
                                    [j.name for j in self.scene.joints])  # fmt: skip
            except ValueError:
                self._write_state(before, idx)
                raise

    def _check_in_plane(self, worlds, poses: dict, rates: dict):
        """For a planar-reduced scene, the body poses and rates given by name, (N, bodies, 12) each,
        refused where they leave the plane (inputs.check_in_plane)."""
        plane = self.model.plane
        if plane is None:
            return
        movable = ~np.array([b.fixed for b in self.scene.bodies])
        items = [b.name for b in self.scene.bodies]
        for velocity, named in ((False, poses), (True, rates)):
            for name, a in named.items():
                inputs.check_in_plane(name, np.asarray(a, dtype=np.float64), worlds, items, plane.held, self.model.q0,
                                      movable, velocity=velocity)  # fmt: skip

    def _set_q(self, idx, q, qd):
        """Restart the worlds idx at body states q, q̇ (N, bodies, 12)."""
        if len(idx):
            idx_dev = rows.indices(idx, self._stage)
            # q, q̇, q_prev and the BDF2 history (a set state has no past: as if the velocity had
            # been constant), and status OK, in one launch
            rows.restart(self.state, idx_dev, q, qd, self.dt, self.model, self._stage)
            self._restarted(idx, idx_dev)

    def _restarted(self, idx, idx_dev):
        """After the worlds idx got new body states: their clocks, joint histories, coordinates and
        (principal) multi-turn angles.  idx_dev: the indices on the device (its first len(idx) rows)."""
        st, m = self.state, self.model
        N = len(idx)
        st.time[idx] = 0.0
        self.solver.restart_joints(st, self._mask(idx_dev, N))
        if m.num_joints:
            self._replay("unwrapped", rows.kernels(m.dtype)["restart_unwrapped"], (N, m.num_joints),
                         [idx_dev, st.coord, st.coord_vel, float(self.dt), st.unwrapped, st.x_hist])  # fmt: skip

    def set_joint_state(self, coordinates, velocities=None, worlds=None):
        """Forward kinematics for tree mechanisms (kinematics.py, on the device): joint coordinates
        (N, num_joints) [rad, m] and rates, from the scene's zero pose.  Joints that close a loop
        are not placed: the coordinates given must close it, to within ``loops.LOOP_TOL`` of the
        closing joint's half_length (a state a step produced reopens it by the joints' stretch
        only; docs/design.md §5).

        Refused with a ValueError naming the joint, the world and the value (nothing is written): a
        non-finite or overflowing value, a limited joint beyond its limit's [lower, upper] by more
        than the limit holds (a penetration a step produced is accepted: inputs.check_within_limits),
        a revolute rate that turns the joint by π or more in one step, coordinates that leave a
        closed loop open (``loops.LoopCheck``: naming the closing joint and the gap)."""
        if self._world0_restart is not None and self._restart_world0(coordinates, velocities, worlds):
            return
        idx = self._worlds(worlds)
        m = self.model
        nj, N = m.num_joints, len(idx)
        x, xd = self.check_joint_state(coordinates, velocities, idx)
        if N == 0:
            return
        fixed = self._joint_names()[2]
        idx_dev = self._one_world() if self.num_worlds == 1 else rows.indices(idx, self._stage)
        # coordinates and rates in one upload; a fixed joint's coordinate (which placing ignores)
        # is 0, which is its multi-turn coordinate; a scene without joints still passes (N, 2, 1)
        if nj:
            xx = np.concatenate((x if fixed is None else np.where(fixed, 0.0, x), xd), axis=1).reshape(N, 2, nj)
        else:
            xx = np.zeros((N, 2, 1))
        xx = self._stage("xx", xx, m.dtype)
        self._replay("restart", *kinematics.restart_launch(*self._tree(), self.state, m, self.solver, idx_dev, xx, N,
                                                           self.dt))  # fmt: skip
        self.state.time[idx] = 0.0

    def check_joint_state(self, coordinates, velocities=None, worlds=None, limits=None):
        """``set_joint_state``'s checks alone (nothing is written): the coordinates and rates as
        float64 (N, num_joints) arrays, or a ValueError naming the joint, the world and the value.
        ``limits``: {limited joint index: (lower (N,), upper (N,))} of the worlds listed, bounds
        to check against in place of those in force (a reset's that are written after the check)."""
        idx = self._worlds(worlds)
        nj, N = self.model.num_joints, len(idx)
        names, revolute, fixed = self._joint_names()
        at = dict(worlds=idx, items=names, item="joint", bound=self._state_bound)
        x = _finite_array("coordinates", coordinates, (N, nj), **at)
        xd = _finite_array("velocities", 0.0 if velocities is None else velocities, (N, nj), **at)
        if N == 0:
            return x, xd
        if limits:
            bounds = self._limit_bounds()
            for k, (lo, up) in limits.items():
                lower, upper, rev = bounds[k]
                lower, upper = lower.astype(np.float64), upper.astype(np.float64)
                lower[idx], upper[idx] = lo, up
                bounds[k] = (lower, upper, rev)
            check_joint_state(names, revolute, x, xd, idx, self.dt, bounds, self._turn)
        else:
            if self._joint_bounds is None:  # kept until set_limit changes the limits
                self._joint_bounds = inputs.joint_state_bounds(self._limit_bounds(), revolute, self.num_worlds,
                                                               self._turn)  # fmt: skip
            if not inputs.joint_state_ok(x, xd, idx, self.dt, self._joint_bounds):
                check_joint_state(names, revolute, x, xd, idx, self.dt, self._limit_bounds(), self._turn)  # names it
        if self._loops is not None:
            self._loops.check("coordinates", x, idx)
        return x, xd

    def _restart_world0(self, coordinates, velocities, worlds) -> bool:
        """``set_joint_state`` of a one-world CPU simulator from float64 arrays (1, joints) of
        coordinates and rates, for world 0 (``worlds`` None or [0]), where each value passes, in
        plain Python floats, the checks that ``set_joint_state`` makes (finite, within half the
        state bound, within the joint's bounds, |rate|·dt below the joint's turn; a closed loop
        closed): the values
        written into a kept array that a captured graph of the restart launch reads.  Returns
        False, having written nothing, for any other input, which ``set_joint_state`` then takes
        (and refuses, naming the joint, where it must)."""
        kept = self._world0_restart
        if not (type(coordinates) is np.ndarray and type(velocities) is np.ndarray and coordinates.dtype is FLOAT64
                and velocities.dtype is FLOAT64 and coordinates.shape == velocities.shape == kept.shape):  # fmt: skip
            return False
        if worlds is not None and not (type(worlds) is np.ndarray and worlds.shape == (1,) and worlds.dtype.kind in "iu"
                                       and worlds[0] == 0):  # fmt: skip
            return False
        if self._joint_bounds is None:  # kept until set_limit changes the limits
            self._joint_bounds = inputs.joint_state_bounds(self._limit_bounds(), self._joint_names()[1], 1, self._turn)
        if kept.bounds is not self._joint_bounds:
            lower, upper, turn = self._joint_bounds
            fixed = self._joint_names()[2]
            fixed = [False] * len(turn) if fixed is None else fixed.tolist()
            kept.bounds = self._joint_bounds
            kept.checks = list(zip(lower[0].tolist(), upper[0].tolist(), turn.tolist(), fixed))
        x, xd = coordinates[0].tolist(), velocities[0].tolist()
        half, dt = 0.5 * self._state_bound, self.dt
        for c, r, (low, high, turn, _) in zip(x, xd, kept.checks):
            if not (-half < c < half and -half < r < half and low <= c <= high and abs(r) * dt < turn):
                return False
        if self._loops is not None and not self._loops.closed(coordinates):
            return False
        nj = len(x)
        for j, (c, r, check) in enumerate(zip(x, xd, kept.checks)):
            kept.values[j] = 0.0 if check[3] else c  # rounded to the model's dtype by the store
            kept.values[nj + j] = r
        if self._world0_graph is None:
            kernel, dim, args = kinematics.restart_launch(*self._tree(), self.state, self.model, self.solver,
                                                          self._one_world(), kept.buffer, 1, self.dt)  # fmt: skip
            wp.launch(kernel, dim=dim, inputs=args, device=self.device)  # (loads the kernel)
            graph = graphs.capture(self.device, lambda: wp.launch(kernel, dim=dim, inputs=args, device=self.device))[0]
            self._world0_graph = (graph, args)
        else:
            wp.capture_launch(self._world0_graph[0])
        self.state.time[0] = 0.0
        return True

    def _one_world(self) -> wp.array:
        """The device indices [0] of a one-world simulator (every nonempty ``worlds`` of it), kept:
        its resets stage no indices."""
        if self._world0 is None:
            self._world0 = wp.zeros(1, dtype=wp.int32, device=self.device)
        return self._world0

    def _joint_names(self):
        """(the joints' names, a bool array (joints,) of the revolute ones, one of the fixed ones or
        None where none is), made once."""
        if self._joints is None:
            joints = self.scene.joints
            fixed = self.model.joint_kind_np[: len(joints)] == FIXED_CODE
            self._joints = ([j.name for j in joints], np.array([j.kind == REVOLUTE for j in joints], dtype=bool),
                            fixed if fixed.any() else None)  # fmt: skip
        return self._joints

    def _limit_bounds(self):
        """{joint index: (lower (W,), upper (W,), revolute)} of the limited joints, from the host copies."""
        m = self.model
        return {j: (self._limits[kind][0][:, c], self._limits[kind][1][:, c], kind == REVOLUTE)
                for kind, ids in m.limit_joints.items() for c, j in enumerate(ids)}  # fmt: skip

    def _tree(self):
        """(forward kinematics' plan, its per-world angular-velocity scratch), made on first use."""
        if self._tree_plan is None:
            m = self.model
            self._tree_plan = kinematics.tree_plan(self.scene, m)
            self._omega = wp.zeros((self.num_worlds, m.num_bodies), dtype=m.vec3, device=self.device)
        return self._tree_plan, self._omega

    def set_joint_state_where(self, mask: wp.array, xx: wp.array):
        """``set_joint_state`` of the worlds w with mask[w] != 0 (a device int32 (num_worlds,) array)
        from xx[w, 0] (coordinates) and xx[w, 1] (rates) (a device (num_worlds, 2, max(joints, 1))
        array of the model's dtype), with no host work on the worlds: one launch on device arrays
        that a graph can hold (the vector env's autoreset).  The host clock
        (``state.time``) of those worlds is left to the caller, who learns which they are later."""
        m, W = self.model, self.num_worlds
        if tuple(mask.shape) != (W,) or mask.dtype != wp.int32:
            raise ValueError(f"mask must be an int32 array of shape ({W},), got {mask.dtype} {tuple(mask.shape)}")
        if tuple(xx.shape) != (W, 2, max(m.num_joints, 1)) or xx.dtype != m.dtype:
            raise ValueError(f"xx must have shape ({W}, 2, {max(m.num_joints, 1)}) and the model's dtype, "
                             f"got {xx.dtype} {tuple(xx.shape)}")  # fmt: skip
        self._replay("restart_where", *kinematics.restart_launch(*self._tree(), self.state, m, self.solver, mask, xx, W,
                                                                 self.dt, mask=mask))  # fmt: skip

    def reset(self, worlds=None):
        """Back to the scene's initial state (all worlds, or those listed); clears failure flags
        and controls."""
        idx = self._worlds(worlds)
        N = len(idx)
        q = np.broadcast_to(self.model.q0, (N,) + self.model.q0.shape)
        qd = np.broadcast_to(self.model.qd0, (N,) + self.model.qd0.shape)
        if self.model.num_drives:
            self._write_rows(self.state.control, idx, 0.0)
        self._set_q(idx, q, qd)

    # ------------------------------------------------------------------ whole state
    def _state_arrays(self) -> dict:
        """{name: device array} of every per-world array of the state (State)."""
        return {name: a for name, a in vars(self.state).items() if isinstance(a, wp.array)}

    def get_state(self, worlds=None) -> dict:
        """Host copies of the whole state of the worlds listed (default all), by name: every array
        of State, (N, ...) in the model's dtype (int32 for flags and counts), and ``"time"`` (N,):
        poses, velocities, the joints' histories, BDF2's past step, controls, status and the last
        step's solver counts.  ``set_state`` writes them back, and the worlds then step exactly as
        they would have from here (the model's parameters, set_body_mass, set_limit..., are not
        part of it)."""
        idx = self._worlds(worlds)
        out = {name: (self.host_view(a) if self.device.is_cpu else a.numpy())[idx]
               for name, a in self._state_arrays().items()}  # fmt: skip
        out["time"] = self.state.time[idx].copy()
        return out

    def set_state(self, state: dict, worlds=None):
        """Restore ``get_state``'s values into the worlds listed (default all; as many as the
        state holds), bit for bit.  Refused with a TypeError or ValueError naming the entry, the
        world and the body or joint (nothing is written): a missing or unknown entry, a shape or
        dtype other than this simulator's, a non-finite or overflowing pose or velocity, a rotation
        part that is not a rotation, a limited joint beyond what its limit holds, an unknown
        status code."""
        self._write_state(*self.check_state(state, worlds))

    def check_state(self, state: dict, worlds=None, limits=None):
        """``set_state``'s checks alone (nothing is written): (the values as arrays, the worlds),
        which ``set_state`` writes.  ``limits``: {limited joint index: (lower (W,), upper (W,))},
        every world's bounds to check against in place of those in force (the vector env's
        set_state, which restores its parameters after the check)."""
        idx = self._worlds(worlds)
        arrays = self._state_arrays()
        if not isinstance(state, dict):
            raise TypeError(f"state must be a dict from get_state, got {type(state).__name__}")
        missing, unknown = (set(arrays) | {"time"}) - set(state), set(state) - set(arrays) - {"time"}
        if missing or unknown:
            raise ValueError(f"state must hold exactly get_state's entries: missing {sorted(missing)}, "
                             f"unknown {sorted(unknown)}")
        vals = {}
        for name, a in list(arrays.items()) + [("time", None)]:
            v = inputs.real_values(f"state[{name!r}]", state[name])
            scalar = None if a is None else getattr(a.dtype, "_wp_scalar_type_", a.dtype)
            dtype = np.float64 if a is None else np.dtype(wp.dtype_to_numpy(scalar))
            shape = (len(idx),) + (() if a is None else rows._row_shape(a))
            if v.dtype != dtype or v.shape != shape:
                raise ValueError(f"state[{name!r}] must be {np.dtype(dtype).name} of shape {shape} (this simulator's, "
                                 f"for {len(idx)} worlds), got {v.dtype} {v.shape}")  # fmt: skip
            vals[name] = v
        bodies, joints = [b.name for b in self.scene.bodies], [j.name for j in self.scene.joints]
        at = dict(worlds=idx, items=bodies, item="body", bound=self._state_bound)
        for name in ("q", "qd", "q_prev", "q_hist", "qd_hist", "qd_hist2"):
            _finite_array(f"state[{name!r}]", vals[name], vals[name].shape, **at)
        fixed = np.array([b.fixed for b in self.scene.bodies])
        inputs.check_rotations("state['q']", vals["q"][..., 3:].reshape(len(idx), -1, 3, 3).astype(np.float64), idx,
                               bodies, movable=~fixed)  # fmt: skip
        self._check_in_plane(idx, poses={f"state[{k!r}]": vals[k] for k in ("q", "q_prev", "q_hist")},
                             rates={f"state[{k!r}]": vals[k] for k in ("qd", "qd_hist", "qd_hist2")})  # fmt: skip
        if self.model.num_joints:
            coord = _finite_array("state['coord']", vals["coord"], vals["coord"].shape, idx, joints, "joint",
                                  self._state_bound)
            bounds = self._limit_bounds()
            for k, (lo, up) in (limits or {}).items():
                bounds[k] = (np.asarray(lo, np.float64), np.asarray(up, np.float64), bounds[k][2])
            check_within_limits("state['coord']", coord, idx, bounds, joints)
        bad = ~np.isin(vals["status"], [int(s) for s in WorldStatus])
        if bad.any():
            raise ValueError(f"state['status'] has an unknown code {vals['status'][bad][0]} in world "
                             f"{int(idx[np.argmax(bad)])}")
        return vals, idx

    def _write_state(self, vals: dict, idx):
        """Write get_state's values (unchecked) into the worlds idx."""
        for name, a in self._state_arrays().items():
            if self.device.is_cpu:
                self.host_view(a)[idx] = vals[name]
            else:
                full = a.numpy()
                full[idx] = vals[name]
                a.assign(full)
        self.state.time[idx] = vals["time"]

    # ------------------------------------------------------------------ per-world parameters
    def _update_K(self, idx):
        """Joint strengths K = strength_ratio·(m_i + m_j) of the worlds idx, written to their rows."""
        m = self.model
        self._energy_changed(idx)
        if not m.num_joints:
            return
        ia, ib = self._joint_bodies
        mass = self._mass[idx]
        self._write_rows(m.K, idx, self._ratio[idx] * (mass[:, ia] + mass[:, ib]))

    def _energy_changed(self, idx):
        """A parameter of the worlds idx changed their energy: the energy test computes it anew
        before their next step (State.energy NaN)."""
        self._write_rows(self.state.energy, idx, np.full((len(idx), 4), np.nan))

    def check_body_mass(self, mass, bodies=None, worlds=None):
        """``set_body_mass``'s checks alone (nothing is written): (world indices, body indices,
        the masses as float64 (N, len(bodies))), or a ValueError naming the world and the body."""
        m = self.model
        idx = self._worlds(worlds)
        bi = np.arange(m.num_bodies) if bodies is None else np.array([self.scene.body_index(b) for b in np.atleast_1d(bodies)])
        vals = _finite_array("mass", mass, (len(idx), len(bi)), idx, [self.scene.bodies[b].name for b in bi], "body",
                             bound=self._bound)  # fmt: skip
        if (vals <= 0).any():
            i, k = np.argwhere(vals <= 0)[0]
            raise ValueError(f"mass must be positive, got {vals[i, k]} in world {int(idx[i])}, "
                             f"body {self.scene.bodies[bi[k]].name!r}")  # fmt: skip
        return idx, bi, vals

    def set_body_mass(self, mass, bodies=None, worlds=None):
        """Per-world body masses [kg] (N, len(bodies)); every mass moment scales with it, and joint
        strengths K = strength_ratio·(m_i + m_j) follow."""
        m = self.model
        idx, bi, vals = self.check_body_mass(mass, bodies, worlds)
        self._mass[np.ix_(idx, bi)] = vals
        scale = self._mass[idx] / m.base_mass  # only the listed worlds' rows travel to the device
        idx_dev = rows.indices(idx, self._stage)
        self._write_rows(m.mass, idx_dev, m.base_mass * scale)
        self._write_rows(m.mc, idx_dev, m.base_mc[None] * scale[..., None])
        self._write_rows(m.S, idx_dev, m.base_S[None] * scale[..., None, None])
        self._update_K(idx)
        self._warn_conditioning(idx)

    def check_joint_strength(self, strength_ratio, joints=None, worlds=None):
        """``set_joint_strength``'s checks alone (nothing is written): (world indices, joint
        indices, the ratios as float64 (N, len(joints))), or a ValueError naming the world and the joint."""
        idx = self._worlds(worlds)
        ji = np.arange(self.model.num_joints) if joints is None else np.array([self.scene.joint_index(j) for j in np.atleast_1d(joints)])
        vals = _finite_array("strength_ratio", strength_ratio, (len(idx), len(ji)), idx,
                             [self.scene.joints[j].name for j in ji], "joint", bound=self._bound)  # fmt: skip
        if (vals <= 0).any():
            i, k = np.argwhere(vals <= 0)[0]
            raise ValueError(f"strength_ratio must be positive, got {vals[i, k]} in world {int(idx[i])}, "
                             f"joint {self.scene.joints[ji[k]].name!r}")  # fmt: skip
        return idx, ji, vals

    def set_joint_strength(self, strength_ratio, joints=None, worlds=None):
        """Per-world joint strength ratios (N, len(joints)): K = strength_ratio·(m_i + m_j)."""
        idx, ji, vals = self.check_joint_strength(strength_ratio, joints, worlds)
        self._ratio[np.ix_(idx, ji)] = vals
        self._update_K(idx)
        self._warn_conditioning(idx)

    def _warn_conditioning(self, idx):
        """The build's conditioning warnings (conditioning.unsolvable_worlds) for the worlds idx,
        after their masses or strength ratios changed."""
        dtype = "float32" if self.model.np_dtype == np.float32 else "float64"
        messages = conditioning.unsolvable_worlds(self.scene, self.dt, dtype, self._ratio[idx], self._mass[idx], idx)
        for message in messages:
            warnings.warn(message, RuntimeWarning, stacklevel=3)

    def set_limit(self, joint, lower=None, upper=None, strength=None, worlds=None, check_state=True):
        """Per-world bounds [rad or m] and strength [J] of a joint's limit (each (N,) or scalar).
        Checked before anything is written (``check_limit``): a bad value changes no world.  With
        ``check_state`` (the default), bounds that leave a world's current coordinate beyond them
        by more than the limit holds (inputs.check_within_limits) are refused; a caller that sets
        every such world's state right after (a reset) passes False."""
        kind, col, idx, new = self.check_limit(joint, lower, upper, strength, worlds, check_state)
        m, host = self.model, self._limits[kind]
        idx_dev = rows.indices(idx, self._stage)
        self._joint_bounds = None
        for h, v, dev_a in zip(host, new, m.limit_params[kind]):
            h[idx, col] = v
            self._write_rows(dev_a, idx_dev, h[idx])
        self._energy_changed(idx)

    def check_limit(self, joint, lower=None, upper=None, strength=None, worlds=None, check_state=True):
        """``set_limit``'s checks alone (nothing is written): (the joint's kind, its column among
        that kind's limits, the world indices, [lower, upper, strength] as float64 (N,) each), or
        a ValueError naming the joint and the world."""
        check_state = inputs.flag("check_state", check_state)
        m = self.model
        j = self.scene.joint_index(joint)
        kind = self.scene.joints[j].kind
        if kind not in m.limit_joints or j not in m.limit_joints[kind]:
            raise ValueError(f"joint {joint!r} has no limit")
        col = m.limit_joints[kind].index(j)
        idx = self._worlds(worlds)
        host = self._limits[kind]
        new = [h[idx, col].copy() for h in host]
        for k, (val, name) in enumerate(zip((lower, upper, strength), ("lower", "upper", "strength"))):
            if val is not None:
                bound = self._bound if name == "strength" else self._state_bound
                new[k] = _finite_array(name, val, (len(idx),), bound=bound).copy()
        lo, up, st = new

        def refuse(bad, what):
            k = int(np.argmax(bad))
            return ValueError(f"limit of joint {self.scene.joints[j].name!r} in world {int(idx[k])}: {what(k)}")

        if (lo > up).any():
            raise refuse(lo > up, lambda k: f"lower ({lo[k]}) must not exceed upper ({up[k]})")
        if (st <= 0).any():
            raise refuse(st <= 0, lambda k: f"strength must be positive, got {st[k]}")
        if kind == REVOLUTE and ((lo < -math.pi) | (up > math.pi)).any():
            raise refuse((lo < -math.pi) | (up > math.pi), lambda k: f"bounds [{lo[k]}, {up[k]}] must lie in [-pi, pi]")
        if check_state and len(idx):
            bounds = {j: (np.zeros(self.num_worlds), np.zeros(self.num_worlds), kind == REVOLUTE)}
            bounds[j][0][idx], bounds[j][1][idx] = lo, up
            names = [jt.name for jt in self.scene.joints]
            check_within_limits("set_limit", self.joint_coordinates()[idx], idx, bounds, names)
        return kind, col, idx, new
