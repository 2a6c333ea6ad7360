"""The checks every door applies to what a user passes in: the scene's builders, the simulator's
constructor and setters, ``step``.  Every error names the argument (and, for per-world values, the
world and the joint or body) and the value, and a caller checks before it writes anything.

The rules, one for every door:

- numbers are real: NumPy's integer and floating types (np.float32, np.int64, 0-d arrays) count
  as numbers; complex, object, string and bool values are a TypeError;
- values are finite; states no larger than ``state_bound(dtype)`` (1/eps: a larger one has no
  digit left below the metre), parameters no larger than ``magnitude_bound(dtype)`` (their energies
  overflow beyond it);
- counts (worlds, steps, iterations) are integers of an integer type, at least their minimum;
- world indices are integers in [0, num_worlds), each listed once, or a bool mask of every world;
- a rotation part is a rotation: ‖AAᵀ − I‖_F ≤ ROTATION_TOL and det A > 0;
- a limited joint lies within its bounds widened by the limit's own scale (``limit_scale``): the
  penetration at which the limit's energy reaches its strength, as much as it can hold.  A state a
  step produced lies inside that (a limit's penetration grows as (S dt²/s)^(1/3) of that scale
  with the swing energy S that reaches a limit of strength s, docs/design.md §3.3).
"""
from __future__ import annotations

import math
import numbers

import numpy as np

# ‖AAᵀ − I‖_F a rotation part may have: a step's A is orthonormal only up to the orthogonality
# penalty's strain (under 1e-3 in the bench mechanisms); a zero, scaled or sheared matrix is far
# beyond it, a reflection has det −1
ROTATION_TOL = 0.05
# NumPy dtype kinds accepted as numbers: signed and unsigned integers, floats
REAL_KINDS = "iuf"


def real_values(name, values) -> np.ndarray:
    """``values`` as a NumPy array of a real number kind (unconverted), else a TypeError."""
    try:
        a = np.asarray(values)
    except (TypeError, ValueError) as e:  # ragged nesting, objects NumPy cannot hold
        raise TypeError(f"{name} must be an array of real numbers, got {type(values).__name__} ({e})") from None
    if a.dtype.kind not in REAL_KINDS:
        raise TypeError(f"{name} must be real numbers (integer or float), got dtype {a.dtype}")
    return a


def magnitude_bound(np_dtype) -> float:
    """The largest |value| of a parameter (mass, strength, control) in ``np_dtype``: its fourth
    power, as far as the energies raise a value, stays finite."""
    return float(np.finfo(np_dtype).max) ** 0.25


def state_bound(np_dtype) -> float:
    """The largest |value| of a state (position [m], velocity [m/s], coordinate, rate, a bound) in
    ``np_dtype``: 1/eps, beyond which the value's rounding exceeds 1 m (or 1 m/s), so that a step's
    increment below it is lost."""
    return 1.0 / float(np.finfo(np_dtype).eps)


def finite_array(name, values, shape, worlds=None, items=None, item="index", bound=math.inf):
    """``values`` broadcast to ``shape`` as float64.  A TypeError for non-real values; a ValueError
    for a wrong shape, or a non-finite entry or one above ``bound`` in magnitude, naming ``name``,
    its world (``worlds[i]`` of row i) and its item (``items[j]`` of column j)."""
    a = real_values(name, values).astype(np.float64, copy=False)
    if a.shape != shape:
        try:
            a = np.broadcast_to(a, shape)
        except ValueError:
            raise ValueError(f"{name} must have shape {shape}, got {np.shape(values)}") from None
    # the common case in one product: Σ a² is NaN or inf where an entry is, and below (bound/2)²
    # only where every |entry| is below the bound (by a margin that rounding cannot cross); vdot,
    # unlike dot, does not warn where Σ a² overflows (huge entries, refused below by name)
    flat = a.ravel()
    if np.vdot(flat, flat) < (0.25 * bound * bound if bound < math.inf else math.inf):
        return a
    bad = ~np.isfinite(a)
    if bound < math.inf:
        bad |= np.abs(a) > bound
    if not bad.any():  # (large entries within the bound)
        return a
    at = tuple(np.argwhere(bad)[0].tolist())
    what = f"a non-finite value {a[at]}" if not np.isfinite(a[at]) else f"a value {a[at]} beyond ±{bound:.3g}"
    raise ValueError(f"{name} has {what}{_where(at, worlds, items, item)}")


