"""The mechanisms abd_gym is measured on beside MuJoCo (C and Warp): each one a :class:`PeerCase`
holding the same mechanism twice, as an abd_gym :class:`~abd_gym.sim.scene.Scene` and as an MJCF
model, with the random starts both engines take.

Joint coordinates are abd_gym's joint order; ``qpos_of_joint`` says where each joint's coordinate
sits in MuJoCo's ``qpos`` (None for a joint that closes a loop: MuJoCo holds it with a ``connect``
equality and it has no coordinate).  ``mujoco_qpos`` / ``ours_from_qpos`` convert.

The cases: ``cartpole`` and ``double_pendulum`` (hand-written MJCF); ``chain5``, ``chain10``,
``chain20`` (0.1 m, 1 kg links); the 3-D chains ``alt_chain5``, ``alt_chain10``, ``alt_chain20``,
``alt_chain30`` (hinges about +y and +x in turn, 0.1 m, 1 kg links) and ``alt_chain30_mixed`` (link
masses 1e-3 to 1e2 kg, ``mechanisms.mixed_masses``); every registered task's mechanism (``PeerCase.tasks`` names the
tasks a case stands for: CartPole-v0 and CartPoleSwingUp-v0 share one), ``fourbar`` and
``slider_crank`` being the closed-loop tasks' and ``pusher_arm`` the 7-joint 3-D arm of
ArmReach-v0 (Gymnasium's ``pusher.xml``).  The abd_gym-built ones reach MuJoCo through
:func:`abd_gym.mjcf.export.to_mjcf`; the ``-v5`` tasks' MuJoCo side is Gymnasium's own model file
(contacts disabled, bodies the task keeps out of its scene deleted), their abd_gym side the scene
the task imports from it.  ``CASES`` builds a case when it is first looked up.
"""
from __future__ import annotations

import importlib
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..sim import mechanisms
from ..sim.scene import Scene


@dataclass(frozen=True)
class PeerCase:
    """One mechanism in both engines.

    scene: builds the abd_gym scene.  xml(dt): the MuJoCo model at timestep dt [s] (its default
    integrator; :func:`with_integrator` sets another).  states(n, seed): joint coordinates and
    rates (n, num_joints) in abd_gym's joint order [rad, m, rad/s, m/s], reproducible by seed.
    qpos_of_joint: MuJoCo qpos address of each abd_gym joint (None: a loop-closing joint).
    loop_joints: the abd_gym joints that close loops (MuJoCo's ``connect`` equalities, in order).
    nq: MuJoCo's qpos size (None: the joints with an address).  tasks: the registered task ids
    whose mechanism this is."""

    name: str
    scene: Callable[[], Scene]
    xml: Callable[[float], str]
    states: Callable[[int, int], tuple[np.ndarray, np.ndarray]]
    qpos_of_joint: tuple[int | None, ...]
    loop_joints: tuple[int, ...] = ()
    nq: int | None = None
    tasks: tuple[str, ...] = ()

    def mujoco_qpos(self, coords: np.ndarray) -> np.ndarray:
        """MuJoCo qpos (or qvel) rows (n, nq) from abd_gym joint values (n, num_joints)."""
        cols = [j for j, a in enumerate(self.qpos_of_joint) if a is not None]
        out = np.zeros((len(coords), self.nq or len(cols)))
        out[:, [self.qpos_of_joint[j] for j in cols]] = np.asarray(coords)[:, cols]
        return out

    def ours_from_qpos(self, qpos: np.ndarray) -> np.ndarray:
        """abd_gym joint values (n, joints with a qpos address) from MuJoCo qpos rows, in abd_gym's
        joint order (loop-closing joints left out)."""
        return np.asarray(qpos)[:, [a for a in self.qpos_of_joint if a is not None]]


def with_integrator(xml: str, integrator: str) -> str:
    """The MJCF with ``<option integrator=...>`` (Euler, implicitfast, implicit, RK4)."""
    return xml.replace("<option ", f'<option integrator="{integrator}" ', 1)


