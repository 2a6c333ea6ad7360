"""Scene: bodies, joints, limits and drives, as plain validated Python.

A scene is built in its zero pose: joint frames and the reference state ``q_ref`` of every joint
are captured when the joint is added, so joint coordinates are measured from that pose.  Nothing
here touches Warp; ``Model`` compiles a scene to device arrays.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from . import inputs
from .shapes import MassMoments, Shape

# libuipc constitution UIDs (docs/specification/constitutions)
UID_AFFINE_BODY = 1
UID_REVOLUTE_JOINT = 18
UID_PRISMATIC_JOINT = 20
UID_FIXED_JOINT = 25  # our own: revolute constraints plus no relative rotation
UID_PRISMATIC_LIMIT = 669
UID_REVOLUTE_LIMIT = 670

REVOLUTE, PRISMATIC, FIXED = "revolute", "prismatic", "fixed"
DRIVE_MODES = ("effort", "position", "velocity")

# κ/ρ [Pa/(kg/m³) = m²/s²] of a body whose stiffness is derived: the square of the speed at which a
# deformation of A travels through the body (316 m/s), so a body's deformation modes keep the same
# frequency relative to its motion whatever its density; κ = 1e8 Pa at 1000 kg/m³
STIFFNESS_PER_DENSITY = 1e5
# a joint's derived strength ratio keeps K = ratio·(m_i + m_j) at least this times the mass it carries
LOAD_STRENGTH_RATIO = 100.0


def _vec3(name, value, unit=False):
    v = inputs.real_values(name, value).astype(np.float64).reshape(-1)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ValueError(f"{name} must be 3 finite numbers, got {value!r}")
    if unit:
        n = np.linalg.norm(v)
        if n < 1e-12:
            raise ValueError(f"{name} must have non-zero length, got {value!r}")
        v = v / n
    return v


def _finite(name, value, nonnegative=False, positive=False, allow_inf=False):
    """A real number (inputs.real_number); +inf only with ``allow_inf`` (an unbounded effort)."""
    return inputs.real_number(name, value, positive=positive, nonnegative=nonnegative, allow_inf=allow_inf)


def _name(name, default: str) -> str:
    """A body's, joint's or drive's name: a string, or ``default`` for None."""
    if name is None:
        return default
    if not isinstance(name, str) or not name:
        raise TypeError(f"name must be a non-empty string or None, got {name!r}")
    return name


def rotation_matrix(rotation) -> np.ndarray:
    """A 3x3 rotation from a 3x3 matrix or a unit quaternion (w, x, y, z)."""
    if rotation is None:
        return np.eye(3)
    r = inputs.real_values("rotation", rotation).astype(np.float64)
    if r.shape == (4,):
        n = np.linalg.norm(r)
        if not np.isfinite(n) or n < 1e-12:
            raise ValueError(f"rotation quaternion must be non-zero and finite, got {rotation!r}")
        w, x, y, z = r / n
        return np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
            ]
        )
    if r.shape != (3, 3) or not np.all(np.isfinite(r)):
        raise ValueError(f"rotation must be a 3x3 matrix or a quaternion (w, x, y, z), got {rotation!r}")
    if not np.allclose(r @ r.T, np.eye(3), atol=1e-6) or np.linalg.det(r) <= 0.0:
        raise ValueError(f"rotation matrix must be orthonormal with det +1, got {r.tolist()}")
    return r


