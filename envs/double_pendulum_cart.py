"""DoublePendulumCart-v0: balance a double inverted pendulum (two poles in a chain) on a cart.

Scene (``abd_gym.envs.cartpole.build_cart_scene`` with two poles; x–z plane, gravity −z; zero pose = both
  poles upright): cart (1 kg) on a slider along +x with prismatic end stops at ±2.4 m; pole 1
  (0.1 kg, 0.5 m) hinged about +y on the cart, pole 2 (0.1 kg, 0.5 m) hinged about +y on top of
  pole 1; a force drive on the slider (|F| ≤ 20 N).

Coordinates: x [m] cart displacement; θ1 [rad] pole 1 relative to the cart, θ2 [rad] pole 2
  relative to pole 1 (0 straight), positive for a right-hand rotation about +y (tops towards +x).
Action: Box(-1, 1, (1,)): force a × 20 N.
Observation: Box(8,) float32 [x, sin θ1, sin θ2, cos θ1, cos θ2, ẋ, θ̇1, θ̇2] (m, –, m/s, rad/s);
  bounds ±(4.8, 1, 1, 1, 1, 100, 100, 100).
Reward: r = clip(1 − 5·(1 − h), 0, 1) with h = z_tip / 1.0 m the height of pole 2's tip over the
  hinge, as a fraction of the full height: per step in [0, 1] (1 upright, 0 once the tip has
  dropped by 20 %); episode return in [0, 500].
Termination: h < 0.8 (the tip dropped by more than 20 % of the full height) or |x| > 2.4 m.
  Truncation at 500 steps (10 s); ``reward_threshold`` 450.
Reset: x, θ1, θ2, ẋ, θ̇1, θ̇2 ~ U(−0.05, 0.05) each.
Step: dt = 0.01 s, two simulator steps per env step (0.02 s, 50 Hz).
"""
from __future__ import annotations

import numpy as np

from abd_gym.vector.vector_env import ABDEnv, ABDVectorEnv
from abd_gym.envs.cartpole import build_cart_scene, draw_track

REWARD_RANGE = (0.0, 1.0)  # per step


class DoublePendulumCartVectorEnv(ABDVectorEnv):
    """Batched DoublePendulumCart-v0 (see the module docstring)."""

    dt, frame_skip = 0.01, 2
    render_center, render_width, render_size = (0.0, 0.4), 6.0, (600, 400)
    track = 2.4  # m
    min_height = 0.8  # of the full height

    def __init__(self, num_envs=1, *, cart_mass=1.0, pole_masses=(0.1, 0.1), pole_lengths=(0.5, 0.5), force=20.0,
                 **kwargs):  # fmt: skip
        self.cart_mass, self.pole_masses, self.pole_lengths, self.force = cart_mass, pole_masses, pole_lengths, force
        self.height = float(sum(pole_lengths))
        super().__init__(num_envs, **kwargs)

    def build_scene(self):
        return build_cart_scene(self.pole_lengths, self.pole_masses, self.cart_mass, self.track, self.force)

    def observation_high(self):
        return np.array([2 * self.track, 1, 1, 1, 1, self.velocity_bound, self.velocity_bound, self.velocity_bound])

    def initial_state(self, n, rng, options):
        s = rng.uniform(-0.05, 0.05, size=(n, 6))
        return s[:, :3], s[:, 3:]

    def observe(self):
        xp, q, v = self.xp, self.coords(), self.velocities()
        return xp.concatenate([q[:, :1], xp.sin(q[:, 1:]), xp.cos(q[:, 1:]), v], axis=1)

    def tip_height(self, obs):
        """Height of pole 2's tip over the cart hinge, as a fraction of the full height."""
        l1, l2 = self.pole_lengths
        c1, s1, s2, c2 = obs[:, 3], obs[:, 1], obs[:, 2], obs[:, 4]
        return (l1 * c1 + l2 * (c1 * c2 - s1 * s2)) / self.height  # cos(θ1 + θ2)

    def reward(self, obs, actions):
        return self.xp.clip(1.0 - 5.0 * (1.0 - self.tip_height(obs)), 0.0, 1.0)

    def terminated(self, obs):
        return (self.tip_height(obs) < self.min_height) | (self.xp.abs(obs[:, 0]) > self.track)

    def render_extras(self, canvas, world):
        draw_track(canvas, self.track)


class DoublePendulumCartEnv(ABDEnv):
    """Single-world DoublePendulumCart-v0."""

    vector_class = DoublePendulumCartVectorEnv


# LQR gains (normalised force per unit of x, θ1, θ2, ẋ, θ̇1, θ̇2) of the default scene, from a
# finite-difference linearisation of the simulator about upright (Q = diag(1, 10, 10, .1, .1, .1), R = 1)
LQR_GAINS = np.array([-0.5872, -4.6439, -12.9703, -0.8102, -1.9218, -1.7475])


def scripted_policy(obs):
    """Linear balancing controller (LQR about upright) for observations (N, 8)."""
    obs = np.asarray(obs, dtype=np.float64)
    state = np.concatenate([obs[:, :1], np.arctan2(obs[:, 1:3], obs[:, 3:5]), obs[:, 5:]], axis=1)
    return np.clip(state @ LQR_GAINS, -1.0, 1.0)[:, None].astype(np.float32)