CARTPOLE_XML = """
<mujoco>
  <option timestep="{dt}" gravity="0 0 -9.81"/>
  <worldbody>
    <body name="cart">
      <joint name="slide" type="slide" axis="1 0 0" limited="true" range="-2.4 2.4"/>
      <geom type="box" size="0.2 0.1 0.05" mass="1.0" contype="0" conaffinity="0"/>
      <body name="pole">
        <joint name="hinge" type="hinge" axis="0 1 0"/>
        <geom type="box" size="0.01 0.01 0.5" pos="0 0 0.5" mass="0.1" contype="0" conaffinity="0"/>
      </body>
    </body>
  </worldbody>
  <actuator><motor joint="slide" ctrlrange="-10 10" ctrllimited="true"/></actuator>
</mujoco>
"""

DOUBLE_PENDULUM_XML = """
<mujoco>
  <option timestep="{dt}" gravity="0 0 -9.81"/>
  <worldbody>
    <body name="link0">
      <joint name="j0" type="hinge" axis="0 1 0"/>
      <geom type="box" size="0.02 0.02 0.25" pos="0 0 -0.25" mass="1.0" contype="0" conaffinity="0"/>
      <body name="link1" pos="0 0 -0.5">
        <joint name="j1" type="hinge" axis="0 1 0"/>
        <geom type="box" size="0.02 0.02 0.25" pos="0 0 -0.25" mass="1.0" contype="0" conaffinity="0"/>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


def _cartpole_states(n, seed=0):
    rng = np.random.default_rng(seed)
    return np.stack([rng.uniform(-0.5, 0.5, n), rng.uniform(-0.3, 0.3, n)], 1), np.zeros((n, 2))


def _double_pendulum_states(n, seed=0):
    return np.random.default_rng(seed).uniform(-0.3, 0.3, (n, 2)), np.zeros((n, 2))


def tree_states(scene: Scene, n: int, seed: int = 0, angle=0.3, offset=0.1, rate=0.5):
    """Random starts of a tree mechanism: revolute coordinates U(−angle, angle) [rad], prismatic
    U(−offset, offset) [m], each kept 0.05 of its range inside a limit; rates U(−rate, rate)
    [rad/s or m/s] (the coordinate's unit per second)."""
    rng = np.random.default_rng(seed)
    q, qd = np.zeros((n, scene.num_joints)), np.zeros((n, scene.num_joints))
    for k, j in enumerate(scene.joints):
        if j.kind == "fixed":
            continue
        half = angle if j.kind == "revolute" else offset
        lo, hi = -half, half
        if j.has_limit:
            a, b = j.attributes["limit/lower"], j.attributes["limit/upper"]
            pad = 0.05 * (b - a)
            lo, hi = max(lo, a + pad), min(hi, b - pad)
        q[:, k] = rng.uniform(lo, hi, n)
        qd[:, k] = rng.uniform(-rate, rate, n)
    return q, qd


def exported_case(name: str, scene: Callable[[], Scene], states=None, tasks=()) -> PeerCase:
    """A case whose MuJoCo model is ``to_mjcf`` of its scene; ``states`` (n, seed) → (q, qd),
    default :func:`tree_states` (a tree only: a loop's starts must keep it closed)."""
    from ..mjcf.export import to_mjcf

    built = scene()
    export = to_mjcf(built, 0.01, name=name)
    if export.loop_joints and states is None:
        raise ValueError(f"case {name!r}: a closed loop needs starts from its own kinematics (states=...)")
    return PeerCase(name, scene, lambda dt: to_mjcf(scene(), dt, name=name).xml,
                    states or (lambda n, seed=0: tree_states(built, n, seed)), export.qpos_of_joint,
                    export.loop_joints, export.nq, tuple(tasks))  # fmt: skip


def _task_env(task: str):
    """A one-world vector env of a registered task (its scene and reset kinematics), on Warp's
    default device (a machine may have no CPU compiler)."""
    import warp as wp

    from ..vector.registration import TASKS

    module, _, vector, _, _ = TASKS[task]
    return getattr(importlib.import_module(module), vector)(num_envs=1, device=str(wp.get_device()))


def task_case(name: str, *tasks: str, closed_loop=False) -> PeerCase:
    """The mechanism of ``tasks`` (one scene), exported; a closed loop starts from the task's own
    reset distribution (its kinematics keep the loop closed)."""
    env = _task_env(tasks[0])
    states = None
    if closed_loop:
        def states(n, seed=0):
            return env.initial_state(n, np.random.default_rng(seed), None)
    return exported_case(name, env.build_scene, states, tasks)


def gymnasium_case(name: str, task: str) -> PeerCase:
    """A ``-v5`` task: Gymnasium's model file on MuJoCo's side (contacts disabled, the bodies the
    task excludes deleted, MuJoCo's default integrator), the imported scene on ours."""
    import mujoco

    from ..envs.gymnasium_mjcf import asset_path

    env = _task_env(task)
    scene = env.build_scene()

    def xml(dt):
        spec = mujoco.MjSpec.from_file(str(asset_path(env.asset)))
        for body in env.exclude:
            spec.delete(spec.body(body))
        spec.option.timestep = dt
        spec.option.integrator = mujoco.mjtIntegrator.mjINT_EULER
        spec.option.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT
        return spec.to_xml()

    m = mujoco.MjModel.from_xml_string(xml(0.01))
    qpos = tuple(int(m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, j)])
                 for j in scene.imported.joint_names)  # fmt: skip
    return PeerCase(name, env.build_scene, xml, lambda n, seed=0: tree_states(scene, n, seed), qpos, (), m.nq,
                    (task,))  # fmt: skip


