"""Whether a scene moves in a plane, and its 6 in-plane unknowns a body (docs/design.md §1, "Planar scenes").

A scene is planar about the world axis ``a`` (its normal n = e_a) where

- every hinge axis (revolute joint) is parallel to n and every slide (prismatic joint) lies in the
  plane ⟂ n;
- gravity lies in that plane, or along n where every free body is joined (through joints) to a
  fixed body that holds it;
- every free body starts turned about n only (row a and column a of its rotation are ±e_a), with
  its velocity in the plane (no out-of-plane translation, spin about n only);
- the scene's data is symmetric under the reflection x_a → −x_a of each body's frame: the first
  moment m c̄ and the second moment S couple nothing to the body's axis a (c̄_a = 0, S_aj = 0 for
  j ≠ a), every joint point lies at x̄_a = 0 or in a pair mirrored through it, and every joint
  frame vector lies in the plane or along n.

Then every term's energy is even in the out-of-plane coordinates about the plane state (the
reflection maps a planar state to itself), so their gradient is zero there and the 12-unknown
Newton step never leaves the plane: solving the 6 in-plane unknowns of each body (p_i and A_ij for
i, j ≠ a) with the other 6 held gives the same step.  Gravity along n (the Reachers, lying flat)
pulls the 12-unknown bodies out of the plane against their joints by m g/K and does no work in the
plane; the planar scene holds them in it.

``Scene.planar``: None (the default) reduces a scene that meets every rule; True reduces one that
meets the kinematic rules (axes, gravity, starts) and raises where it does not (the data's symmetry
is then not required: the bodies are held in the plane, as a rigid body on a planar hinge is);
False keeps 12 unknowns a body.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .scene import FIXED, PRISMATIC, REVOLUTE, Scene

# a relative tolerance for "parallel", "in the plane" and "zero" on the scene's float64 data, which
# carries ~1e-16 of rounding where a value computed through a rotation is exactly 0
TOL = 1e-9


@dataclass(frozen=True)
class Plane:
    """A planar scene's normal axis and its body layout."""

    axis: int  # the normal n = e_axis (0: x, 1: y, 2: z)

    @property
    def keep(self) -> tuple:
        """The in-plane world axes (i ≠ axis), in order."""
        return tuple(i for i in range(3) if i != self.axis)

    @property
    def dofs(self) -> tuple:
        """The 6 of a body's 12 coordinates (p, a1, a2, a3; a_k the rows of A) that move: p_i and
        A_ij for i, j in ``keep``."""
        i, j = self.keep
        return (i, j) + tuple(3 + 3 * r + c for r in (i, j) for c in (i, j))

    @property
    def held(self) -> tuple:
        """The 6 coordinates held at their values."""
        return tuple(r for r in range(12) if r not in self.dofs)

    def __str__(self) -> str:
        return "xyz"[self.keep[0]] + "xyz"[self.keep[1]]


def _small(v, scale=1.0) -> bool:
    return bool(np.all(np.abs(np.asarray(v, dtype=np.float64)) <= TOL * max(scale, 1.0)))


def _normal_axis(scene: Scene):
    """(axis, why not): the normal from the hinge axes, else from gravity, else z."""
    hinges = [j.frame[0] for j in scene.joints if j.kind == REVOLUTE]
    for t in hinges:
        a = int(np.argmax(np.abs(t)))
        if _small(np.delete(t, a)):
            return a, None
        return None, f"hinge axis {np.round(t, 6).tolist()} is not along a world axis"
    slides = [j.frame[0] for j in scene.joints if j.kind == PRISMATIC]
    g = scene.gravity
    for a in (1, 0, 2):  # without hinges: a plane holding every slide and gravity (xz first)
        if all(_small(t[a]) for t in slides) and _small(g[a], np.abs(g).max()):
            return a, None
    return None, "no world plane holds every slide and gravity"


