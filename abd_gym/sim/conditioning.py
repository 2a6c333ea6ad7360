"""Stiffnesses a dtype cannot solve, found when a simulator is built.

Two dimensionless numbers compare a stiffness with the inertia it acts on:

- a joint's ``K/m`` [–]: its strength K = γ·(m_i + m_j) [kg] over the lighter of its free bodies'
  mass m [kg] (the penalty sits in E as is, beside the mass matrix);
- a body's ``4κ·vol·h²/λ_min(S)`` [–]: the orthogonality Hessian's scale 4κ·vol·h² [kg·m²] over the
  smallest eigenvalue of its second moment S [kg·m²], with h = dt [s].

Past a limit of its dtype the Newton solve of a step fails (a factor breaks down, or it does not
converge within its iterations); somewhat below it, it still converges but its rounding shows (a
BDF2 world gains energy).  SOLVABLE sits under both, for each dtype (docs/design.md §1 and §3.1,
"Solvable range"; docs/robustness.md, ``python -m abd_gym.bench robustness``, the strength cases).
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
# far from the prediction Newton starts from, and Newton often fails to converge (docs/robustness.md:
# the large_dt and fourbar cases of ``python -m abd_gym.bench robustness``)
STEP_TURN = 1.0


# the turn a step of the scene's fastest gravity mode [rad] past which the energy test runs by
# default (``task_energy_gain``, for simulators and vector envs alike): BDF2's large steps gain energy in many worlds from about
# 0.19 rad a step on (docs/robustness.md), while at the tasks' own steps a policy's drives push in
# every step, so the test would never run there and would only cost each env step its check
# (figures: docs/design.md §4.1, results/energy_gain_tasks_cpu.json)
ENERGY_TEST_TURN = 0.16


def task_energy_gain(scene, dt: float) -> float:
    """The energy test's default tolerance (Simulator's energy_gain None): 0.05 where a step
    turns the scene's fastest gravity mode past ENERGY_TEST_TURN, else 0 (off)."""
    return 0.05 if gravity_turn(scene, dt) > ENERGY_TEST_TURN else 0.0


def gravity_turn(scene, dt: float) -> float:
    """The most a step of ``dt`` [s] turns a free body's gravity mode √(|g|/r) (r its bounding
    radius) [rad]; 0 without gravity or free bodies."""
    g = float(np.linalg.norm(scene.gravity))
    rates = [np.sqrt(g / b.shape.bounding_radius()) for b in scene.bodies if not b.fixed]
    return float(max(rates, default=0.0)) * dt


def step_too_large(scene, dt: float) -> list[str]:
    """One message per body or drive whose mode turns more than STEP_TURN rad in a step of ``dt``
    [s]: a free body as a pendulum of its size under gravity, √(|g|/r) with r its bounding radius
    [m]; a position drive as the spring-damper of its stiffness kp and damping kv (the joint's
    passive damping added) on what it moves, I the inertia of the bodies beyond the joint about
    its axis (a slide: their mass): ω₀ = √(kp/I) where it oscillates (ζ = kv/(2√(kp·I)) < 1),
    else its slow mode ω₀(ζ − √(ζ² − 1)) ≈ kp/kv (its fast mode only decays, which the implicit
    step damps in any step)."""
    g = float(np.linalg.norm(scene.gravity))
    modes = []  # (rate [rad/s], what)
    for b in scene.bodies:
        if not b.fixed:
            modes.append((np.sqrt(g / b.shape.bounding_radius()), f"body {b.name!r} (gravity over its size)"))
    for d in scene.drives:
        if d.mode == "position":
            inertia = driven_inertia(scene, d.joint)
            if inertia > 0.0 and d.stiffness > 0.0:
                w0 = np.sqrt(d.stiffness / inertia)
                zeta = (d.damping + scene.joints[d.joint].damping) / (2.0 * np.sqrt(d.stiffness * inertia))
                modes.append((w0 if zeta < 1.0 else w0 * (zeta - np.sqrt(zeta * zeta - 1.0)),
                              f"the position drive of joint {scene.joints[d.joint].name!r} (its stiffness over "
                              f"what it moves)"))  # fmt: skip
    out = []
    for rate, what in modes:
        if rate * dt > STEP_TURN:
            out.append(f"dt {dt} s is beyond what {what} can take: its mode of {rate:.3g} rad/s turns {rate * dt:.2g} "
                       f"rad a step, above {STEP_TURN}; Newton then often fails to converge and steps are retried as "
                       f"substeps (Simulator.substeps): take dt below {STEP_TURN / rate:.3g} s")  # fmt: skip
    return out


def driven_inertia(scene, joint: int) -> float:
    """What a drive on ``joint`` moves: the free bodies reached from its second body without
    crossing the joint, as their moment of inertia about its hinge axis [kg·m²] (revolute) or
    their mass [kg] (prismatic), at the scene's pose."""
    j = scene.joints[joint]
    others = [k for k, jt in enumerate(scene.joints) if k != joint]
    seen, todo = {j.body_b}, [j.body_b]
    while todo:
        b = todo.pop()
        for k in others:
            jt = scene.joints[k]
            for here, there in ((jt.body_a, jt.body_b), (jt.body_b, jt.body_a)):
                if here == b and there not in seen and not scene.bodies[there].fixed:
                    seen.add(there)
                    todo.append(there)
    bodies = [scene.bodies[k] for k in seen if not scene.bodies[k].fixed]
    if j.kind != "revolute":
        return float(sum(b.mass for b in bodies))
    u = j.frame[0] / np.linalg.norm(j.frame[0])
    across = np.eye(3) - np.outer(u, u)  # projection onto the plane normal to the axis
    total = 0.0
    for b in bodies:
        m, R = b.moments, b.rotation
        d = b.position - j.anchor
        first = R @ (m.mass * m.com)
        # ∫ρ (x − a)(x − a)ᵀ dV in world axes, x = p + R x̄ over the body
        second = R @ m.second_moment @ R.T + np.outer(first, d) + np.outer(d, first) + m.mass * np.outer(d, d)
        total += float(np.trace(across @ second))
    return total


def default_max_iterations(scene) -> int:
    """Newton's iteration budget a step for ``scene`` (SolverSettings.max_iterations where none is
    given): ITERATIONS, plus ITERATIONS a decade of its largest joint K/m past STIFF_JOINT."""
    worst = float(np.max(joint_numbers(scene), initial=0.0))
    if not worst > STIFF_JOINT:
        return ITERATIONS
    return ITERATIONS + int(np.ceil(ITERATIONS * np.log10(worst / STIFF_JOINT)))
