"""The mechanisms abd_gym is measured on beside MuJoCo (C and Warp): each one a :class:`PeerCase`
holding the same mechanism twice, as an abd_gym :class:`~abd_gym.scene.Scene` and as an MJCF
model, with the random starts both engines take.

Joint coordinates are abd_gym's joint order; ``qpos_of_joint`` says where each joint's coordinate
sits in MuJoCo's ``qpos`` (None for a joint that closes a loop: MuJoCo holds it with a ``connect``
equality and it has no coordinate).  ``mujoco_qpos`` / ``ours_from_qpos`` convert.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from . import mechanisms
from .scene import Scene


@dataclass(frozen=True)
class PeerCase:
    """One mechanism in both engines.

    scene: builds the abd_gym scene.  xml(dt): the MuJoCo model at timestep dt [s] (its default
    integrator; :func:`with_integrator` sets another).  states(n, seed): joint coordinates and
    rates (n, num_joints) in abd_gym's joint order [rad, m, rad/s, m/s], reproducible by seed.
    qpos_of_joint: MuJoCo qpos address of each abd_gym joint (None: a loop-closing joint)."""

    name: str
    scene: Callable[[], Scene]
    xml: Callable[[float], str]
    states: Callable[[int, int], tuple[np.ndarray, np.ndarray]]
    qpos_of_joint: tuple[int | None, ...]

    def mujoco_qpos(self, coords: np.ndarray) -> np.ndarray:
        """MuJoCo qpos (or qvel) rows (n, nq) from abd_gym joint values (n, num_joints)."""
        cols = [j for j, a in enumerate(self.qpos_of_joint) if a is not None]
        out = np.zeros((len(coords), len(cols)))
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


CASES = {
    "cartpole": PeerCase("cartpole", mechanisms.cartpole, lambda dt: CARTPOLE_XML.format(dt=dt), _cartpole_states, (0, 1)),
    "double_pendulum": PeerCase("double_pendulum", mechanisms.double_pendulum,
                                lambda dt: DOUBLE_PENDULUM_XML.format(dt=dt),
                                _double_pendulum_states, (0, 1)),
}  # fmt: skip