def _chain(n):
    return lambda: mechanisms.chain(n, length=0.1)


def _alt_chain(n, masses=None):
    return lambda: mechanisms.alternating_chain(n, length=0.1, masses=masses)


_BUILDERS = {
    "cartpole": lambda: PeerCase("cartpole", mechanisms.cartpole, lambda dt: CARTPOLE_XML.format(dt=dt),
                                 _cartpole_states, (0, 1)),
    "double_pendulum": lambda: PeerCase("double_pendulum", mechanisms.double_pendulum,
                                        lambda dt: DOUBLE_PENDULUM_XML.format(dt=dt), _double_pendulum_states, (0, 1)),
    "chain5": lambda: exported_case("chain5", _chain(5)),
    "chain10": lambda: exported_case("chain10", _chain(10)),
    "chain20": lambda: exported_case("chain20", _chain(20)),
    "alt_chain5": lambda: exported_case("alt_chain5", _alt_chain(5)),
    "alt_chain10": lambda: exported_case("alt_chain10", _alt_chain(10)),
    "alt_chain20": lambda: exported_case("alt_chain20", _alt_chain(20)),
    "alt_chain30": lambda: exported_case("alt_chain30", _alt_chain(30)),
    "alt_chain30_mixed": lambda: exported_case("alt_chain30_mixed", _alt_chain(30, mechanisms.mixed_masses(30))),
    "fourbar": lambda: task_case("fourbar", "FourBar-v0", closed_loop=True),
    "slider_crank": lambda: task_case("slider_crank", "SliderCrank-v0", closed_loop=True),
    "pendulum": lambda: task_case("pendulum", "Pendulum-v0"),
    "cartpole_task": lambda: task_case("cartpole_task", "CartPole-v0", "CartPoleSwingUp-v0"),
    "double_pendulum_cart": lambda: task_case("double_pendulum_cart", "DoublePendulumCart-v0"),
    "acrobot": lambda: task_case("acrobot", "Acrobot-v0"),
    "reacher": lambda: task_case("reacher", "TwoLinkReacher-v0"),
    "inverted_pendulum_v5": lambda: gymnasium_case("inverted_pendulum_v5", "InvertedPendulum-v5"),
    "inverted_double_pendulum_v5": lambda: gymnasium_case("inverted_double_pendulum_v5", "InvertedDoublePendulum-v5"),
    "reacher_v5": lambda: gymnasium_case("reacher_v5", "Reacher-v5"),
    # the 7-joint arm of Gymnasium's pusher.xml (object and goal deleted), ArmReach-v0's mechanism
    "pusher_arm": lambda: gymnasium_case("pusher_arm", "ArmReach-v0"),
}  # fmt: skip


