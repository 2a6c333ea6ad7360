"""The gap that joint coordinates leave at a closed loop's closing joints, on the host in float64.

``set_joint_state`` places the bodies along a spanning tree of the joints (``kinematics``) and
leaves a joint between two placed bodies, one that closes a loop, to the coordinates given: they
must close it.  ``LoopCheck`` places the bodies as the device kernel does (positions and rotations,
no rates) and measures each closing joint's gap in metres:

- revolute and fixed joints: the largest distance between a point of the joint as its first body
  carries it and the same point as its second body carries it (the points of the joint's energy,
  ``anchor ± L·t̂``, or ``anchor`` and ``anchor + L·e_k``);
- prismatic joints: the larger of the bodies' offset across the axis (the seed's C0 and C1) and
  the misalignment of their frames at the joint's length, L·‖n̂_i − n̂_j‖ and L·‖b̂_i − b̂_j‖.

L is the joint's ``half_length``, its own scale (by default the larger body's bounding radius).  A
gap up to ``LOOP_TOL``·L is accepted: a state a step produced reads back joint coordinates whose
placement reopens the loop by the joints' penalty stretch, which the tree's placement moves to the
closing joint (measured on the four-bar and the slider-crank at dt up to 0.2 s: docs/design.md §5).
Coordinates from another branch of the loop or another crank angle open it by a sizeable fraction
of the links, far beyond.
"""
from __future__ import annotations

import numpy as np

from ..core.affine import axis_rotations
from .scene import FIXED, PRISMATIC, REVOLUTE

# a closing joint's gap accepted, as a fraction of its half_length
LOOP_TOL = 0.1


def tree_order(scene):
    """The spanning tree that places the bodies (fixed bodies first, then free roots at their scene
    pose): ([(joint, parent, child, sign)] in placement order, sign −1 where the joint's first
    body is the child), and [the joints that close a loop]."""
    bodies = scene.bodies
    placed = np.array([b.fixed for b in bodies])
    rows, closing = [], []
    pending = list(range(len(scene.joints)))
    while pending:
        progress = False
        for k in list(pending):
            j = scene.joints[k]
            a, b = j.body_a, j.body_b
            if placed[a] and placed[b]:
                pending.remove(k)  # closes a loop: the solver pulls it together
                closing.append(k)
                continue
            if not (placed[a] or placed[b]):
                continue
            rows.append((k, a, b, 1.0) if placed[a] else (k, b, a, -1.0))
            placed[b if placed[a] else a] = True
            pending.remove(k)
            progress = True
        if not progress and pending:
            # a free body with no placed neighbour: it is a root at its scene pose
            placed[scene.joints[pending[0]].body_a] = True
    return rows, closing