def axis_frame(axis) -> np.ndarray:
    """Rows (t̂, n̂, b̂) of a joint frame: t̂ the axis, n̂ ⟂ t̂, and b̂ = n̂ × t̂.

    With b̂ = n̂ × t̂ the seed's sin θ = (n̂_i·b̂_j − b̂_i·n̂_j)/2 is +sin φ when body j turns by φ
    about +t̂ relative to body i (right-hand rule): the sign convention of docs/design.md §3.2.
    """
    t = _vec3("axis", axis, unit=True)
    helper = np.array([1.0, 0.0, 0.0]) if abs(t[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    n = np.cross(t, helper)
    n /= np.linalg.norm(n)
    b = np.cross(n, t)
    return np.stack([t, n, b])


@dataclass
class Body:
    name: str
    shape: Shape
    moments: MassMoments
    fixed: bool
    position: np.ndarray
    rotation: np.ndarray
    linear_velocity: np.ndarray
    angular_velocity: np.ndarray
    stiffness: float  # orthogonality stiffness κ [Pa], resolved (see Scene.add_body)

    @property
    def mass(self) -> float:
        return self.moments.mass

    @property
    def density(self) -> float:
        """Mean density m/vol [kg/m³]."""
        return self.moments.mass / self.shape.volume()

    def q(self) -> np.ndarray:
        """12-vector (p, a1, a2, a3) of the body's initial pose."""
        return np.concatenate([self.position, self.rotation.reshape(-1)])

    def qdot(self) -> np.ndarray:
        """Initial velocity: ṗ = v, Ȧ = [ω]× A (rows of Ȧ follow a_k)."""
        w = self.angular_velocity
        wx = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
        return np.concatenate([self.linear_velocity, (wx @ self.rotation).reshape(-1)])

    def to_local_point(self, x):
        return self.rotation.T @ (np.asarray(x) - self.position)

    def to_local_dir(self, v):
        return self.rotation.T @ np.asarray(v)


@dataclass
class Joint:
    kind: str
    body_a: int
    body_b: int
    anchor: np.ndarray  # world, at creation [m]
    frame: np.ndarray  # rows t̂, n̂, b̂ in world coordinates at creation
    strength_ratio: float | None  # None: derived from the load (Scene.strength_ratios)
    half_length: float  # axis points at anchor ± half_length·t̂ [m]
    name: str
    attributes: dict = field(default_factory=dict)  # "limit/lower", "limit/upper", "limit/strength"
    meta: dict = field(default_factory=dict)  # "constitution_uid", "extra_constitution_uids"

    @property
    def has_limit(self) -> bool:
        return "limit/lower" in self.attributes

    @property
    def damping(self) -> float:
        """Passive joint damping [N·m·s/rad or N·s/m] (Scene.set_joint_passive)."""
        return self.attributes.get("passive/damping", 0.0)

    @property
    def armature(self) -> float:
        """Inertia on the joint coordinate [kg·m² or kg] (Scene.set_joint_passive)."""
        return self.attributes.get("passive/armature", 0.0)

    @property
    def has_passive(self) -> bool:
        return self.damping > 0.0 or self.armature > 0.0


@dataclass
class Drive:
    joint: int
    mode: str
    stiffness: float  # N·m/rad or N/m
    damping: float  # N·m·s/rad or N·s/m
    max_effort: float  # N·m or N (inf: unlimited)
    name: str


class Scene:
    """An articulated mechanism: affine bodies, joints, limits and drives.

    Units are SI throughout: metres, kilograms, seconds, radians.
    """

    def __init__(self, gravity=(0.0, 0.0, -9.81), planar=None):
        self.gravity = _vec3("gravity", gravity)
        self.planar = planar
        self.bodies: list[Body] = []
        self.joints: list[Joint] = []
        self.drives: list[Drive] = []
        self.imported = None  # abd_gym.mjcf.MjcfInfo of a scene made by from_mjcf / from_urdf

    @property
    def planar(self):
        """Whether the step solves 6 unknowns a body in the plane the scene moves in (abd_gym.sim.planar):
        None (the default) where the scene meets every rule there, True where its axes, gravity and
        starts lie in a plane (else the Simulator refuses it), False never."""
        return self._planar

    @planar.setter
    def planar(self, value):
        if value is not None and not isinstance(value, (bool, np.bool_)):
            raise TypeError(f"planar must be None, True or False, got {value!r}")
        self._planar = None if value is None else bool(value)

    @classmethod
    def from_mjcf(cls, path_or_xml, *, exclude=(), ignore_contacts=False) -> "Scene":
        """The scene of an MJCF model (a file path, an XML string, or a compiled ``mujoco.MjModel``),
        compiled by MuJoCo (``pip install "abd-gym[mjcf]"``); the mapping and what is refused:
        ``abd_gym.mjcf``.  ``exclude``: names of bodies left out with their subtrees (and the joints,
        actuators and equalities on them); ``ignore_contacts``: import a model whose geoms can collide,
        without its contacts.  ``scene.imported`` holds the model's MjcfInfo (joint and actuator
        names, qpos0, gear and control ranges, body frames and sites, the timestep)."""
        from ..mjcf.importer import build

        return build(path_or_xml, cls, exclude=exclude, ignore_contacts=ignore_contacts)

    @classmethod
    def from_urdf(cls, path, *, exclude=(), ignore_contacts=False) -> "Scene":
        """The scene of a URDF file, compiled by MuJoCo's URDF reader (as ``from_mjcf``)."""
        from ..mjcf.importer import build

        return build(path, cls, exclude=exclude, ignore_contacts=ignore_contacts)

    # ------------------------------------------------------------------ bodies
    def add_body(
        self,
        shape: Shape,
        mass: float | None = None,
        density: float = 1000.0,
        position=(0.0, 0.0, 0.0),
        rotation=None,
        linear_velocity=(0.0, 0.0, 0.0),
        angular_velocity=(0.0, 0.0, 0.0),
        fixed: bool = False,
        stiffness: float | None = None,
        name: str | None = None,
    ) -> int:
        """Add an affine body; returns its index.

        ``mass`` [kg] overrides ``density`` [kg/m³]; ``stiffness`` is the orthogonality κ [Pa] of
        ``V(A) = κ·vol·‖A Aᵀ − I‖²_F``.  By default ``κ = STIFFNESS_PER_DENSITY·ρ`` with
        ``ρ = m/vol`` the body's mean density (1e5 m²/s² · ρ: κ = 1e8 Pa at 1000 kg/m³), so the
        deformation modes' stiffness 4κ·vol relative to their inertia S = m·∫x xᵀdV/vol does not
        depend on the density.  A fixed body is kinematic: it carries no unknowns.
        """
        if not isinstance(shape, Shape):
            raise ValueError(f"shape must be an abd_gym shape (Box, Sphere, ...), got {shape!r}")
        if mass is not None:
            _finite("mass", mass, positive=True)
        _finite("density", density, positive=True)
        if stiffness is not None:
            _finite("stiffness", stiffness, positive=True)
        name = _name(name, f"body{len(self.bodies)}")
        if not isinstance(fixed, (bool, np.bool_)):
            raise TypeError(f"fixed must be True or False, got {fixed!r}")
        if any(b.name == name for b in self.bodies):
            raise ValueError(f"a body named {name!r} already exists")
        moments = shape.moments(mass=mass, density=density)
        if stiffness is None:
            stiffness = STIFFNESS_PER_DENSITY * moments.mass / shape.volume()
        self.bodies.append(
            Body(
                name=name,
                shape=shape,
                moments=moments,
                fixed=bool(fixed),
                position=_vec3("position", position),
                rotation=rotation_matrix(rotation),
                linear_velocity=_vec3("linear_velocity", linear_velocity),
                angular_velocity=_vec3("angular_velocity", angular_velocity),
                stiffness=float(stiffness),
            )
        )
        return len(self.bodies) - 1

    def body_index(self, body) -> int:
        if isinstance(body, (int, np.integer)) and not isinstance(body, bool):
            if 0 <= int(body) < len(self.bodies):
                return int(body)
        elif isinstance(body, str):
            for k, b in enumerate(self.bodies):
                if b.name == body:
                    return k
        raise ValueError(f"unknown body {body!r} (scene has {len(self.bodies)} bodies)")

    # ------------------------------------------------------------------ joints
    def _add_joint(self, kind, a, b, anchor, axis, strength_ratio, half_length, name, uid):
        ia, ib = self.body_index(a), self.body_index(b)
        if ia == ib:
            raise ValueError(f"a joint needs two different bodies, got {a!r} twice")
        if self.bodies[ia].fixed and self.bodies[ib].fixed:
            raise ValueError(f"joint between two fixed bodies {a!r} and {b!r} has no effect")
        if strength_ratio is not None:
            strength_ratio = _finite("strength_ratio", strength_ratio, positive=True)
        anchor = _vec3("anchor", anchor)
        frame = axis_frame(axis)
        if half_length is None:
            # axis points a body size apart: rotational stiffness comparable to the links' inertia
            half_length = max(self.bodies[ia].shape.bounding_radius(), self.bodies[ib].shape.bounding_radius())
        _finite("half_length", half_length, positive=True)
        self.joints.append(
            Joint(
                kind=kind,
                body_a=ia,
                body_b=ib,
                anchor=anchor,
                frame=frame,
                strength_ratio=strength_ratio,
                half_length=float(half_length),
                name=_name(name, f"{kind}{len(self.joints)}"),
                meta={"constitution_uid": uid, "extra_constitution_uids": []},
            )
        )
        return len(self.joints) - 1

    def add_revolute_joint(self, a, b, anchor, axis, strength_ratio=None, half_length=None, name=None) -> int:
        """Hinge about ``axis`` through ``anchor`` (UID 18); returns the joint index.

        Two points on the axis, ``anchor ± half_length·t̂``, are fixed in both bodies and must
        coincide: ``E = K/2 Σ‖x_a(P) − x_b(P)‖²``, ``K = strength_ratio·(m_a + m_b)`` [kg].
        ``strength_ratio=None`` derives it from the load the joint carries (``strength_ratios``).
        """
        return self._add_joint(REVOLUTE, a, b, anchor, axis, strength_ratio, half_length, name, UID_REVOLUTE_JOINT)

    def add_prismatic_joint(self, a, b, anchor, axis, strength_ratio=None, name=None) -> int:
        """Slider along ``axis`` through ``anchor`` (UID 20, the seed's C0..C3)."""
        return self._add_joint(PRISMATIC, a, b, anchor, axis, strength_ratio, 1.0, name, UID_PRISMATIC_JOINT)

    def add_fixed_joint(self, a, b, anchor=None, strength_ratio=None, half_length=None, name=None) -> int:
        """Weld: four points (anchor and anchor + L·e_k) fixed in both bodies must coincide."""
        if anchor is None:
            anchor = 0.5 * (self.bodies[self.body_index(a)].position + self.bodies[self.body_index(b)].position)
        return self._add_joint(FIXED, a, b, anchor, (0, 0, 1), strength_ratio, half_length, name, UID_FIXED_JOINT)

    def joint_index(self, joint) -> int:
        if isinstance(joint, (int, np.integer)) and not isinstance(joint, bool):
            if 0 <= int(joint) < len(self.joints):
                return int(joint)
        elif isinstance(joint, str):
            for k, j in enumerate(self.joints):
                if j.name == joint:
                    return k
        raise ValueError(f"unknown joint {joint!r} (scene has {len(self.joints)} joints)")

    # ------------------------------------------------------------------ limits
    def _add_limit(self, joint, kind, uid, lower, upper, strength):
        j = self.joints[self.joint_index(joint)]
        if j.kind != kind:
            raise ValueError(f"a {kind} limit needs a {kind} joint, but joint {j.name!r} is {j.kind}")
        lower = _finite("lower", lower)
        upper = _finite("upper", upper)
        if lower > upper:
            raise ValueError(f"limit lower ({lower}) must not exceed upper ({upper})")
        slack = float(inputs.limit_scale(kind == REVOLUTE, lower, upper))
        if not lower - slack <= 0.0 <= upper + slack:
            raise ValueError(f"limit [{lower}, {upper}] of joint {j.name!r} leaves its zero pose (coordinate 0, where the "
                             f"scene starts) outside by more than the limit holds ({slack:.4g}, where its energy "
                             "reaches its strength)")  # fmt: skip
        strength = _finite("strength", strength, positive=True)
        if j.has_limit:
            raise ValueError(f"joint {j.name!r} already has a limit")
        j.attributes.update({"limit/lower": lower, "limit/upper": upper, "limit/strength": strength})
        j.meta["extra_constitution_uids"].append(uid)

    def add_revolute_limit(self, joint, lower, upper, strength=1e3):
        """Revolute joint limit (UID 670): ``E = s(x−u)³`` above, ``s(l−x)³`` below [J], x in rad."""
        lower, upper = _finite("lower", lower), _finite("upper", upper)
        if not (-math.pi <= lower and upper <= math.pi):
            raise ValueError(f"revolute limits must lie in [-pi, pi], got lower={lower}, upper={upper}")
        self._add_limit(joint, REVOLUTE, UID_REVOLUTE_LIMIT, lower, upper, strength)

    def add_prismatic_limit(self, joint, lower, upper, strength=1e3):
        """Prismatic joint limit (UID 669): ``E = s((x−u)/(u−l))³`` above, mirrored below [J]."""
        self._add_limit(joint, PRISMATIC, UID_PRISMATIC_LIMIT, lower, upper, strength)

    # ------------------------------------------------------------------ passive joint terms
    def set_joint_passive(self, joint, damping=0.0, armature=0.0):
        """Passive dynamics of a revolute or prismatic joint's coordinate x (MuJoCo's joint
        ``damping`` and ``armature``), terms of the incremental potential with no control input:

        - damping ``d`` [N·m·s/rad or N·s/m]: the force ``−d ẋ``;
        - armature ``a`` [kg·m² or kg]: an inertia on the coordinate, kinetic energy ``½ a ẋ²`` (a
          motor's rotor seen through its gear), with no weight.

        Both are implicit: ``E = a/(2ĥ²)·(x − x̂ − ĥ v̂)² + d/(2ĥ)·(x − x̂)²`` inside ĥ², with x̂ and v̂
        the step's predicted coordinate and rate (docs/design.md).  Setting both to 0 removes them.
        """
        j = self.joints[self.joint_index(joint)]
        if j.kind not in (REVOLUTE, PRISMATIC):
            raise ValueError(f"passive terms act on revolute or prismatic joints, joint {j.name!r} is {j.kind}")
        damping = _finite("damping", damping, nonnegative=True)
        armature = _finite("armature", armature, nonnegative=True)
        j.attributes["passive/damping"] = damping
        j.attributes["passive/armature"] = armature

    # ------------------------------------------------------------------ drives
    def add_drive(self, joint, mode="effort", stiffness=0.0, damping=0.0, max_effort=math.inf, name=None) -> int:
        """Actuator on a revolute or prismatic joint; returns the drive index (a control column).

        - ``effort``: the control is a torque [N·m] / force [N], clipped to ``max_effort``.
        - ``position``: implicit PD, force ``−k(x − x*) − d ẋ`` with ``x*`` the control.
        - ``velocity``: implicit damper, force ``−d(ẋ − v*)`` with ``v*`` the control.
        PD forces are clipped to ``max_effort`` too (a Huber energy, so the solve stays convex).
        """
        ji = self.joint_index(joint)
        j = self.joints[ji]
        if j.kind not in (REVOLUTE, PRISMATIC):
            raise ValueError(f"drives act on revolute or prismatic joints, joint {j.name!r} is {j.kind}")
        if mode not in DRIVE_MODES:
            raise ValueError(f"drive mode must be one of {DRIVE_MODES}, got {mode!r}")
        stiffness = _finite("stiffness", stiffness, nonnegative=True)
        damping = _finite("damping", damping, nonnegative=True)
        max_effort = _finite("max_effort", max_effort, nonnegative=True, allow_inf=True)
        if max_effort == 0.0:
            raise ValueError("max_effort must be positive")
        if mode == "position" and stiffness == 0.0:
            raise ValueError("a position drive needs stiffness > 0")
        if mode == "velocity" and (damping == 0.0 or stiffness != 0.0):
            raise ValueError("a velocity drive needs damping > 0 and stiffness 0")
        if mode == "effort" and (stiffness or damping):
            raise ValueError("an effort drive takes no stiffness or damping")
        self.drives.append(Drive(ji, mode, stiffness, damping, max_effort, _name(name, f"drive{len(self.drives)}")))
        return len(self.drives) - 1

    # ------------------------------------------------------------------ queries
    @property
    def num_bodies(self):
        return len(self.bodies)

    @property
    def num_joints(self):
        return len(self.joints)

    def joints_of(self, kind):
        return [k for k, j in enumerate(self.joints) if j.kind == kind]

    # ------------------------------------------------------------------ joint strengths
    def strength_ratios(self) -> np.ndarray:
        """(num_joints,) the strength ratio γ of each joint, ``K = γ·(m_i + m_j)`` [kg].

        An explicit ``strength_ratio`` is returned as given.  A derived one is
        ``γ = LOAD_STRENGTH_RATIO·max(1, M/(m_i + m_j))`` with ``M`` [kg] the mass the joint carries
        (``supported_masses``): K ≥ 100·M, so the joint's gap under the load's weight is
        ``M·g·h²/K ≤ g·h²/100`` (0.01 mm at h = 0.01 s), and K = 100·(m_i + m_j) where the joint
        carries no more than its own two bodies.
        """
        load = self.supported_masses()
        out = np.empty(self.num_joints)
        for k, j in enumerate(self.joints):
            if j.strength_ratio is not None:
                out[k] = j.strength_ratio
            else:
                own = self.bodies[j.body_a].mass + self.bodies[j.body_b].mass
                out[k] = LOAD_STRENGTH_RATIO * max(1.0, load[k] / own)
        return out

    def supported_masses(self) -> np.ndarray:
        """(num_joints,) the free mass [kg] each joint carries, through the joint graph (bodies the
        nodes, joints the edges, every fixed body one ground node):

        - a joint whose removal splits its bodies apart carries the side away from the ground (of a
          mechanism with no fixed body, the lighter side);
        - a joint on a loop shares the load with the loop's other joints in proportions the graph
          does not tell, so it is counted as carrying all that hangs together with it: the free mass
          of its bodies' component once the ground is removed (an upper bound, which errs stiff).
        """
        ground = -1
        node = [ground if b.fixed else k for k, b in enumerate(self.bodies)]
        mass = {k: b.mass for k, b in enumerate(self.bodies) if not b.fixed}
        edges = [(node[j.body_a], node[j.body_b]) for j in self.joints]

        def component(start, skip_edge=None, skip_ground=False):
            seen, todo = {start}, [start]
            while todo:
                n = todo.pop()
                for e, (a, b) in enumerate(edges):
                    if e == skip_edge or n not in (a, b):
                        continue
                    other = b if n == a else a
                    if other not in seen and not (skip_ground and other == ground):
                        seen.add(other)
                        todo.append(other)
            return seen

        def free_mass(nodes):
            return sum(mass.get(n, 0.0) for n in nodes)

        out = np.zeros(self.num_joints)
        for e, (a, b) in enumerate(edges):
            side_a = component(a, skip_edge=e)
            if b not in side_a:  # a bridge
                side_b = component(b, skip_edge=e)
                if ground in side_a:
                    out[e] = free_mass(side_b)
                elif ground in side_b:
                    out[e] = free_mass(side_a)
                else:
                    out[e] = min(free_mass(side_a), free_mass(side_b))
            else:
                start = b if a == ground else a
                out[e] = free_mass(component(start, skip_ground=True))
        return out
