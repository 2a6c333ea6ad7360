"""Acrobot-v0: swing the tip of a two-link chain above a line, with torque at the elbow only.

Scene (x–z plane, gravity −z; zero pose = both links hanging straight down): a fixed base; link 1
  (1 kg, 1 m) on the shoulder hinge about +y at the base (passive); link 2 (1 kg, 1 m) on the
  elbow hinge about +y at link 1's lower end, with a revolute limit ±2.5 rad (UID 670) and an
  effort drive (|τ| ≤ 4 N·m).  The elbow motor cannot lift link 2 straight (its weight gives up
  to 4.9 N·m): the chain must be swung up by pumping.

Coordinates: θ1 [rad] shoulder (0 hanging down), θ2 [rad] elbow relative to link 1 (0
  straight), positive for a right-hand rotation about +y.  The tip is at height
  −cos θ1 − cos(θ1 + θ2) [m] over the shoulder.
Action: Box(-1, 1, (1,)): elbow torque a × 4 N·m.
Observation: Box(6,) float32 [cos θ1, sin θ1, cos θ2, sin θ2, θ̇1, θ̇2] (θ̇ in rad/s); bounds
  ±(1, 1, 1, 1, 100, 100).
Reward: a dense version of the classic −1 per step: r = −(L − h)/(2L) with h the tip height and
  L = 2 m the chain length, so −1 hanging straight down, rising towards 0 as the tip rises; 0 on
  the step that reaches the goal.  Per step in [−1, 0], episode return in [−500, 0]; every step
  costs, so reaching the goal fast pays.
Termination: the tip rises more than 0.5 m above the shoulder (the classic asks for one link
  length; the config and threshold are set for 0.5 m).  Truncation at 500 steps (25 s);
  ``reward_threshold`` −100.
Reset: θ1, θ2, θ̇1, θ̇2 ~ U(−0.1, 0.1) each.
Step: dt = 0.01 s, five simulator steps per env step (0.05 s, 20 Hz).
"""
from __future__ import annotations

import numpy as np

import abd_gym as ag
from abd_gym.vector.vector_env import ABDEnv, ABDVectorEnv


REWARD_RANGE = (-1.0, 0.0)  # per step


def build_acrobot_scene(masses=(1.0, 1.0), lengths=(1.0, 1.0), max_torque=4.0, elbow_limit=2.5,
                        limit_strength=1e3) -> ag.Scene:  # fmt: skip
    scene = ag.Scene(gravity=(0.0, 0.0, -9.81))
    base = scene.add_body(ag.Box(half_extents=(0.05, 0.05, 0.05)), mass=1.0, fixed=True, name="base")
    l1, l2 = lengths
    link1 = scene.add_body(ag.Box(half_extents=(0.02, 0.02, l1 / 2)), mass=masses[0], position=(0, 0, -l1 / 2),
                           name="link1")  # fmt: skip
    link2 = scene.add_body(ag.Box(half_extents=(0.02, 0.02, l2 / 2)), mass=masses[1], position=(0, 0, -l1 - l2 / 2),
                           name="link2")  # fmt: skip
    scene.add_revolute_joint(base, link1, anchor=(0, 0, 0), axis=(0, 1, 0), name="shoulder")
    elbow = scene.add_revolute_joint(link1, link2, anchor=(0, 0, -l1), axis=(0, 1, 0), name="elbow")
    scene.add_revolute_limit(elbow, -elbow_limit, elbow_limit, strength=limit_strength)
    scene.add_drive(elbow, mode="effort", max_effort=max_torque)
    return scene


class AcrobotVectorEnv(ABDVectorEnv):
    """Batched Acrobot-v0 (see the module docstring)."""

    dt, frame_skip = 0.01, 5
    render_center, render_width, render_size = (0.0, 0.0), 4.6, (400, 400)

    def __init__(self, num_envs=1, *, masses=(1.0, 1.0), lengths=(1.0, 1.0), max_torque=4.0, elbow_limit=2.5,
                 goal_height=0.5, **kwargs):  # fmt: skip
        self.masses, self.lengths, self.max_torque, self.elbow_limit = masses, lengths, max_torque, elbow_limit
        self.goal_height = goal_height
        super().__init__(num_envs, **kwargs)

    def build_scene(self):
        return build_acrobot_scene(self.masses, self.lengths, self.max_torque, self.elbow_limit)

    def observation_high(self):
        return np.array([1, 1, 1, 1, self.velocity_bound, self.velocity_bound])

    def initial_state(self, n, rng, options):
        s = rng.uniform(-0.1, 0.1, size=(n, 4))
        return s[:, :2], s[:, 2:]

    def observe(self):
        xp, q, v = self.xp, self.coords(), self.velocities()
        return xp.stack([xp.cos(q[:, 0]), xp.sin(q[:, 0]), xp.cos(q[:, 1]), xp.sin(q[:, 1]), v[:, 0], v[:, 1]], axis=1)

    def tip_height(self, obs):
        """Height of link 2's end over the shoulder [m]."""
        c1, s1, c2, s2 = obs[:, 0], obs[:, 1], obs[:, 2], obs[:, 3]
        return -(self.lengths[0] * c1 + self.lengths[1] * (c1 * c2 - s1 * s2))

    def terminated(self, obs):
        return self.tip_height(obs) > self.goal_height

    def reward(self, obs, actions):
        length = sum(self.lengths)
        h = self.tip_height(obs)
        return self.xp.where(h > self.goal_height, 0.0, -(length - h) / (2 * length))

    def render_extras(self, canvas, world):
        canvas.segment((-2.2, 0, self.goal_height), (2.2, 0, self.goal_height), 0.01, (160, 160, 160))


class AcrobotEnv(ABDEnv):
    """Single-world Acrobot-v0."""

    vector_class = AcrobotVectorEnv


# a tanh-linear swing-up policy found by a few rounds of the cross-entropy method
SWING_UP_WEIGHTS = np.array([-1.13, 1.72, 0.5, 1.36, 3.5, 1.59])
SWING_UP_BIAS = 1.1


def scripted_policy(obs):
    """Swing-up policy a = tanh(w·obs + b) (normalised torque) for observations (N, 6)."""
    obs = np.asarray(obs, dtype=np.float64)
    return np.tanh(obs @ SWING_UP_WEIGHTS + SWING_UP_BIAS)[:, None].astype(np.float32)