def _where(at, worlds, items, item) -> str:
    """" in world w, item 'name'" of an index tuple (row: world, column: item), or " at index at"."""
    if worlds is None or items is None or len(at) < 2:
        return f" at index {at}"
    return f" in world {int(worlds[at[0]])}, {item} {items[at[1]]!r}" + (f" (index {at})" if len(at) > 2 else "")


def real_number(name, value, positive=False, nonnegative=False, allow_inf=False) -> float:
    """A real scalar (Python or NumPy int or float, or a 0-d array of one) as a float; a TypeError
    for anything else (bool, complex, str), a ValueError for NaN, an infinity (unless
    ``allow_inf``: +inf), or a value not positive / negative where asked."""
    a = real_values(name, value)
    if a.ndim != 0 or isinstance(value, (bool, np.bool_)):
        raise TypeError(f"{name} must be a real number, got {value!r}")
    v = float(a)
    if math.isnan(v) or (math.isinf(v) and not (allow_inf and v > 0)):
        raise ValueError(f"{name} must be finite, got {value!r}")
    if positive and not v > 0.0:
        raise ValueError(f"{name} must be positive, got {value!r}")
    if nonnegative and v < 0.0:
        raise ValueError(f"{name} must be non-negative, got {value!r}")
    return v


def count(name, value, minimum=0) -> int:
    """An integer count (Python or NumPy integer, not bool) of at least ``minimum``."""
    if type(value) is int and value >= minimum:  # the common case, before the abstract type checks
        return value
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (numbers.Integral, np.integer)):
        raise TypeError(f"{name} must be an integer, got {value!r}")
    if value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def flag(name, value) -> bool:
    """A bool (Python's or NumPy's); a TypeError for anything else (a string, a number, None)."""
    if not isinstance(value, (bool, np.bool_)):
        raise TypeError(f"{name} must be True or False, got {value!r}")
    return bool(value)


def seed(value):
    """A random seed: None, or an integer (Python or NumPy, not bool) >= 0, as a Python int."""
    return None if value is None else count("seed", value)


def world_indices(worlds, num_worlds) -> np.ndarray:
    """``worlds`` (None: every world; an integer or integer array; a bool mask (num_worlds,)) as
    int64 indices, each in [0, num_worlds) and listed once."""
    if worlds is None:
        return np.arange(num_worlds)
    try:
        w = np.asarray(worlds)
    except (TypeError, ValueError):
        raise TypeError(f"worlds must be integer world indices or a bool mask, got {worlds!r}") from None
    if w.dtype == np.bool_:
        if w.shape != (num_worlds,):
            raise ValueError(f"a world mask must have shape ({num_worlds},), got {w.shape}")
        return np.flatnonzero(w)
    if w.dtype.kind not in "iu" and not (w.size == 0 and w.dtype.kind == "f"):  # [] is float64
        raise TypeError(f"worlds must be integer world indices or a bool mask, got dtype {w.dtype}: {worlds!r}")
    w = w.astype(np.int64).reshape(-1)
    if w.size == 1 and 0 <= w[0] < num_worlds:  # one world, without the reductions
        return w
    if w.size and (w.min() < 0 or w.max() >= num_worlds):
        raise ValueError(f"world indices must lie in [0, {num_worlds}), got {w.tolist()}")
    if w.size > 1 and np.unique(w).size != w.size:
        raise ValueError(f"world indices must be listed once each, got {w.tolist()}")
    return w


def check_rotations(name, R, worlds, items, item="body", movable=None):
    """Raise a ValueError where a rotation part R (N, items, 3, 3) is not a rotation: ‖RRᵀ − I‖_F
    above ROTATION_TOL, or det R ≤ 0 (a reflection).  ``movable`` (items,) bool: the items checked."""
    strain = np.linalg.norm(R @ np.swapaxes(R, -1, -2) - np.eye(3), axis=(-2, -1))
    bad = (strain > ROTATION_TOL) | (np.linalg.det(R) <= 0.0)
    if movable is not None:
        bad &= movable
    if bad.any():
        i, b = np.argwhere(bad)[0]
        det = float(np.linalg.det(R[i, b]))
        why = f"det R = {det:.3g} <= 0" if det <= 0.0 else f"|R R^T - I| = {float(strain[i, b]):.3g} > {ROTATION_TOL}"
        raise ValueError(f"{name}: {item} {items[b]!r} in world {int(worlds[i])} is not a rotation ({why}): "
                         f"{R[i, b].tolist()}")  # fmt: skip