def _held_by_fixed(scene: Scene) -> bool:
    """Whether every free body is joined, through joints, to a fixed body (which then holds it
    against gravity along the plane's normal)."""
    held = {k for k, b in enumerate(scene.bodies) if b.fixed}
    grew = True
    while grew:
        grew = False
        for j in scene.joints:
            if (j.body_a in held) != (j.body_b in held):
                held |= {j.body_a, j.body_b}
                grew = True
    return len(held) == scene.num_bodies


def kinematic_reasons(scene: Scene, a: int) -> list:
    """Why the scene does not move in the plane ⟂ e_a: axes, gravity and the bodies' starts."""
    why = []
    g, gs = scene.gravity, float(np.abs(scene.gravity).max())
    if not (_small(g[a], gs) or _small(np.delete(g, a), gs)):
        why.append(f"gravity {g.tolist()} is neither in the plane nor along its normal")
    elif not _small(g[a], gs) and not _held_by_fixed(scene):
        why.append(f"gravity {g.tolist()} lies along the plane's normal and a body is not joined to a fixed one")
    for j in scene.joints:
        t = j.frame[0]
        if j.kind == REVOLUTE and not _small(np.delete(t, a)):
            why.append(f"joint {j.name!r}: hinge axis {np.round(t, 6).tolist()} is not along the normal")
        if j.kind == PRISMATIC and not _small(t[a]):
            why.append(f"joint {j.name!r}: slide axis {np.round(t, 6).tolist()} leaves the plane")
    for b in scene.bodies:
        if b.fixed:
            continue
        R = b.rotation
        if not (_small(np.delete(R[a], a)) and _small(np.delete(R[:, a], a))):
            why.append(f"body {b.name!r} starts turned out of the plane (rotation {np.round(R, 6).tolist()})")
        if not _small(b.linear_velocity[a]) or not _small(np.delete(b.angular_velocity, a)):
            why.append(f"body {b.name!r} starts moving out of the plane")
    return why


def symmetry_reasons(scene: Scene, a: int) -> list:
    """Where the scene's data is not mirror-symmetric about each body's plane x̄_a = 0 (the rule
    that makes the 12-unknown step stay in the plane exactly)."""
    why = []
    for b in scene.bodies:
        if b.fixed:
            continue
        c, S = b.moments.com, b.moments.second_moment
        if not _small(c[a], np.abs(c).max()) or not _small(np.delete(S[a], a), np.abs(S).max()):
            why.append(f"body {b.name!r}: its mass is not symmetric about its plane (com {np.round(c, 9).tolist()})")
    for j in scene.joints:
        for k in (j.body_a, j.body_b):
            body = scene.bodies[k]
            if body.fixed:
                continue
            size = max(1.0, float(np.abs(j.anchor).max()))
            anchor = body.to_local_point(j.anchor)
            if not _small(anchor[a], size):
                why.append(f"joint {j.name!r}: its anchor lies off body {body.name!r}'s plane")
            if j.kind == FIXED:  # its points anchor + L e_k include one off the plane, not mirrored
                why.append(f"joint {j.name!r}: a fixed joint's points are not mirrored about the plane")
            for v in j.frame:
                d = body.to_local_dir(v)
                if not (_small(d[a]) or _small(np.delete(d, a))):
                    why.append(f"joint {j.name!r}: a frame vector is neither in body {body.name!r}'s plane nor normal to it")
                    break
    return why


def plane_of(scene: Scene):
    """The scene's ``Plane`` (6 unknowns a body), or None (12), as ``scene.planar`` asks; raises
    ValueError where ``planar`` is True and the scene does not move in a plane."""
    mode = getattr(scene, "planar", None)
    if mode is False:
        return None
    a, why = _normal_axis(scene)
    reasons = [why] if why else kinematic_reasons(scene, a)
    if mode is True:
        if reasons:
            raise ValueError("Scene.planar is True but the scene does not move in a plane: " + "; ".join(reasons))
        return Plane(a)
    return None if reasons or symmetry_reasons(scene, a) else Plane(a)


def explain(scene: Scene) -> list:
    """Every reason the scene is not reduced automatically (empty: it is)."""
    a, why = _normal_axis(scene)
    return [why] if why else kinematic_reasons(scene, a) + symmetry_reasons(scene, a)
