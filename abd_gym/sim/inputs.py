"""Checks of the states a user sets: every error names the argument, the world, the joint or body
and the value, and nothing is written when one fails."""
from __future__ import annotations

import math

import numpy as np

from .scene import REVOLUTE


def finite_array(name, values, shape, worlds=None, items=None, item="index"):
    """``values`` broadcast to ``shape`` as float64; a non-finite entry raises a ValueError naming
    ``name``, its world (``worlds[i]`` of row i) and its item (``items[j]`` of column j)."""
    a = np.asarray(values, dtype=np.float64)
    try:
        a = np.broadcast_to(a, shape)
    except ValueError:
        raise ValueError(f"{name} must have shape {shape}, got {np.shape(values)}") from None
    if np.isfinite(a).all():  # the common case, without argwhere's cost
        return a
    at = tuple(np.argwhere(~np.isfinite(a))[0].tolist())
    if worlds is None or items is None or len(at) < 2:
        raise ValueError(f"{name} has a non-finite value {a[at]} at index {at}")
    raise ValueError(f"{name} has a non-finite value {a[at]} in world {int(worlds[at[0]])}, {item} {items[at[1]]!r}"
                     + (f" (index {at})" if len(at) > 2 else ""))  # fmt: skip


def check_joint_state(scene, x, xd, worlds, dt, limits):
    """Raise a ValueError for a joint state the step cannot start from.

    x, xd: (N, joints) coordinates [rad, m] and rates [rad/s, m/s] of the worlds ``worlds``;
    limits: {joint index: (lower (W,), upper (W,))} of the limited joints, per world.

    An unlimited revolute angle may lie outside [−π, π]: it is kept as the multi-turn angle.

    - A limited joint must start inside [lower, upper]: a limit's cubic starts from zero at its
      bound, and a state far beyond it starts the solve from an energy of any size.
    - A revolute rate must turn the joint less than π in one step (|ẋ|·dt < π): the step's
      incremental angle δ ∈ (−π, π] cannot tell a larger turn from one the other way.
    """
    names = [j.name for j in scene.joints]
    rev = np.array([j.kind == REVOLUTE for j in scene.joints], dtype=bool)
    if not rev.size:
        return

    def fail(mask, what):
        w, k = np.argwhere(mask)[0]
        return ValueError(what(int(worlds[w]), names[k], w, k))

    fast = rev & (np.abs(xd) * dt >= math.pi)
    if fast.any():
        raise fail(fast, lambda w, n, i, k: f"velocities: revolute joint {n!r} in world {w} has rate {float(xd[i, k])!r} rad/s, "
                                            f"which turns it by pi or more in one step of {dt} s (|rate| < {math.pi / dt:.4g})")  # fmt: skip
    for k, (lower, upper) in limits.items():
        lo, up = lower[worlds], upper[worlds]
        bad = (x[:, k] < lo) | (x[:, k] > up)
        if bad.any():
            i = int(np.argmax(bad))
            raise ValueError(f"coordinates: joint {names[k]!r} in world {int(worlds[i])} is at {float(x[i, k])!r}, outside its "
                             f"limit [{float(lo[i])!r}, {float(up[i])!r}]")  # fmt: skip


def check_body_spin(scene, omega, worlds, dt):
    """Raise a ValueError where a free body's angular velocity ω (N, bodies, 3) [rad/s] turns it by π
    or more in one step of ``dt`` [s] (|ω|·dt ≥ π): the step's incremental joint angles lie in
    (−π, π], and a turn that large leaves A's Newton solve starting from a state whose rounding is
    metres."""
    free = np.array([not b.fixed for b in scene.bodies], dtype=bool)
    fast = (np.linalg.norm(omega, axis=-1) * dt >= math.pi) & free
    if fast.any():
        i, b = np.argwhere(fast)[0]
        raise ValueError(f"angular_velocities: body {scene.bodies[b].name!r} in world {int(worlds[i])} turns at "
                         f"{float(np.linalg.norm(omega[i, b]))!r} rad/s, which turns it by pi or more in one step of "
                         f"{dt} s (|omega| < {math.pi / dt:.4g})")  # fmt: skip