# how far a held entry of a planar scene's body state (sim/planar.py) may be off its scene value: q's
# rounding, far below any motion out of the plane
PLANE_TOL = 1e-9


def check_in_plane(name, q, worlds, items, held, q0, movable, velocity=False):
    """Raise a ValueError where a planar-reduced scene's body state (N, items, 12) would leave the
    plane: an entry the step holds (``held``: sim.planar.Plane.held) off the body's scene value
    ``q0`` (items, 12) (a velocity's: off 0) by more than PLANE_TOL·(1 + |value|).  The scene is
    solved in its plane only (Scene.planar); a state out of it is refused, never projected."""
    held = list(held)
    ref = np.zeros_like(q[..., held]) if velocity else np.broadcast_to(q0[:, held], q[..., held].shape)
    off = np.abs(q[..., held] - ref) > PLANE_TOL * (1.0 + np.abs(ref))
    off &= np.asarray(movable)[None, :, None]
    if off.any():
        i, b, k = np.argwhere(off)[0]
        r = held[k]
        entry = f"p[{r}]" if r < 3 else f"A[{(r - 3) // 3}, {(r - 3) % 3}]"
        raise ValueError(f"{name}: body {items[b]!r} in world {int(worlds[i])} leaves the plane the scene is solved "
                         f"in: {entry} = {float(q[i, b, r]):.9g}, held at {float(ref[i, b, k]):.9g} (Scene.planar=False "
                         f"solves the scene in 3-D)")  # fmt: skip


def limit_scale(revolute: bool, lower, upper):
    """The penetration of a limit at which its energy reaches its strength s: 1 rad for a revolute
    limit (E = s·d³), the range width u − l for a prismatic one (E = s·(d/(u − l))³), and 1 m for
    a prismatic one with u = l (E = s·d³, libuipc's fallback)."""
    lower, upper = np.asarray(lower, dtype=np.float64), np.asarray(upper, dtype=np.float64)
    if revolute:
        return np.ones_like(lower)
    return np.where(upper > lower, upper - lower, 1.0)


def check_within_limits(name, x, worlds, limits, names):
    """Raise a ValueError where a limited joint's coordinate x[:, k] (N, joints) lies beyond its
    bounds by more than the limit's scale.  limits: {joint index: (lower (W,), upper (W,),
    revolute)}, per world (indexed by ``worlds``)."""
    for k, (lower, upper, revolute) in limits.items():
        lo, up = lower[worlds], upper[worlds]
        slack = limit_scale(revolute, lo, up)
        bad = (x[:, k] < lo - slack) | (x[:, k] > up + slack)
        if bad.any():
            i = int(np.argmax(bad))
            unit = "rad" if revolute else "m"
            raise ValueError(f"{name}: joint {names[k]!r} in world {int(worlds[i])} is at {float(x[i, k])!r}, outside its "
                             f"limit [{float(lo[i])!r}, {float(up[i])!r}] by more than the limit holds "
                             f"({float(slack[i]):.4g} {unit}, where its energy reaches its strength)")  # fmt: skip


def max_turn(integrator: str, substeps: int = 1) -> float:
    """The largest |rate|·dt [rad] a revolute joint's state may have, as much as a step produces: a
    step turns the joint by δ ∈ (−π, π] (all it can tell), its rate is δ/h under implicit Euler
    and (3δⁿ⁺¹ − δⁿ)/(2h), up to 2π/h, under BDF2; a step retried as ``substeps`` implicit Euler
    substeps (solver/retry.py) ends at a substep's rate, up to π·substeps/h."""
    return max(2.0 * math.pi if integrator == "bdf2" else math.pi, math.pi * substeps)


