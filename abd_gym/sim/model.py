"""Model: a scene compiled to static device arrays, one batch row per world.

Everything a task may randomise per world (mass moments, joint frames and strengths, limit
bounds and strengths, drive gains) has a leading world dimension; topology (which bodies a
joint links, which constitutions exist) is shared by all worlds.  Built once from a validated
``Scene``; the only writes afterwards come from the ``Simulator.set_*`` parameter setters.
"""
from __future__ import annotations

import numpy as np
import warp as wp

from ..core import angles
from ..constitutions import drive as drive_mod
from ..core.warp_ops import ops
from . import conditioning, planar
from .coordinates import FIXED_CODE, PRISMATIC_CODE, REVOLUTE_CODE
from ..core.devices import resolve_device
from .scene import FIXED, PRISMATIC, REVOLUTE, Scene

_KIND_CODE = {REVOLUTE: REVOLUTE_CODE, PRISMATIC: PRISMATIC_CODE, FIXED: FIXED_CODE}
_DTYPES = {"float32": wp.float32, "float64": wp.float64, np.float32: wp.float32, np.float64: wp.float64}


def resolve_dtype(dtype):
    if dtype in (wp.float32, wp.float64):
        return dtype
    try:
        key = dtype if dtype in _DTYPES else getattr(np.dtype(dtype), "name", None) if dtype is not None else None
    except TypeError:  # a value NumPy does not know as a dtype
        key = None
    if key not in _DTYPES:
        raise ValueError(f"dtype must be float32 or float64, got {dtype!r}")
    return _DTYPES[key]


def without_rounding_noise(x: np.ndarray, rel: float = 1e-12, axis: int | None = None) -> np.ndarray:
    """A copy of ``x`` with the entries at most ``rel`` × the largest magnitude set to 0: of the
    whole array, or along ``axis`` (each vector of a stack of them on its own).

    Data computed through a rotation (an MJCF geom's ``fromto``, a rotated inertia tensor, a joint
    frame or anchor in a rotated body's coordinates) carries float64 rounding noise, ~1e-17 of the
    largest entry, where the exact value is 0.  float32 products of such entries fall below
    1.2e-38, into denormal numbers, which an x86 CPU handles by a slow microcode assist on every
    operation that touches them: zeroing the noise keeps the CPU step at its normal speed."""
    x = np.array(x, dtype=np.float64)
    scale = np.abs(x).max(axis=axis, keepdims=axis is not None, initial=0.0)
    x[np.abs(x) <= rel * scale] = 0.0
    return x


