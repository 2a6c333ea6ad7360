"""An abd_gym Scene as an equivalent MuJoCo model (MJCF), the inverse of ``abd_gym.mjcf``.

The mapping:

- **Tree.** The joint graph (bodies the nodes, every fixed body one ground node) is cut to a
  spanning tree rooted at the ground: prismatic and fixed joints are taken first (MuJoCo can close
  a loop only through a point or a weld), then revolute joints, each in scene order, each kept if
  it reaches a body the tree does not hold yet.  The tree is MuJoCo's body tree; fixed bodies are
  the ``worldbody``.
- **Bodies** are placed at their zero pose, their frame the abd body frame, so MuJoCo's
  ``qpos = 0`` is abd_gym's zero pose and a joint's qpos value is its abd_gym coordinate.  Mass
  properties are one ``<inertial>``: mass m, centre of mass c and the full inertia tensor about
  it, ``I = tr(Σ)·1 − Σ`` with ``Σ = S − m c cᵀ`` from the body's second moment S (exact for any
  shape).  No geoms: the model has no contacts.
- **Joints** of the tree: revolute → hinge, prismatic → slide, at the joint anchor, axis t̂ (the
  parent must be the joint's ``body_a``: then MuJoCo's positive rotation/translation of the
  child is abd_gym's positive coordinate); fixed → the child body has no joint (MuJoCo welds it).
  Limits → ``limited="true" range="lower upper"`` (no margin); passive damping and armature →
  the joint's ``damping`` and ``armature``.
- **Loop-closing joints**: revolute → a ``connect`` equality at the anchor (exact for a planar
  loop, whose tree hinges hold the axis); fixed → a ``weld`` equality.
- **Drives** in order (actuator k is drive k): effort → ``motor`` with ``ctrlrange ±max_effort``;
  position → ``position`` with kp = stiffness, kv = damping; velocity → ``velocity`` with
  kv = damping; a finite max_effort of a PD drive → ``forcerange``.
- **Gravity** and the timestep → ``<option>``.

Refused with a ValueError naming it: a loop-closing prismatic joint, a limit, drive or passive
term on a loop-closing joint, a tree joint whose ``body_a`` is the child, and a scene without a
fixed body.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..sim.scene import FIXED, PRISMATIC, REVOLUTE, Scene

GROUND = -1


@dataclass(frozen=True)
class MjcfExport:
    """An exported model: ``xml`` the MJCF; ``qpos_of_joint`` the MuJoCo qpos address of each
    abd_gym joint (None: a fixed joint or one that closes a loop); ``loop_joints`` the abd_gym
    joints held by equalities, in MuJoCo's equality order; ``nq`` MuJoCo's qpos size."""

    xml: str
    qpos_of_joint: tuple
    loop_joints: tuple
    nq: int


def spanning_tree(scene: Scene):
    """(tree joints, loop-closing joints) of the joint graph (see the module docstring)."""
    node = [GROUND if b.fixed else k for k, b in enumerate(scene.bodies)]
    root = {n: n for n in set(node)}

    def find(n):
        while root[n] != n:
            root[n] = root[root[n]]
            n = root[n]
        return n

    order = [k for k, j in enumerate(scene.joints) if j.kind != REVOLUTE]
    order += [k for k, j in enumerate(scene.joints) if j.kind == REVOLUTE]
    tree, loops = [], []
    for k in order:
        j = scene.joints[k]
        a, b = find(node[j.body_a]), find(node[j.body_b])
        if a == b:
            loops.append(k)
        else:
            root[a] = b
            tree.append(k)
    return sorted(tree), sorted(loops)


def _fmt(values) -> str:
    """Numbers as the shortest text that reads back to the same float64."""
    return " ".join(repr(float(v)) for v in np.atleast_1d(values))


def _quat(R) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation matrix (Shepperd's method)."""
    t = np.trace(R)
    if t > 0:
        s = 2.0 * math.sqrt(1.0 + t)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k])
        q = [0.0] * 4
        q[0] = (R[k, j] - R[j, k]) / s
        q[1 + i], q[1 + j], q[1 + k] = 0.25 * s, (R[j, i] + R[i, j]) / s, (R[k, i] + R[i, k]) / s
    q = np.asarray(q)
    return q / np.linalg.norm(q)


def inertia_about_com(body):
    """(mass [kg], centre of mass (3,) [m], inertia about it (3, 3) [kg·m²]) in the body frame:
    ``I = tr(Σ)·1 − Σ``, ``Σ = S − m c cᵀ``."""
    m = body.moments
    sigma = m.second_moment - m.mass * np.outer(m.com, m.com)
    return m.mass, np.asarray(m.com, dtype=np.float64), np.trace(sigma) * np.eye(3) - sigma