def joint_state_bounds(limits, revolute, num_worlds, turn=math.pi):
    """``check_joint_state``'s bounds as arrays, for ``joint_state_ok``: (lower, upper), each
    (num_worlds, joints), every limited joint's bounds widened by the limit's scale
    (``limit_scale``; −inf and +inf for a joint without a limit), and (joints,) the bound of
    |rate|·dt, ``turn`` (``max_turn``) for a revolute joint, +inf for another.  ``limits`` as for
    ``check_within_limits``, ``revolute`` (joints,) bool."""
    revolute = np.asarray(revolute, dtype=bool)
    lower, upper = np.full((num_worlds, revolute.size), -np.inf), np.full((num_worlds, revolute.size), np.inf)
    for k, (lo, up, rev) in limits.items():
        slack = limit_scale(rev, lo, up)
        lower[:, k], upper[:, k] = lo - slack, up + slack
    return lower, upper, np.where(revolute, turn, np.inf)


def joint_state_ok(x, xd, worlds, dt, bounds) -> bool:
    """Whether ``check_joint_state`` passes the finite joint state x, xd (N, joints) of the worlds
    ``worlds``: its comparisons on whole arrays, against ``joint_state_bounds``'s ``bounds``.
    Where it is False, ``check_joint_state`` finds and names the joint."""
    lower, upper, turn = bounds
    if lower.shape[0] > 1:  # (of one world, the worlds are [0])
        lower, upper = lower[worlds], upper[worlds]
    bad = (x < lower) | (x > upper)
    bad |= np.abs(xd) * dt >= turn
    return not np.count_nonzero(bad)


def check_joint_state(names, revolute, x, xd, worlds, dt, limits, turn=math.pi):
    """Raise a ValueError for a joint state the step cannot start from.

    names, revolute: (joints,) the joints' names and whether each is revolute; x, xd: (N, joints)
    coordinates [rad, m] and rates [rad/s, m/s] of the worlds ``worlds``; limits as for
    ``check_within_limits``; ``turn``: ``max_turn`` of the integrator.

    An unlimited revolute angle may lie outside [−π, π]: it is kept as the multi-turn angle.

    - A limited joint must lie within its bounds widened by the limit's scale
      (``check_within_limits``): beyond, the limit's cubic starts the solve from an energy above
      its strength, which no state a step produced has.
    - A revolute rate must turn the joint less than ``turn`` in one step (|ẋ|·dt < turn): the
      step's incremental angle δ ∈ (−π, π] cannot tell a larger turn from one the other way, and
      a BDF2 step's rate reaches 2π/h from two turns below π each (``max_turn``).
    """
    rev = np.asarray(revolute, dtype=bool)
    if not rev.size:
        return
    fast = rev & (np.abs(xd) * dt >= turn)
    if fast.any():
        i, k = np.argwhere(fast)[0]
        raise ValueError(f"velocities: revolute joint {names[k]!r} in world {int(worlds[i])} has rate {float(xd[i, k])!r} rad/s, "
                         f"which turns it by {turn / math.pi:g} pi or more in one step of {dt} s "
                         f"(|rate| < {turn / dt:.4g})")  # fmt: skip
    check_within_limits("coordinates", x, worlds, limits, names)


def check_body_spin(scene, omega, worlds, dt, turn=math.pi):
    """Raise a ValueError where a free body's angular velocity ω (N, bodies, 3) [rad/s] turns it by
    ``turn`` or more in one step of ``dt`` [s] (|ω|·dt ≥ turn): the step's incremental joint angles
    lie in (−π, π], and a turn that large leaves A's Newton solve starting from a state whose
    rounding is metres.  ``turn``: ``max_turn`` of the integrator, what a step produces (a body's
    rate, like a joint's, is a BDF2 combination of two turns or a quarter substep's)."""
    free = np.array([not b.fixed for b in scene.bodies], dtype=bool)
    fast = (np.linalg.norm(omega, axis=-1) * dt >= turn) & free
    if fast.any():
        i, b = np.argwhere(fast)[0]
        raise ValueError(f"angular_velocities: body {scene.bodies[b].name!r} in world {int(worlds[i])} turns at "
                         f"{float(np.linalg.norm(omega[i, b]))!r} rad/s, which turns it by {turn / math.pi:g} pi or "
                         f"more in one step of {dt} s (|omega| < {turn / dt:.4g})")  # fmt: skip