class Model:
    """Device arrays of one scene for ``num_worlds`` worlds (see module docstring)."""

    def __init__(self, scene: Scene, num_worlds: int, dtype=wp.float32, device="cpu", reduce: bool = True):
        if not isinstance(num_worlds, (int, np.integer)) or num_worlds < 1:
            raise ValueError(f"num_worlds must be a positive integer, got {num_worlds!r}")
        if scene.num_bodies == 0:
            raise ValueError("the scene has no bodies")
        self.scene = scene
        self.num_worlds = int(num_worlds)
        self.dtype = resolve_dtype(dtype)
        self.np_dtype = np.float32 if self.dtype == wp.float32 else np.float64
        self.device = resolve_device(device)
        o = ops(self.dtype)
        self.vec3, self.vec12, self.mat33 = o.vec3, o.vec12, o.mat33
        dof, free = self._bodies(scene, reduce)
        self._joints(scene)
        self._sparsity(scene, dof, free)
        self._joint_frames(scene)
        self._limits(scene.joints)
        self._drives(scene.drives)
        self._passive(scene.joints)

    def _bodies(self, scene, reduce):
        """The bodies' unknowns and their per-world mass moments; returns (each body's first
        unknown, -1 for a fixed body; the free bodies' indices)."""
        # the plane a planar scene moves in (sim/planar.py; ``reduce`` False: none, the staged
        # reference step's 12 unknowns a body), and dof offsets (fixed bodies carry no unknowns)
        bodies = scene.bodies
        self.plane = planar.plane_of(scene) if reduce else None
        D = self.body_dofs = 6 if self.plane else 12  # unknowns a free body
        self.axis = self.plane.axis if self.plane else -1  # the plane's normal axis, -1: none
        dof, free = [], []
        for k, b in enumerate(bodies):
            dof.append(-1 if b.fixed else D * len(free))
            if not b.fixed:
                free.append(k)
        if not free:
            raise ValueError("the scene has no free (non-fixed) body")
        self.num_bodies, self.num_free = len(bodies), len(free)
        self.num_dofs = D * len(free)
        self.dof = self.int_array(dof)
        self.free = self.int_array(free)
        self.gravity = self.vec3(*scene.gravity)
        self.base_mass = np.array([b.mass for b in bodies])
        self.base_mc = np.array([without_rounding_noise(b.mass * b.moments.com) for b in bodies])
        self.base_S = np.array([without_rounding_noise(b.moments.second_moment) for b in bodies])
        self.base_kv = np.array([b.stiffness * b.shape.volume() for b in bodies])
        self.mass = self._world(self.base_mass)
        self.mc = self._world(self.base_mc, self.vec3)
        self.S = self._world(self.base_S, self.mat33)
        self.kv = self._world(self.base_kv)
        self.q0 = np.stack([b.q() for b in bodies])  # (bodies, 12) float64 initial pose
        self.qd0 = np.stack([b.qdot() for b in bodies])
        return dof, free

    def _joints(self, scene):
        """The joints' bodies and kinds."""
        joints = scene.joints
        self.num_joints = len(joints)
        self.joint_kind_np = np.array([_KIND_CODE[j.kind] for j in joints], dtype=np.int32)
        self.body_a = self.int_array([j.body_a for j in joints])
        self.body_b = self.int_array([j.body_b for j in joints])
        self.joint_kind = self.int_array(self.joint_kind_np)

    def _sparsity(self, scene, dof, free):
        """Where the Hessian of a world's system is zero (its envelope, its block band) and the
        system's size; whether a joint is stiff enough for the exact Hessian."""
        # the Hessian's envelope: row i's first non-zero column, from the body pairs the joints (and
        # their limits and drives) couple; a chain in scene order is block-banded, and Cholesky
        # fills nothing outside the envelope, so a 20-link chain factors in O(n·D²), not O(n³)
        D = self.body_dofs
        block_first = [dof[k] for k in free]
        for j in scene.joints:
            da, db = dof[j.body_a], dof[j.body_b]
            if da >= 0 and db >= 0:
                lo, hi = min(da, db), max(da, db)
                block_first[hi // D] = min(block_first[hi // D], lo)
        self.first_np = np.repeat(np.array(block_first, dtype=np.int32), D)
        self.envelope = bool(self.first_np.any())  # False: the Hessian is dense, the plain loops run
        # a world's system: the unknowns, then rows to a multiple of 4 (the factor's 4 × 4 tiles) that
        # couple to nothing (H 1 on their diagonal, g 0: fused.assembly), so D = 6 needs no other factor
        self.system_size = -(-self.num_dofs // 4) * 4
        pad = np.arange(self.num_dofs, self.system_size, dtype=np.int32)
        self.first_np = np.concatenate([self.first_np, pad]) if self.envelope else np.zeros(self.system_size, np.int32)
        # three or more free bodies, each coupled to the one before it at most (chains, and loops
        # closed through the ground: the four-bar, the slider-crank): the Hessian lies in its block
        # band, which the fused step stores packed (solver.kernels.h_words, plan.plan_band)
        # (12 unknowns a body: the band's 12-row blocks are what its 4 × 4 tiles step over)
        self.banded = D == 12 and len(block_first) >= 3 and all(f >= D * (b - 1) for b, f in enumerate(block_first))
        # a joint whose K/m is past conditioning.STIFF_JOINT: Newton may assemble the exact orthogonality
        # Hessian (fused.kernel's ``exact``)
        self.stiff = bool(np.max(conditioning.joint_numbers(scene), initial=0.0) > conditioning.STIFF_JOINT)
        self.first = self.int_array(self.first_np)

    def _joint_frames(self, scene):
        """Each joint's frames, points and stiffness in its bodies' local coordinates at creation
        (q_ref), and its reference cos/sin."""
        bodies, joints, nj = scene.bodies, scene.joints, self.num_joints
        frames = np.zeros((8, max(nj, 1), 3))
        pts = np.zeros((2, max(nj, 1), 4, 3))
        K = np.zeros(max(nj, 1))
        ratios = scene.strength_ratios()
        cs_ref = np.zeros((2, max(nj, 1)))
        for k, j in enumerate(joints):
            A, B = bodies[j.body_a], bodies[j.body_b]
            t, n, b = j.frame
            frames[:, k] = without_rounding_noise(
                [A.to_local_point(j.anchor), B.to_local_point(j.anchor), A.to_local_dir(t), B.to_local_dir(t),
                 A.to_local_dir(n), B.to_local_dir(n), A.to_local_dir(b), B.to_local_dir(b)], axis=-1)  # fmt: skip
            L = j.half_length
            if j.kind == FIXED:
                world_pts = [j.anchor] + [j.anchor + L * e for e in np.eye(3)]
            else:
                world_pts = [j.anchor + L * t, j.anchor - L * t]
            for p, x in enumerate(world_pts):
                pts[0, k, p] = without_rounding_noise(A.to_local_point(x))
                pts[1, k, p] = without_rounding_noise(B.to_local_point(x))
            K[k] = ratios[k] * (A.mass + B.mass)
            qpair = np.concatenate([A.q(), B.q()])
            (c, *_), (s, *_) = angles.cos_sin_np(qpair, frames[4, k], frames[6, k], frames[5, k], frames[7, k])
            cs_ref[:, k] = c, s
        self.base_frames, self.base_points, self.base_K = frames, pts, K
        self.c_a, self.c_b, self.t_a, self.t_b, self.n_a, self.n_b, self.b_a, self.b_b = (
            self._world(f, self.vec3) for f in frames
        )
        self.pts_a, self.pts_b = (self._world(p, self.vec3) for p in pts)
        self.K = self._world(K)
        self.c_ref, self.s_ref = (self._world(v) for v in cs_ref)
        self.joint_ids = {kind: self.int_array(scene.joints_of(kind)) for kind in (REVOLUTE, PRISMATIC, FIXED)}
        self.joint_count = {kind: len(scene.joints_of(kind)) for kind in (REVOLUTE, PRISMATIC, FIXED)}

    def _limits(self, joints):
        """The limits per joint kind, in joint order."""
        self.limit_joints, self.limit_params = {}, {}
        for kind in (REVOLUTE, PRISMATIC):
            ids = [k for k, j in enumerate(joints) if j.kind == kind and j.has_limit]
            self.limit_joints[kind] = ids
            vals = np.array([[joints[k].attributes[f"limit/{a}"] for k in ids] for a in ("lower", "upper", "strength")])
            self.limit_params[kind] = [self._world(v.reshape(-1)) for v in vals.reshape(3, -1)]
        self.limit_joint_ids = {kind: self.int_array(v) for kind, v in self.limit_joints.items()}

    def _drives(self, drives):
        """The drives' joints, modes and per-world gains."""
        self.num_drives = len(drives)
        self.drive_joint = self.int_array([d.joint for d in drives])
        self.drive_mode = self.int_array([drive_mod.MODES[d.mode] for d in drives])
        self.drive_stiffness = self._world(np.array([d.stiffness for d in drives]))
        self.drive_damping = self._world(np.array([d.damping for d in drives]))
        self.drive_max_effort = self._world(np.array([min(d.max_effort, 1e30) for d in drives]))

    def _passive(self, joints):
        """The passive joint terms (constitutions.passive): one per joint with damping or armature."""
        passive = [k for k, j in enumerate(joints) if j.has_passive]
        self.num_passive = len(passive)
        self.passive_joint = self.int_array(passive)
        self.passive_armature = self._world(np.array([joints[k].armature for k in passive]))
        self.passive_damping = self._world(np.array([joints[k].damping for k in passive]))

    # ------------------------------------------------------------------ helpers
    def int_array(self, values):
        """``values`` as a flat int32 device array (one unused 0 where there are none: a kernel
        argument must be an array even where it is never read)."""
        v = np.asarray(values, dtype=np.int32).reshape(-1)
        return wp.array(v if v.size else np.zeros(1, np.int32), dtype=wp.int32, device=self.device)

    def _world(self, per_item, vtype=None):
        """Tile a per-item array over worlds: (W, items, ...) on the device."""
        a = np.asarray(per_item, dtype=np.float64)
        if a.shape[0] == 0:
            a = np.zeros((1,) + a.shape[1:])
        tiled = np.ascontiguousarray(np.broadcast_to(a, (self.num_worlds,) + a.shape), dtype=self.np_dtype)
        if vtype is None:
            return wp.array(tiled, dtype=self.dtype, device=self.device)
        return wp.array(tiled, dtype=vtype, device=self.device)