class _Writer:
    def __init__(self, scene: Scene, dt: float, name: str):
        if not any(b.fixed for b in scene.bodies):
            raise ValueError("to_mjcf: the scene has no fixed body (MuJoCo's tree hangs from the world)")
        self.scene, self.dt, self.name = scene, dt, name
        self.tree, self.loops = spanning_tree(scene)
        for k in self.loops:
            j = scene.joints[k]
            if j.kind == PRISMATIC:
                raise ValueError(f"to_mjcf: prismatic joint {j.name!r} closes a loop (MuJoCo has no sliding equality)")
            if j.has_limit or j.has_passive or any(d.joint == k for d in scene.drives):
                raise ValueError(f"to_mjcf: joint {j.name!r} closes a loop and has a limit, drive or passive term")
        self.children = {}  # parent body (GROUND) -> [(child body, joint)]
        node = [GROUND if b.fixed else k for k, b in enumerate(scene.bodies)]
        adjacent = {}
        for k in self.tree:
            j = scene.joints[k]
            a, b = node[j.body_a], node[j.body_b]
            adjacent.setdefault(a, []).append((b, k))
            adjacent.setdefault(b, []).append((a, k))
        seen, todo = {GROUND}, [GROUND]
        while todo:
            parent = todo.pop(0)
            for child, k in adjacent.get(parent, []):
                if child in seen:
                    continue
                if node[scene.joints[k].body_a] != parent:
                    raise ValueError(f"to_mjcf: joint {scene.joints[k].name!r} has the child body "
                                     f"{scene.bodies[child].name!r} as body_a (MuJoCo's coordinate would be the "
                                     "negative of abd_gym's); add the joint parent first")  # fmt: skip
                seen.add(child)
                self.children.setdefault(parent, []).append((child, k))
                todo.append(child)
        self.qpos = {}

    def body(self, index, joint, parent_pos, parent_rot, depth):
        s, b = self.scene, self.scene.bodies[index]
        pad = "  " * depth
        pos = parent_rot.T @ (b.position - parent_pos)
        rot = parent_rot.T @ b.rotation
        lines = [f'{pad}<body name="{b.name}" pos="{_fmt(pos)}" quat="{_fmt(_quat(rot))}">']
        mass, com, inertia = inertia_about_com(b)
        full = [inertia[0, 0], inertia[1, 1], inertia[2, 2], inertia[0, 1], inertia[0, 2], inertia[1, 2]]
        lines.append(f'{pad}  <inertial pos="{_fmt(com)}" mass="{_fmt(mass)}" fullinertia="{_fmt(full)}"/>')
        j = s.joints[joint]
        if j.kind in (REVOLUTE, PRISMATIC):
            kind = "hinge" if j.kind == REVOLUTE else "slide"
            attrs = [f'name="{j.name}"', f'type="{kind}"', f'pos="{_fmt(b.to_local_point(j.anchor))}"',
                     f'axis="{_fmt(b.to_local_dir(j.frame[0]))}"']  # fmt: skip
            if j.has_limit:
                bounds = [j.attributes["limit/lower"], j.attributes["limit/upper"]]
                attrs.append(f'limited="true" range="{_fmt(bounds)}"')
            if j.damping:
                attrs.append(f'damping="{_fmt(j.damping)}"')
            if j.armature:
                attrs.append(f'armature="{_fmt(j.armature)}"')
            self.qpos[joint] = len(self.qpos)
            lines.append(f"{pad}  <joint {' '.join(attrs)}/>")
        elif j.kind != FIXED:
            raise ValueError(f"to_mjcf: joint {j.name!r} of kind {j.kind!r} has no MuJoCo equivalent")
        for child, k in self.children.get(index, []):
            lines += self.body(child, k, b.position, b.rotation, depth + 1)
        lines.append(f"{pad}</body>")
        return lines

    def equalities(self):
        s, out = self.scene, []
        for k in self.loops:
            j = s.joints[k]
            a, b = s.bodies[j.body_a], s.bodies[j.body_b]
            first, second = (b, a) if a.fixed else (a, b)  # a fixed body is MuJoCo's world
            names = f'body1="{first.name}"' + ("" if second.fixed else f' body2="{second.name}"')
            local = first.to_local_point(j.anchor)
            if j.kind == REVOLUTE:
                out.append(f'    <connect name="{j.name}" {names} anchor="{_fmt(local)}"/>')
            else:  # FIXED: the relative pose at the zero pose is the one held
                out.append(f'    <weld name="{j.name}" {names} anchor="{_fmt(local)}"/>')
        return ["  <equality>", *out, "  </equality>"] if out else []

    def actuators(self):
        out = []
        for d in self.scene.drives:
            joint = self.scene.joints[d.joint].name
            if d.joint not in self.qpos:
                raise ValueError(f"to_mjcf: drive {d.name!r} acts on joint {joint!r}, which has no MuJoCo coordinate")
            limit = math.isfinite(d.max_effort)
            if d.mode == "effort":
                rng = f' ctrllimited="true" ctrlrange="{_fmt(-d.max_effort)} {_fmt(d.max_effort)}"' if limit else ""
                out.append(f'    <motor name="{d.name}" joint="{joint}"{rng}/>')
                continue
            force = f' forcelimited="true" forcerange="{_fmt(-d.max_effort)} {_fmt(d.max_effort)}"' if limit else ""
            if d.mode == "position":
                out.append(f'    <position name="{d.name}" joint="{joint}" kp="{_fmt(d.stiffness)}" '
                           f'kv="{_fmt(d.damping)}"{force}/>')  # fmt: skip
            else:
                out.append(f'    <velocity name="{d.name}" joint="{joint}" kv="{_fmt(d.damping)}"{force}/>')
        return ["  <actuator>", *out, "  </actuator>"] if out else []

    def xml(self):
        s = self.scene
        lines = [f'<mujoco model="{self.name}">', '  <compiler angle="radian" autolimits="true"/>',
                 f'  <option timestep="{_fmt(self.dt)}" gravity="{_fmt(s.gravity)}"/>', "  <worldbody>"]  # fmt: skip
        for child, k in self.children.get(GROUND, []):
            lines += self.body(child, k, np.zeros(3), np.eye(3), 2)
        lines.append("  </worldbody>")
        lines += self.equalities() + self.actuators() + ["</mujoco>", ""]
        return "\n".join(lines)


def to_mjcf(scene: Scene, dt: float, *, name: str = "abd_gym") -> MjcfExport:
    """The MuJoCo model of ``scene`` at timestep ``dt`` [s] (see the module docstring)."""
    w = _Writer(scene, float(dt), name)
    xml = w.xml()
    qpos = tuple(w.qpos.get(k) for k in range(scene.num_joints))
    return MjcfExport(xml, qpos, tuple(w.loops), len(w.qpos))
