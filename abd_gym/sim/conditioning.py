"""Stiffnesses a dtype cannot solve, found when a simulator is built.

Two dimensionless numbers compare a stiffness with the inertia it acts on:

- a joint's ``K/m`` [–]: its strength K = γ·(m_i + m_j) [kg] over the lighter of its free bodies'
  mass m [kg] (the penalty sits in E as is, beside the mass matrix);
- a body's ``4κ·vol·h²/λ_min(S)`` [–]: the orthogonality Hessian's scale 4κ·vol·h² [kg·m²] over the
  smallest eigenvalue of its second moment S [kg·m²], with h = dt [s].

A double pendulum of 1 kg, 0.5 m links fails in every world at its first steps (float32, dt 0.002 to
0.05) once a joint's K/m reaches 2e7 and a body's number 2e9; float64 fails at K/m 2e10 (dt 0.01) and
at a body number of 6e10 (dt 0.05), where Newton no longer converges within 50 iterations.  Below
float32's failure, at K/m 2e6, the solve still converges but its rounding shows: under BDF2 one of
64 double pendulums released from up to ±2 rad gained 12% of its swing energy in 1 s (dt 0.01;
``python -m abd_gym.bench robustness``, case strength_1e+06).  The limits below sit under those.
"""
from __future__ import annotations

import numpy as np

# dtype name -> (largest joint K/m, largest body 4κ·vol·h²/λ_min(S))
SOLVABLE = {"float32": (1e6, 5e8), "float64": (5e9, 1e10)}


def joint_numbers(scene, ratios=None) -> np.ndarray:
    """(num_joints,) K/m of each joint: K = γ·(m_i + m_j) over its lighter free body's mass
    (``ratios``: the scene's strength_ratios(), if already at hand)."""
    ratios = scene.strength_ratios() if ratios is None else ratios
    out = np.zeros(scene.num_joints)
    for k, j in enumerate(scene.joints):
        a, b = scene.bodies[j.body_a], scene.bodies[j.body_b]
        lightest = min(x.mass for x in (a, b) if not x.fixed)
        out[k] = ratios[k] * (a.mass + b.mass) / lightest
    return out


def body_numbers(scene, dt: float) -> np.ndarray:
    """(num_bodies,) 4κ·vol·dt²/λ_min(S) of each body (0 for a fixed one)."""
    out = np.zeros(scene.num_bodies)
    for k, b in enumerate(scene.bodies):
        if not b.fixed:
            out[k] = 4.0 * b.stiffness * b.shape.volume() * dt**2 / np.linalg.eigvalsh(b.moments.second_moment)[0]
    return out


def unsolvable(scene, dt: float, dtype: str) -> list[str]:
    """One message per joint or body whose stiffness relative to its inertia exceeds what
    ``dtype`` ("float32" or "float64") solves at step ``dt`` [s]."""
    joint_max, body_max = SOLVABLE[dtype]
    out = []
    ratios = scene.strength_ratios()  # (the joint graph's search, once)
    for k, n in enumerate(joint_numbers(scene, ratios)):
        if n > joint_max:
            j = scene.joints[k]
            ratio = ratios[k]
            out.append(f"joint {j.name!r}: strength ratio {ratio:.3g} gives K/m = {n:.3g} against its lighter body, "
                       f"above the {joint_max:.0e} that {dtype} solves reliably: lower strength_ratio below "
                       f"{ratio * joint_max / n:.3g}" + (" or use float64" if dtype == "float32" else ""))  # fmt: skip
    for k, n in enumerate(body_numbers(scene, dt)):
        if n > body_max:
            b = scene.bodies[k]
            out.append(f"body {b.name!r}: stiffness {b.stiffness:.3g} Pa gives 4κ·vol·dt²/λ_min(S) = {n:.3g} at dt {dt} s, "
                       f"above the {body_max:.0e} that {dtype} solves: lower stiffness below {b.stiffness * body_max / n:.3g} Pa "
                       "(or leave it to the default), or dt")  # fmt: skip
    return out