class _Cases(Mapping):
    """Case name → PeerCase, each built on first lookup (a task case makes its env's scene, and
    a ``-v5`` case needs the ``mujoco`` package)."""

    def __init__(self, builders):
        self._builders, self._built = builders, {}

    def __getitem__(self, name):
        if name not in self._built:
            self._built[name] = self._builders[name]()
        return self._built[name]

    def __iter__(self):
        return iter(self._builders)

    def __len__(self):
        return len(self._builders)


CASES = _Cases(_BUILDERS)


def connect_gap(mjm, xpos, xmat) -> np.ndarray:
    """(W,) the largest distance [m] between the two anchors of any ``connect`` equality of the
    MuJoCo model ``mjm``: ``‖(p₁ + R₁ a₁) − (p₂ + R₂ a₂)‖`` with a₁ = eq_data[0:3] in body1's frame,
    a₂ = eq_data[3:6] in body2's; ``xpos`` (W, nbody, 3), ``xmat`` (W, nbody, 9 or 3×3) batched
    body frames (MuJoCo C's one world: add a leading axis).  0 without connects."""
    xpos = np.asarray(xpos, dtype=np.float64)
    xmat = np.asarray(xmat, dtype=np.float64).reshape(xpos.shape + (3,))
    gap = np.zeros(len(xpos))
    for e in range(mjm.neq):
        if int(mjm.eq_type[e]) != 0:  # mjEQ_CONNECT
            continue
        b1, b2, data = int(mjm.eq_obj1id[e]), int(mjm.eq_obj2id[e]), np.asarray(mjm.eq_data[e], dtype=np.float64)
        x1 = xpos[:, b1] + np.einsum("wij,j->wi", xmat[:, b1], data[:3])
        x2 = xpos[:, b2] + np.einsum("wij,j->wi", xmat[:, b2], data[3:6])
        gap = np.maximum(gap, np.linalg.norm(x1 - x2, axis=-1))
    return gap


def mujoco_limit_penetration(mjm, qpos) -> np.ndarray:
    """(W,) how far [rad or m] any limited hinge or slide joint of ``mjm`` is beyond its range,
    from qpos rows (W, nq); 0 inside every range."""
    qpos = np.asarray(qpos, dtype=np.float64)
    out = np.zeros(len(qpos))
    for j in range(mjm.njnt):
        if mjm.jnt_limited[j] and int(mjm.jnt_type[j]) in (2, 3):  # slide, hinge
            x = qpos[:, int(mjm.jnt_qposadr[j])]
            lo, hi = mjm.jnt_range[j]
            out = np.maximum(out, np.maximum(lo - x, x - hi))
    return out


def ours_limit_penetration(scene: Scene, coords) -> np.ndarray:
    """(W,) how far [rad or m] any limited abd_gym joint is beyond [lower, upper], from joint
    coordinates (W, num_joints); 0 inside every limit."""
    coords = np.asarray(coords, dtype=np.float64)
    out = np.zeros(len(coords))
    for k, j in enumerate(scene.joints):
        if j.has_limit:
            x = coords[:, k]
            out = np.maximum(out, np.maximum(j.attributes["limit/lower"] - x, x - j.attributes["limit/upper"]))
    return out
