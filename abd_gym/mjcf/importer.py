"""MJCF and URDF models as scenes: a compiled ``mujoco.MjModel`` → ``abd_gym.Scene``.

Every MJCF/URDF rule (defaults, ``inertiafromgeom``, frames, angle units, URDF's fused static
links) is MuJoCo's own: the file is compiled by ``mujoco.MjModel`` and only the compiled arrays are
read here.  The mapping:

- **Pose.** The scene is built at ``qpos = 0`` (not ``qpos0``): ``mj_kinematics`` there gives every
  body's frame (``xpos``, ``xmat``) and every joint's anchor and axis, so a hinge's or slide's
  abd_gym coordinate *is* MuJoCo's ``qpos`` value, ``ref`` offsets included (``qpos0 = ref`` is a
  state, kept in ``MjcfInfo.qpos0``).
- **Bodies.** Each MuJoCo body with joints is one abd body whose frame is the MuJoCo body frame.  A
  body without joints is welded to its parent (MuJoCo's ``body_weldid``): its mass joins the abd
  body's (composite mass, centre of mass, inertia), and its frame is kept in ``MjcfInfo.frames``.
  The world and its jointless descendants are one fixed body ``"world"``.  Mass properties are an
  ``abd_gym.Inertia``: ``body_mass``, ``body_ipos`` and ``body_inertia`` rotated by ``body_iquat``;
  its ``size`` is the largest half-extent of the body's equivalent inertia box (uniform box of the
  same mass and principal inertias).  The fixed world body gets the mass and size of the lightest
  moving body: a fixed body's mass enters only the strength of the joints on it, which then
  follows the mass they carry.
- **Several joints on one body.** MuJoCo applies them in order, each after the previous one's
  motion.  The importer chains them through k − 1 *carrier* bodies at the body's frame, each with
  ``CARRIER_FRACTION`` of the body's mass and inertia: the chain's kinematics is MuJoCo's exactly,
  its inertia is larger by that fraction per carrier.  A moving body with no mass of its own gets
  the same fraction of the mass of its subtree.
- **Joints.** hinge → ``add_revolute_joint`` and slide → ``add_prismatic_joint`` at the world
  anchor ``xanchor`` and axis ``xaxis``, parent body first, in MuJoCo's joint (= qpos) order, with
  MuJoCo's names (unnamed: ``"joint<id>"``).  Ranges → limits (lower + margin, upper − margin:
  MuJoCo's limit pushes back from ``margin`` inside the range) of strength
  ``LIMIT_STRENGTH_RATIO·I`` with ``I`` the inertia the joint moves about its axis [kg·m²]
  (hinge) or ``LIMIT_STRENGTH_RATIO·M·w²`` with ``M`` the mass it moves and ``w`` the range width
  (slide).  Damping and armature → ``Scene.set_joint_passive``.
- **Actuators** (in MuJoCo's order: drive k is actuator k) with a joint transmission of gear g:
  ``motor`` → effort drive with u = g·ctrl, ``max_effort`` = g·max|ctrlrange| (a symmetric range;
  g·forcerange where force-limited); ``position`` (kp, kv) → position drive of stiffness g²·kp,
  damping g²·kv and target u = ctrl/g; ``velocity`` (kv) → velocity drive of damping g²·kv and
  target u = ctrl/g.  ``MjcfInfo.ctrl_scale`` holds the factor (u = ctrl_scale·ctrl).
- **Equalities.** ``weld`` → ``add_fixed_joint``; ``connect`` → a revolute joint through the
  anchor about the common axis of the hinges on the loop it closes (exact for a planar loop; any
  other loop is refused, abd_gym having no point joint).  Both must hold at ``qpos = 0``.
- **Gravity** → ``Scene(gravity=...)``; the timestep → ``MjcfInfo.timestep``.

Refused with a ValueError naming the element: ball and free joints, mocap bodies, tendons, flexes,
plugins, fluid forces, joint stiffness, friction loss, gravity compensation, non-joint
transmissions, actuator dynamics or gains other than the three above, asymmetric motor control
ranges, hinge ranges outside [−π, π], equalities other than weld/connect, explicit contact pairs,
and geoms that can collide (``ignore_contacts=True`` imports such a model without contacts, with a
warning).  What only draws or reads out (geoms of a contact-free model, cameras, lights, sensors) is
skipped and listed in ``MjcfInfo.skipped``; sensors and ignored contacts are warned about once.
"""
from __future__ import annotations