def unsolvable_worlds(scene, dt: float, dtype: str, ratios: np.ndarray, masses: np.ndarray, worlds) -> list[str]:
    """``unsolvable`` for per-world parameters: ``ratios`` (N, num_joints) strength ratios and
    ``masses`` (N, num_bodies) body masses [kg] of the worlds ``worlds`` (N,) (every mass moment
    scales with its mass, the orthogonality stiffness κ does not).  One message per joint or body
    that exceeds what ``dtype`` solves in any of them, naming those worlds and the largest number."""
    joint_max, body_max = SOLVABLE[dtype]
    out = []
    worlds = np.asarray(worlds)
    if scene.num_joints:
        ia = np.array([j.body_a for j in scene.joints])
        ib = np.array([j.body_b for j in scene.joints])
        fixed = np.array([b.fixed for b in scene.bodies])
        free_mass = np.where(fixed[None], np.inf, masses)
        lightest = np.minimum(free_mass[:, ia], free_mass[:, ib])
        numbers = ratios * (masses[:, ia] + masses[:, ib]) / lightest
        for k in np.flatnonzero((numbers > joint_max).any(axis=0)):
            over = numbers[:, k] > joint_max
            i = int(np.argmax(np.where(over, numbers[:, k], -np.inf)))
            out.append(f"joint {scene.joints[k].name!r} in worlds {_list(worlds[over])}: K/m up to {numbers[i, k]:.3g} "
                       f"(world {int(worlds[i])}: strength ratio {ratios[i, k]:.3g}) against its lighter body, above "
                       f"the {joint_max:.0e} that {dtype} solves reliably: lower the strength ratio or the mass ratio"
                       + (" or use float64" if dtype == "float32" else ""))  # fmt: skip
    base = np.array([b.mass for b in scene.bodies])
    numbers = body_numbers(scene, dt)[None] * base[None] / masses
    for k in np.flatnonzero((numbers > body_max).any(axis=0)):
        over = numbers[:, k] > body_max
        i = int(np.argmax(np.where(over, numbers[:, k], -np.inf)))
        out.append(f"body {scene.bodies[k].name!r} in worlds {_list(worlds[over])}: mass {masses[i, k]:.3g} kg (world "
                   f"{int(worlds[i])}) gives 4κ·vol·dt²/λ_min(S) = {numbers[i, k]:.3g} at dt {dt} s, above the "
                   f"{body_max:.0e} that {dtype} solves: raise the mass, or lower the stiffness or dt")  # fmt: skip
    return out


def _list(worlds, most=8) -> str:
    """The first ``most`` world indices as a list, with how many more there are."""
    head = [int(w) for w in worlds[:most]]
    return str(head) if len(worlds) <= most else f"{head} and {len(worlds) - most} more"


# the most a step may turn the scene's fastest pendulum mode [rad]: beyond it the step's motion is
# far from the prediction Newton starts from.  Measured (float64, 50 iterations, no retries):
# double pendulums of 0.5 m links (√(g/r) = 6.2 rad/s) released from ±2.5 rad at ±3 rad/s, 2 of
# 16 failed within 5 steps at dt 0.1 (0.62 rad a step), 10 at dt 0.2 (1.25); FourBar-v0's linkage
# (13.7 rad/s) from its reset distribution, 44 of 64 at its first step at dt 0.1 (1.37), 54 at 0.2
STEP_TURN = 1.0


def step_too_large(scene, dt: float) -> list[str]:
    """One message per free body whose fastest mode turns more than STEP_TURN rad in a step of
    ``dt`` [s]: a pendulum of its size under gravity, √(|g|/r) with r its bounding radius [m], or
    a position drive's stiffness kp over the inertia m·r² it moves, √(kp/(m·r²))."""
    g = float(np.linalg.norm(scene.gravity))
    rate = np.zeros(scene.num_bodies)
    for k, b in enumerate(scene.bodies):
        if not b.fixed:
            rate[k] = np.sqrt(g / b.shape.bounding_radius())
    for d in scene.drives:
        if d.mode == "position":
            k = scene.joints[d.joint].body_b
            b = scene.bodies[k]
            if not b.fixed:
                rate[k] = max(rate[k], np.sqrt(d.stiffness / (b.mass * b.shape.bounding_radius() ** 2)))
    out = []
    for k in np.flatnonzero(rate * dt > STEP_TURN):
        out.append(f"dt {dt} s is beyond what body {scene.bodies[k].name!r} can take: its fastest mode "
                   f"({rate[k]:.3g} rad/s, gravity or a position drive over its size) turns {rate[k] * dt:.2g} rad a "
                   f"step, above {STEP_TURN}; Newton then often fails to converge and steps are retried as substeps "
                   f"(Simulator.substeps): take dt below {STEP_TURN / rate[k]:.3g} s")  # fmt: skip
    return out