class LoopCheck:
    """Measures the closing joints' gaps of joint coordinates (``gaps``) and refuses those beyond
    LOOP_TOL of the joint's scale (``check``).  Built only for a scene with a closing joint
    (``for_scene``)."""

    def __init__(self, scene, model, rows, closing):
        self.scene, self.rows, self.closing = scene, rows, closing
        self.kinds = [scene.joints[k].kind for k in closing]
        self.scale = np.array([scene.joints[k].half_length for k in closing])
        self.frames = model.base_frames  # (8, joints, 3): c, t, n, b in each body's frame
        self.points = model.base_points  # (2, joints, 4, 3): the joint's points in each body's frame
        bodies = scene.bodies
        self.R0 = np.array([b.rotation for b in bodies])
        self.p0 = np.array([b.position for b in bodies])
        self.rel = []  # per tree row: the child's rest pose, the axis and the anchor in the parent's frame
        for k, par, ch, _ in rows:
            j, Bp, Bc = scene.joints[k], bodies[par], bodies[ch]
            self.rel.append((Bp.rotation.T @ Bc.rotation, Bp.rotation.T @ (Bc.position - Bp.position),
                             Bp.to_local_dir(j.frame[0]), Bp.to_local_point(j.anchor)))  # fmt: skip

    @classmethod
    def for_scene(cls, scene, model):
        """A LoopCheck of the scene, or None where no joint closes a loop."""
        rows, closing = tree_order(scene)
        return cls(scene, model, rows, closing) if closing else None

    def place(self, x):
        """Rotations (N, bodies, 3, 3) and positions (N, bodies, 3) of joint coordinates x (N, joints),
        placed as ``set_joint_state`` places them."""
        N = x.shape[0]
        R = np.broadcast_to(self.R0, (N,) + self.R0.shape).copy()
        p = np.broadcast_to(self.p0, (N,) + self.p0.shape).copy()
        for (k, par, ch, sign), (R_rel0, p_rel0, t, c) in zip(self.rows, self.rel):
            kind, xs = self.scene.joints[k].kind, sign * x[:, k]
            R_rel, p_rel = np.broadcast_to(R_rel0, (N, 3, 3)), np.broadcast_to(p_rel0, (N, 3))
            if kind == REVOLUTE:
                G = axis_rotations(t, xs)
                R_rel, p_rel = G @ R_rel0, c + np.einsum("nij,j->ni", G, p_rel0 - c)
            elif kind == PRISMATIC:
                p_rel = p_rel0 + xs[:, None] * t
            R[:, ch] = R[:, par] @ R_rel
            p[:, ch] = p[:, par] + np.einsum("nij,nj->ni", R[:, par], p_rel)
        return R, p

    def gaps(self, x):
        """The closing joints' gaps (N, closing) [m] of joint coordinates x (N, joints)."""
        R, p = self.place(np.asarray(x, dtype=np.float64))
        out = np.zeros((x.shape[0], len(self.closing)))
        for i, (k, kind) in enumerate(zip(self.closing, self.kinds)):
            j = self.scene.joints[k]
            Ra, Rb, pa, pb = R[:, j.body_a], R[:, j.body_b], p[:, j.body_a], p[:, j.body_b]
            if kind == PRISMATIC:
                f = self.frames[:, k]
                ca, cb = pa + Ra @ f[0], pb + Rb @ f[1]
                ta, tb, na, nb, ba, bb = (Rm @ v for Rm, v in zip((Ra, Rb) * 3, f[2:]))
                parts = [np.cross(cb - ca, ta), np.cross(ca - cb, tb), self.scale[i] * (na - nb),
                         self.scale[i] * (ba - bb)]  # fmt: skip
            else:
                n = 4 if kind == FIXED else 2
                parts = [(pa + Ra @ self.points[0, k, m]) - (pb + Rb @ self.points[1, k, m]) for m in range(n)]
            out[:, i] = np.max([np.linalg.norm(c, axis=-1) for c in parts], axis=0)
        return out

    def closed(self, x) -> bool:
        """Whether every closing joint's gap of joint coordinates x (N, joints) is within the tolerance."""
        return bool(np.all(self.gaps(x) <= LOOP_TOL * self.scale))

    def check(self, name, x, worlds):
        """Raise a ValueError naming the argument, the world, the closing joint and its gap where
        joint coordinates x (N, joints) of the worlds ``worlds`` leave a closing joint open by more
        than LOOP_TOL of its half_length."""
        gap = self.gaps(x)
        bad = gap > LOOP_TOL * self.scale
        if bad.any():
            i, c = np.argwhere(bad)[0]
            j = self.scene.joints[self.closing[c]]
            tol = LOOP_TOL * float(self.scale[c])
            raise ValueError(f"{name}: the coordinates in world {int(worlds[i])} leave the loop that joint {j.name!r} "
                             f"closes open by {float(gap[i, c]):.4g} m, more than {tol:.4g} m "
                             f"({LOOP_TOL} of its half_length {float(self.scale[c]):.4g} m): the loop's coordinates "
                             f"must follow from its kinematics")  # fmt: skip