import math
import os
import warnings
from dataclasses import dataclass, field

import numpy as np

from ..sim.shapes import Inertia

# carrier body of a multi-joint body (and a massless moving body): this fraction of the mass
CARRIER_FRACTION = 1e-3
# a limit's strength over the inertia (hinge, kg·m²) or mass·width² (slide, kg·m²) it stops: a hinge
# arriving at v rad/s overshoots by (v²/(2·ratio))^(1/3) rad (0.017 rad at 1 rad/s, 0.08 at 10), and
# the limit's Hessian stays below 1e5·(v/10)^(2/3) times the inertia term, well inside what float32 solves
LIMIT_STRENGTH_RATIO = 1e5
# a loop-closing connect: hinge axes count as parallel, and its two anchors as one, within these
PARALLEL_TOLERANCE = 1e-6
ANCHOR_TOLERANCE = 1e-6  # [m], relative to the model's extent

INSTALL_HINT = 'importing MJCF/URDF needs MuJoCo\'s compiler: pip install "abd-gym[mjcf]"'


def _mujoco():
    try:
        import mujoco
    except ImportError as err:  # the optional extra
        raise ImportError(INSTALL_HINT) from err
    return mujoco


@dataclass
class MjcfInfo:
    """What a task needs from the source model beyond the scene (``Scene.imported``).

    ``joint_names`` and ``qpos0`` (num_joints,) are in the scene's joint order (MuJoCo's qpos order,
    then the joints that close loops); ``gear``, ``ctrl_scale`` (u = ctrl_scale·ctrl) and
    ``ctrlrange`` (num_drives, 2) (±inf where not ctrl-limited) in drive order (MuJoCo's actuator
    order).  ``frames``: MuJoCo body name → (abd body index, position (3,), rotation (3, 3)) of that
    body's frame in the abd body's frame; ``sites``: site name → (abd body index, position (3,));
    ``model``: the compiled ``mujoco.MjModel`` (the one passed, if one was), which
    ``compare_with_mujoco`` steps beside the scene.
    """

    model_name: str
    timestep: float
    joint_names: list
    qpos0: np.ndarray
    actuator_names: list
    gear: np.ndarray
    ctrl_scale: np.ndarray
    ctrlrange: np.ndarray
    frames: dict = field(default_factory=dict)
    sites: dict = field(default_factory=dict)
    skipped: list = field(default_factory=list)
    model: object = None  # the compiled mujoco.MjModel the scene was built from (compare_with_mujoco)


def load(source):
    """A compiled ``mujoco.MjModel`` from an MjModel, an XML string, or a path to an MJCF or URDF
    file (MuJoCo reads both)."""
    mujoco = _mujoco()
    if isinstance(source, mujoco.MjModel):
        return source
    if isinstance(source, (str, os.PathLike)):
        text = os.fspath(source)
        if text.lstrip().startswith("<"):
            return mujoco.MjModel.from_xml_string(text)
        return mujoco.MjModel.from_xml_path(text)
    raise ValueError(f"expected a path, an XML string or a mujoco.MjModel, got {type(source).__name__}")


def build(source, scene_class, *, exclude=(), ignore_contacts=False):
    """A ``scene_class`` (``abd_gym.Scene``, which calls this) of an MJCF/URDF model (see the module
    docstring); ``scene.imported`` its MjcfInfo."""
    return _Importer(load(source), scene_class, exclude, ignore_contacts).scene


def _name(m, obj, i, prefix):
    return _mujoco().mj_id2name(m, obj, i) or f"{prefix}{i}"


def _quat_matrix(q):
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])  # fmt: skip


