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

# Newton's default budget a step, where no joint's K/m exceeds STIFF_JOINT; past it, ITERATIONS more
# per decade of the largest K/m.  A light body between heavy ones (a 30-link chain with link masses
# from 1e-3 to 1e2 kg, K/m 2e7) carries loads far beyond its own weight through its deformation, which
# the orthogonality Hessian's PSD part (affine_body) overestimates: its worlds converge only linearly
# for tens of iterations (docs/performance.md, "A 30-link 3-D chain of mixed masses").
ITERATIONS = 50
STIFF_JOINT = 1e4


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


def default_max_iterations(scene) -> int:
    """Newton's iteration budget a step for ``scene`` (SolverSettings.max_iterations where none is
    given): ITERATIONS, plus ITERATIONS a decade of its largest joint K/m past STIFF_JOINT."""
    worst = float(np.max(joint_numbers(scene), initial=0.0))
    if not worst > STIFF_JOINT:
        return ITERATIONS
    return ITERATIONS + int(np.ceil(ITERATIONS * np.log10(worst / STIFF_JOINT)))
