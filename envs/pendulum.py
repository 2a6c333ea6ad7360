"""Pendulum-v0: swing a torque-limited pendulum up and hold it upright (as Gymnasium's Pendulum).

Scene (x–z plane, gravity −z; zero pose = pendulum upright): a fixed base and a uniform rod
  (1 kg, 1 m, box cross-section 0.04 m) on a revolute joint about +y at its lower end; an effort
  drive on the hinge.  The rod's weight gives up to m·g·l/2 = 4.9 N·m, more than the 2 N·m the
  motor has: it must swing up.

Coordinates: θ [rad] the hinge angle, 0 upright, positive for a right-hand rotation about +y
  (top towards +x); ±π hanging down.
Action: Box(-1, 1, (1,)): hinge torque a × 2 N·m.
Observation: Box(3,) float32 [cos θ, sin θ, θ̇] (θ̇ in rad/s); bounds ±(1, 1, 100).
Reward: −(θ² + 0.1·min(θ̇, 8)² + 0.001·τ²) with θ wrapped to [−π, π], τ the torque [N·m]:
  per step in [−(π² + 6.4 + 0.004), 0] = [−16.27, 0]; episode return in [−3254, 0].
Termination: none; truncation at 200 steps (8 s).  ``reward_threshold`` −200.
Reset: θ ~ U(−π, π), θ̇ ~ U(−1, 1) rad/s.
Step: dt = 0.02 s, two simulator steps per env step (0.04 s, 25 Hz).
"""
from __future__ import annotations

import math

import numpy as np

import abd_gym as ag
from abd_gym.vector.vector_env import ABDEnv, ABDVectorEnv

MAX_SPEED = 8.0  # rad/s, where the velocity cost saturates
REWARD_RANGE = (-(math.pi**2 + 0.1 * MAX_SPEED**2 + 0.001 * 2.0**2), 0.0)  # per step


def build_pendulum_scene(mass=1.0, length=1.0, max_torque=2.0) -> ag.Scene:
    scene = ag.Scene(gravity=(0.0, 0.0, -9.81))
    base = scene.add_body(ag.Box(half_extents=(0.05, 0.05, 0.05)), mass=1.0, fixed=True, name="base")
    rod = scene.add_body(ag.Box(half_extents=(0.02, 0.02, length / 2)), mass=mass, position=(0, 0, length / 2),
                         name="rod")  # fmt: skip
    hinge = scene.add_revolute_joint(base, rod, anchor=(0, 0, 0), axis=(0, 1, 0), name="hinge")
    scene.add_drive(hinge, mode="effort", max_effort=max_torque)
    return scene


class PendulumVectorEnv(ABDVectorEnv):
    """Batched Pendulum-v0 (see the module docstring)."""

    dt, frame_skip = 0.02, 2
    render_center, render_width, render_size = (0.0, 0.0), 2.6, (400, 400)

    def __init__(self, num_envs=1, *, mass=1.0, length=1.0, max_torque=2.0, **kwargs):
        self.mass, self.length, self.max_torque = mass, length, max_torque
        super().__init__(num_envs, **kwargs)

    def build_scene(self):
        return build_pendulum_scene(self.mass, self.length, self.max_torque)

    def observation_high(self):
        return np.array([1.0, 1.0, self.velocity_bound])

    def initial_state(self, n, rng, options):
        return rng.uniform(-math.pi, math.pi, size=(n, 1)), rng.uniform(-1.0, 1.0, size=(n, 1))

    def observe(self):
        xp, q, v = self.xp, self.coords(), self.velocities()
        return xp.stack([xp.cos(q[:, 0]), xp.sin(q[:, 0]), v[:, 0]], axis=1)

    def reward(self, obs, actions):
        xp = self.xp
        theta = xp.arctan2(obs[:, 1], obs[:, 0])
        speed = xp.clip(obs[:, 2], -MAX_SPEED, MAX_SPEED)
        torque = actions[:, 0] * self.max_torque
        return -(theta**2 + 0.1 * speed**2 + 0.001 * torque**2)


class PendulumEnv(ABDEnv):
    """Single-world Pendulum-v0."""

    vector_class = PendulumVectorEnv


def scripted_policy(obs, mass=1.0, length=1.0, max_torque=2.0):
    """Energy-pumping swing-up, then a PD hold near the top (normalised torque) for obs (N, 3)."""
    obs = np.asarray(obs, dtype=np.float64)
    c, s, w = obs[:, 0], obs[:, 1], obs[:, 2]
    theta = np.arctan2(s, c)
    inertia = mass * length**2 / 3.0
    energy = 0.5 * inertia * w**2 + mass * 9.81 * length / 2 * c  # upright at rest: m g l / 2
    e_top = mass * 9.81 * length / 2
    pump = np.sign(w + 1e-6) * np.sign(e_top - energy) * max_torque
    hold = -(20.0 * theta + 4.0 * w)
    torque = np.where((c > 0.85) & (np.abs(w) < 4.0), hold, pump)
    return np.clip(torque / max_torque, -1.0, 1.0)[:, None].astype(np.float32)