def box_size(mass, inertia) -> float:
    """Largest half-extent [m] of the uniform box of ``mass`` [kg] with the principal inertias of
    ``inertia`` (3, 3) [kg·m²] about its centre: a_i² = 3(I_j + I_k − I_i)/(2m)."""
    p = np.linalg.eigvalsh(inertia)
    half_sq = 1.5 * (p.sum() - 2.0 * p) / mass
    return float(np.sqrt(max(half_sq.max(), 0.0)))


def composite(parts):
    """Mass [kg], centre of mass (3,) and inertia about it (3, 3) of parts [(m, c, I about c)]."""
    mass = sum(p[0] for p in parts)
    com = sum(p[0] * p[1] for p in parts) / mass
    inertia = np.zeros((3, 3))
    for m, c, i in parts:
        d = c - com
        inertia += i + m * (d @ d * np.eye(3) - np.outer(d, d))
    return mass, com, inertia


class _Importer:
    """One model's import: the steps of the mapping, in order."""

    def __init__(self, m, scene_class, exclude, ignore_contacts):
        self.mj = _mujoco()
        self.m = m
        self.body_names = [_name(m, self.mj.mjtObj.mjOBJ_BODY, b, "body") for b in range(m.nbody)]
        self.body_names[0] = "world"
        self.joint_names = [_name(m, self.mj.mjtObj.mjOBJ_JOINT, j, "joint") for j in range(m.njnt)]
        self.kept = self._kept(exclude)
        self.skipped = []
        self._refuse_unsupported()
        self.d = self._pose_at_zero()
        gravity = np.zeros(3) if int(m.opt.disableflags) & int(self.mj.mjtDisableBit.mjDSBL_GRAVITY) else m.opt.gravity
        self.scene = scene_class(gravity=np.array(gravity, dtype=np.float64))
        self._bodies()
        self._joints()
        self._drives()
        self._equalities()
        self._contacts(ignore_contacts)
        self._drawing()
        self.scene.imported = self._info()

    # ------------------------------------------------------------------ selection and refusals
    def _kept(self, exclude):
        """(nbody,) bool: bodies outside the excluded subtrees."""
        if isinstance(exclude, str):
            exclude = (exclude,)
        m, kept = self.m, np.ones(self.m.nbody, dtype=bool)
        for name in exclude:
            if name not in self.body_names[1:]:
                raise ValueError(f"exclude: no body named {name!r} in the model (bodies: {self.body_names[1:]})")
            root = self.body_names.index(name)
            for b in range(m.nbody):
                a = b
                while a != 0 and a != root:
                    a = m.body_parentid[a]
                if a == root:
                    kept[b] = False
        return kept

    def _kept_joints(self):
        return [j for j in range(self.m.njnt) if self.kept[self.m.jnt_bodyid[j]]]

    def _refuse_unsupported(self):
        m, mj = self.m, self.mj
        refuse = []
        for what, count in (("tendon", m.ntendon), ("flex", m.nflex), ("plugin", m.nplugin),
                            ("explicit contact pair", m.npair)):  # fmt: skip
            if count:
                refuse.append(f"{count} {what}(s) (abd_gym models no {what}s)")
        if m.opt.density > 0 or m.opt.viscosity > 0:
            refuse.append(f"fluid forces (option density={m.opt.density}, viscosity={m.opt.viscosity})")
        for b in range(1, m.nbody):
            if not self.kept[b]:
                continue
            if m.body_mocapid[b] >= 0:
                refuse.append(f"mocap body {self.body_names[b]!r}")
            if m.body_gravcomp[b] != 0:
                refuse.append(f"gravcomp on body {self.body_names[b]!r}")
        kinds = {int(mj.mjtJoint.mjJNT_FREE): "free", int(mj.mjtJoint.mjJNT_BALL): "ball"}
        for j in self._kept_joints():
            where = f"joint {self.joint_names[j]!r} of body {self.body_names[m.jnt_bodyid[j]]!r}"
            if int(m.jnt_type[j]) in kinds:
                refuse.append(f"{kinds[int(m.jnt_type[j])]} {where} (abd_gym has hinge and slide joints only)")
                continue
            if m.jnt_stiffness[j] != 0:
                refuse.append(f"stiffness {m.jnt_stiffness[j]} on {where}")
            if m.dof_frictionloss[m.jnt_dofadr[j]] != 0:
                refuse.append(f"frictionloss {m.dof_frictionloss[m.jnt_dofadr[j]]} on {where}")
        if refuse:
            raise ValueError("cannot import this model: " + "; ".join(refuse))

    def _pose_at_zero(self):
        d = self.mj.MjData(self.m)
        d.qpos[:] = 0.0
        self.mj.mj_kinematics(self.m, d)
        return d

    # ------------------------------------------------------------------ bodies
    def _world_inertia(self, b):
        """Body b's mass, com and inertia about it, in the world frame at qpos = 0."""
        m, d = self.m, self.d
        rot = d.xmat[b].reshape(3, 3) @ _quat_matrix(m.body_iquat[b])
        return float(m.body_mass[b]), d.xpos[b] + d.xmat[b].reshape(3, 3) @ m.body_ipos[b], rot @ np.diag(m.body_inertia[b]) @ rot.T

    def _bodies(self):
        """One abd body per weld group (a body with joints and its jointless descendants), the carriers
        of multi-joint bodies before it; the frames of all kept MuJoCo bodies."""
        m, d, s = self.m, self.d, self.scene
        groups = {}
        for b in range(m.nbody):
            if self.kept[b]:
                groups.setdefault(int(m.body_weldid[b]), []).append(b)
        inertias = {}
        for root, members in groups.items():
            parts = [self._world_inertia(b) for b in members if m.body_mass[b] > 0]
            inertias[root] = composite(parts) if parts else None
        moving = [v for r, v in inertias.items() if r != 0 and v is not None]
        if not moving:
            raise ValueError("cannot import this model: it has no moving body with mass")
        lightest = min(moving, key=lambda v: v[0])
        self.abd_of = {}  # MuJoCo weld root -> abd body index
        self.carriers = {}  # MuJoCo body -> abd indices of its carriers (one per joint but the last)
        for root in sorted(groups):
            if root == 0:
                inertia = (lightest[0], np.zeros(3), lightest[2])
            elif inertias[root] is None:
                sub = composite([v for r, v in inertias.items() if v is not None and self._descends(r, root)])
                inertia = (CARRIER_FRACTION * sub[0], sub[1], CARRIER_FRACTION * sub[2])
            else:
                inertia = inertias[root]
            make = lambda name, frac: self._add_body(root, name, frac, inertia)  # noqa: E731
            jn = m.body_jntnum[root] if root else 0
            self.carriers[root] = [make(f"{self.body_names[root]}/{self.joint_names[m.body_jntadr[root] + k]}", CARRIER_FRACTION)
                                   for k in range(jn - 1)]  # fmt: skip
            self.abd_of[root] = make(self.body_names[root], 1.0)
        self.frames = {}
        for b in range(m.nbody):
            if self.kept[b]:
                k = self.abd_of[int(m.body_weldid[b])]
                body = s.bodies[k]
                rel_rot = body.rotation.T @ d.xmat[b].reshape(3, 3)
                self.frames[self.body_names[b]] = (k, body.to_local_point(d.xpos[b]), rel_rot)

    def _descends(self, b, root):
        while b != 0 and b != root:
            b = int(self.m.body_parentid[b])
        return b == root

    def _add_body(self, root, name, fraction, inertia):
        """abd body at MuJoCo body ``root``'s frame with ``fraction`` of ``inertia`` (mass, world com,
        world inertia about the com)."""
        d = self.d
        rot = d.xmat[root].reshape(3, 3)
        mass, com, inertia_world = inertia
        size = box_size(mass, inertia_world) or 0.01
        if root == 0:
            com_local, inertia_local = np.zeros(3), inertia_world
        else:
            com_local = rot.T @ (com - d.xpos[root])
            inertia_local = rot.T @ inertia_world @ rot
        inertia_local = 0.5 * (inertia_local + inertia_local.T)
        shape = Inertia(mass=fraction * mass, com=tuple(com_local), inertia=tuple(map(tuple, fraction * inertia_local)),
                        size=size)  # fmt: skip
        return self.scene.add_body(shape, position=d.xpos[root], rotation=rot, fixed=root == 0, name=name)

    # ------------------------------------------------------------------ joints
    def _joints(self):
        m, d, s, mj = self.m, self.d, self.scene, self.mj
        self.abd_joint = {}  # MuJoCo joint -> abd joint index
        for j in self._kept_joints():
            b = int(m.jnt_bodyid[j])
            k = j - m.body_jntadr[b]
            chain = [self.abd_of[int(m.body_weldid[m.body_parentid[b]])]] + self.carriers[b] + [self.abd_of[b]]
            parent, child = chain[k], chain[k + 1]
            hinge = int(m.jnt_type[j]) == int(mj.mjtJoint.mjJNT_HINGE)
            add = s.add_revolute_joint if hinge else s.add_prismatic_joint
            # a slide's line may pass through any point of the child: its point at qpos = 0
            anchor = d.xanchor[j] if hinge else d.xpos[b] + d.xmat[b].reshape(3, 3) @ m.jnt_pos[j]
            ji = add(parent, child, anchor=anchor.copy(), axis=d.xaxis[j].copy(), name=self.joint_names[j])
            self.abd_joint[j] = ji
            if m.jnt_limited[j]:
                self._limit(j, ji, hinge)
            dof = m.jnt_dofadr[j]
            if m.dof_damping[dof] > 0 or m.dof_armature[dof] > 0:
                s.set_joint_passive(ji, damping=float(m.dof_damping[dof]), armature=float(m.dof_armature[dof]))

    def _limit(self, j, ji, hinge):
        m = self.m
        lower, upper = (float(x) for x in m.jnt_range[j])
        margin = float(m.jnt_margin[j])
        name = self.joint_names[j]
        if hinge and not (-math.pi <= lower and upper <= math.pi):
            raise ValueError(f"hinge joint {name!r}: range [{lower:.4g}, {upper:.4g}] rad reaches beyond [-pi, pi], "
                             "which abd_gym's revolute limit cannot represent")  # fmt: skip
        lower, upper = lower + margin, upper - margin
        if lower > upper:
            raise ValueError(f"joint {name!r}: margin {margin} leaves no range inside [{lower - margin}, {upper + margin}]")
        moved = [self._world_inertia(b) for b in range(m.nbody)
                 if self.kept[b] and m.body_mass[b] > 0 and self._descends(b, int(m.jnt_bodyid[j]))]  # fmt: skip
        mass, com, inertia = composite(moved)
        if hinge:
            axis, r = self.d.xaxis[j], com - self.d.xanchor[j]
            scale = axis @ inertia @ axis + mass * float(np.sum(np.cross(r, axis) ** 2))
            self.scene.add_revolute_limit(ji, lower, upper, strength=LIMIT_STRENGTH_RATIO * scale)
        else:
            scale = mass * max(upper - lower, 1e-3) ** 2
            self.scene.add_prismatic_limit(ji, lower, upper, strength=LIMIT_STRENGTH_RATIO * scale)

    # ------------------------------------------------------------------ actuators
    def _drives(self):
        m, mj = self.m, self.mj
        self.actuator_names, gear, scale, ctrlrange = [], [], [], []
        fixed, affine, none = int(mj.mjtGain.mjGAIN_FIXED), int(mj.mjtBias.mjBIAS_AFFINE), int(mj.mjtBias.mjBIAS_NONE)
        for a in range(m.nu):
            name = _name(m, mj.mjtObj.mjOBJ_ACTUATOR, a, "actuator")
            if int(m.actuator_trntype[a]) != int(mj.mjtTrn.mjTRN_JOINT):
                raise ValueError(f"actuator {name!r}: only joint transmissions map to abd_gym drives")
            j = int(m.actuator_trnid[a, 0])
            if not self.kept[m.jnt_bodyid[j]]:
                continue
            bias = int(m.actuator_biastype[a])
            if int(m.actuator_dyntype[a]) != int(mj.mjtDyn.mjDYN_NONE) or int(m.actuator_gaintype[a]) != fixed:
                raise ValueError(f"actuator {name!r}: activation dynamics or a non-fixed gain (abd_gym drives are "
                                 "motor, position or velocity servos)")  # fmt: skip
            g = float(m.actuator_gear[a, 0])
            kp, (b0, b1, b2) = float(m.actuator_gainprm[a, 0]), (float(x) for x in m.actuator_biasprm[a, :3])
            limited = bool(m.actuator_ctrllimited[a])
            lo, hi = (float(x) for x in m.actuator_ctrlrange[a]) if limited else (-math.inf, math.inf)
            force = math.inf
            if m.actuator_forcelimited[a]:
                flo, fhi = (float(x) for x in m.actuator_forcerange[a])
                if flo != -fhi:
                    raise ValueError(f"actuator {name!r}: asymmetric forcerange [{flo}, {fhi}] (abd_gym's effort "
                                     "limit is symmetric)")  # fmt: skip
                force = abs(g) * fhi
            if bias == none:
                if limited and lo != -hi:
                    raise ValueError(f"motor actuator {name!r}: asymmetric ctrlrange [{lo}, {hi}] (abd_gym's effort "
                                     "limit is symmetric)")  # fmt: skip
                kwargs = dict(mode="effort", max_effort=min(force, abs(g * kp) * hi))
                u_scale = g * kp
            elif bias == affine and b0 == 0 and b1 == -kp and b2 <= 0 and kp > 0:
                kwargs = dict(mode="position", stiffness=g * g * kp, damping=-g * g * b2, max_effort=force)
                u_scale = 1.0 / g
            elif bias == affine and b0 == 0 and b1 == 0 and b2 == -kp and kp > 0:
                kwargs = dict(mode="velocity", damping=g * g * kp, max_effort=force)
                u_scale = 1.0 / g
            else:
                raise ValueError(f"actuator {name!r}: gain/bias {kp}, ({b0}, {b1}, {b2}) is not a motor, position "
                                 "or velocity actuator")  # fmt: skip
            self.scene.add_drive(self.abd_joint[j], name=name, **kwargs)
            self.actuator_names.append(name)
            gear.append(g)
            scale.append(u_scale)
            ctrlrange.append((lo, hi))
        self.gear = np.array(gear, dtype=np.float64)
        self.ctrl_scale = np.array(scale, dtype=np.float64)
        self.ctrlrange = np.array(ctrlrange, dtype=np.float64).reshape(-1, 2)

    # ------------------------------------------------------------------ equalities
    def _equalities(self):
        m, mj = self.m, self.mj
        for e in range(m.neq):
            name = _name(m, mj.mjtObj.mjOBJ_EQUALITY, e, "equality")
            kind = int(m.eq_type[e])
            if kind not in (int(mj.mjtEq.mjEQ_CONNECT), int(mj.mjtEq.mjEQ_WELD)):
                raise ValueError(f"equality {name!r}: only connect and weld map to abd_gym joints")
            if int(m.eq_objtype[e]) != int(mj.mjtObj.mjOBJ_BODY):
                raise ValueError(f"equality {name!r}: defined by sites; abd_gym imports body-defined connect/weld")
            b1, b2 = int(m.eq_obj1id[e]), int(m.eq_obj2id[e])
            if not (self.kept[b1] and self.kept[b2]):
                continue  # part of an excluded subtree
            if not m.eq_active0[e]:
                self.skipped.append(f"equality {name!r} (inactive)")
                continue
            if kind == int(mj.mjtEq.mjEQ_WELD):
                self._weld(name, e, b1, b2)
            else:
                self._connect(name, e, b1, b2)

    def _abd(self, b):
        return self.abd_of[int(self.m.body_weldid[b])]

    def _frame(self, b):
        return self.d.xpos[b], self.d.xmat[b].reshape(3, 3)

    def _weld(self, name, e, b1, b2):
        """body2's pose relative to body1 at qpos = 0 must be the weld's relpose (eq_data[3:10])."""
        (p1, r1), (p2, r2) = self._frame(b1), self._frame(b2)
        data = self.m.eq_data[e]
        rel_p, rel_r = r1.T @ (p2 - p1), r1.T @ r2
        if not (np.allclose(rel_p, data[3:6], atol=ANCHOR_TOLERANCE) and np.allclose(rel_r, _quat_matrix(data[6:10]), atol=1e-6)):
            raise ValueError(f"weld {name!r}: its relative pose is not the bodies' pose at qpos = 0, "
                             "where abd_gym builds and welds them")  # fmt: skip
        if self._abd(b1) == self._abd(b2):
            raise ValueError(f"weld {name!r}: bodies {self.body_names[b1]!r} and {self.body_names[b2]!r} are already rigidly joined")
        self.scene.add_fixed_joint(self._abd(b1), self._abd(b2), anchor=p2 + r2 @ data[:3], name=name)

    def _connect(self, name, e, b1, b2):
        """A revolute joint through the anchor about the loop's common hinge axis."""
        (p1, r1), (p2, r2) = self._frame(b1), self._frame(b2)
        data = self.m.eq_data[e]
        x1, x2 = p1 + r1 @ data[:3], p2 + r2 @ data[3:6]
        if np.linalg.norm(x1 - x2) > ANCHOR_TOLERANCE * (1.0 + np.abs(self.d.xpos).max()):
            raise ValueError(f"connect {name!r}: its anchors are {np.linalg.norm(x1 - x2):.3g} m apart at qpos = 0; "
                             "abd_gym builds the model there, so the loop must be closed at qpos = 0")  # fmt: skip
        axis = self._planar_axis(name, b1, b2)
        self.scene.add_revolute_joint(self._abd(b1), self._abd(b2), anchor=x1, axis=axis, name=name)

    def _planar_axis(self, name, b1, b2):
        """The common axis of the hinges on the tree path between b1 and b2 (slides on it must be
        perpendicular to it): the loop is planar, so a point constraint is a hinge about that axis."""
        m, mj = self.m, self.mj

        def up(b):
            path = [b]
            while b:
                b = int(m.body_parentid[b])
                path.append(b)
            return path

        p1, p2 = up(b1), up(b2)
        common = next(b for b in p1 if b in p2)
        bodies = p1[: p1.index(common)] + p2[: p2.index(common)]
        joints = [j for b in bodies for j in range(m.body_jntadr[b], m.body_jntadr[b] + m.body_jntnum[b])]
        hinges = [self.d.xaxis[j] for j in joints if int(m.jnt_type[j]) == int(mj.mjtJoint.mjJNT_HINGE)]
        why = None
        if not hinges:
            why = "the loop it closes has no hinge"
        else:
            axis = hinges[0] / np.linalg.norm(hinges[0])
            if any(np.linalg.norm(np.cross(axis, h)) > PARALLEL_TOLERANCE for h in hinges):
                why = "the hinges on the loop it closes are not parallel"
            elif any(abs(axis @ self.d.xaxis[j]) > PARALLEL_TOLERANCE for j in joints if int(m.jnt_type[j]) == int(mj.mjtJoint.mjJNT_SLIDE)):
                why = "a slide on the loop it closes leaves the plane of its hinges"
        if why:
            raise ValueError(f"connect {name!r}: {why}, so it needs a point (ball) joint, which abd_gym does not have")
        return axis

    # ------------------------------------------------------------------ contacts and what only draws
    def _can_collide(self, g1, g2):
        """MuJoCo's filter for a geom pair: different weld bodies, not parent and child (unless the
        parent filter is off or one is the world), compatible contype/conaffinity, not excluded."""
        m = self.m
        if not ((m.geom_contype[g1] & m.geom_conaffinity[g2]) or (m.geom_contype[g2] & m.geom_conaffinity[g1])):
            return False
        b1, b2 = int(m.geom_bodyid[g1]), int(m.geom_bodyid[g2])
        w1, w2 = int(m.body_weldid[b1]), int(m.body_weldid[b2])
        if w1 == w2:
            return False
        filter_parent = not (int(m.opt.disableflags) & int(self.mj.mjtDisableBit.mjDSBL_FILTERPARENT))
        pw1, pw2 = int(m.body_weldid[m.body_parentid[w1]]), int(m.body_weldid[m.body_parentid[w2]])
        if filter_parent and w1 and w2 and (w1 == pw2 or w2 == pw1):
            return False
        signatures = {(b1 << 16) + b2, (b2 << 16) + b1}
        return not any(int(s) in signatures for s in m.exclude_signature)

    def _contacts(self, ignore_contacts):
        m = self.m
        if int(m.opt.disableflags) & int(self.mj.mjtDisableBit.mjDSBL_CONTACT):
            return
        geoms = [g for g in range(m.ngeom) if self.kept[m.geom_bodyid[g]]]
        for i, g1 in enumerate(geoms):
            for g2 in geoms[i + 1:]:
                if self._can_collide(g1, g2):
                    pair = (_name(m, self.mj.mjtObj.mjOBJ_GEOM, g1, "geom"), _name(m, self.mj.mjtObj.mjOBJ_GEOM, g2, "geom"))
                    if not ignore_contacts:
                        raise ValueError(f"geoms {pair[0]!r} and {pair[1]!r} can collide, and abd_gym has no contacts: "
                                         "ignore_contacts=True imports the model without them")  # fmt: skip
                    warnings.warn(f"imported without contacts (e.g. between geoms {pair[0]!r} and {pair[1]!r})",
                                  RuntimeWarning, stacklevel=4)  # fmt: skip
                    return

    def _drawing(self):
        """Geoms, cameras and lights only draw here and are skipped silently; sensors read out
        what abd_gym does not compute, so skipping them is warned about."""
        m, mj = self.m, self.mj
        for obj, count, prefix, bodies in ((mj.mjtObj.mjOBJ_GEOM, m.ngeom, "geom", m.geom_bodyid),
                                           (mj.mjtObj.mjOBJ_CAMERA, m.ncam, "camera", m.cam_bodyid),
                                           (mj.mjtObj.mjOBJ_LIGHT, m.nlight, "light", m.light_bodyid)):  # fmt: skip
            self.skipped += [f"{prefix} {_name(m, obj, i, prefix)!r}" for i in range(count) if self.kept[bodies[i]]]
        sensors = [f"sensor {_name(m, mj.mjtObj.mjOBJ_SENSOR, i, 'sensor')!r}" for i in range(m.nsensor)]
        if sensors:
            warnings.warn("abd_gym computes no MuJoCo sensors; skipped " + ", ".join(sensors), RuntimeWarning, stacklevel=4)
            self.skipped += sensors

    def _info(self) -> MjcfInfo:
        m, mj = self.m, self.mj
        joints = self._kept_joints()
        sites = {}
        for i in range(m.nsite):
            b = int(m.site_bodyid[i])
            if self.kept[b]:
                k, pos, rot = self.frames[self.body_names[b]]
                sites[_name(m, mj.mjtObj.mjOBJ_SITE, i, "site")] = (k, pos + rot @ m.site_pos[i])
        loops = [j.name for j in self.scene.joints[len(joints):]]
        return MjcfInfo(
            model_name=m.names[: m.names.index(b"\0")].decode() if m.names else "",
            timestep=float(m.opt.timestep),
            joint_names=[self.joint_names[j] for j in joints] + loops,
            qpos0=np.array([m.qpos0[m.jnt_qposadr[j]] for j in joints] + [0.0] * len(loops)),
            actuator_names=self.actuator_names,
            gear=self.gear,
            ctrl_scale=self.ctrl_scale,
            ctrlrange=self.ctrlrange,
            frames=self.frames,
            sites=sites,
            skipped=self.skipped,
            model=m,
        )
