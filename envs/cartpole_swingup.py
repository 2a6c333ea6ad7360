"""CartPoleSwingUp-v0: swing the pole up from hanging down and balance it, on a track with end stops.

Scene: the CartPole-v0 scene (``abd_gym.envs.cartpole.build_cart_scene``): cart (1 kg) on a slider along
  +x with prismatic end stops at ±2.4 m, uniform pole (0.1 kg, 1 m) on a hinge about +y, zero
  pose = pole upright; force drive on the slider (|F| ≤ 10 N).  The end stops are physical: the
  episode does not end when the cart reaches them, the limit holds the cart.

Coordinates: x [m] cart displacement; θ [rad] pole angle, 0 upright, ±π hanging down, positive
  for the top leaning towards +x.
Action: Box(-1, 1, (1,)): force a × 10 N.
Observation: Box(5,) float32 [x, ẋ, cos θ, sin θ, θ̇] (m, m/s, –, –, rad/s); bounds
  ±(4.8, 100, 1, 1, 100).
Reward (as DeepMind Control's cartpole swing-up, smooth): r = upright · centred · small_control
  · small_velocity with upright = (1 + cos θ)/2, centred = 1 − 0.5·min((x/2.4)², 1),
  small_control = (4 + 1 − a²)/5, small_velocity = (1 + 1/(1 + 0.1·θ̇²))/2: per step in [0, 1],
  episode return in [0, 500].  Hanging still at the centre earns 0, balancing still at the centre
  earns 1 per step.
Termination: none; truncation at 500 steps (10 s).  ``reward_threshold`` 350.
Reset: θ = π + U(−0.05, 0.05), x, ẋ, θ̇ ~ U(−0.05, 0.05).
Step: dt = 0.02 s, one simulator step per env step.
"""
from __future__ import annotations

import math

import numpy as np

from abd_gym.vector.vector_env import ABDEnv, ABDVectorEnv
from abd_gym.envs.cartpole import build_cart_scene, draw_track

REWARD_RANGE = (0.0, 1.0)  # per step


class CartPoleSwingUpVectorEnv(ABDVectorEnv):
    """Batched CartPoleSwingUp-v0 (see the module docstring)."""

    dt, frame_skip = 0.02, 1
    render_center, render_width, render_size = (0.0, 0.0), 6.0, (600, 400)
    track = 2.4  # m

    def __init__(self, num_envs=1, *, cart_mass=1.0, pole_mass=0.1, pole_length=1.0, force=10.0, **kwargs):
        self.cart_mass, self.pole_mass, self.pole_length, self.force = cart_mass, pole_mass, pole_length, force
        super().__init__(num_envs, **kwargs)

    def build_scene(self):
        return build_cart_scene((self.pole_length,), (self.pole_mass,), self.cart_mass, self.track, self.force)

    def observation_high(self):
        return np.array([2 * self.track, self.velocity_bound, 1.0, 1.0, self.velocity_bound])

    def initial_state(self, n, rng, options):
        s = rng.uniform(-0.05, 0.05, size=(n, 4))
        return np.stack([s[:, 0], math.pi + s[:, 2]], axis=1), s[:, [1, 3]]

    def observe(self):
        xp, q, v = self.xp, self.coords(), self.velocities()
        return xp.stack([q[:, 0], v[:, 0], xp.cos(q[:, 1]), xp.sin(q[:, 1]), v[:, 1]], axis=1)

    def reward(self, obs, actions):
        xp = self.xp
        upright = (1.0 + obs[:, 2]) / 2
        centred = 1.0 - 0.5 * xp.clip((obs[:, 0] / self.track) ** 2, 0.0, 1.0)
        small_control = (5.0 - actions[:, 0] ** 2) / 5
        small_velocity = (1.0 + 1.0 / (1.0 + 0.1 * obs[:, 4] ** 2)) / 2
        return upright * centred * small_control * small_velocity

    def render_extras(self, canvas, world):
        draw_track(canvas, self.track)


class CartPoleSwingUpEnv(ABDEnv):
    """Single-world CartPoleSwingUp-v0."""

    vector_class = CartPoleSwingUpVectorEnv


def scripted_policy(obs, pole_mass=0.1, pole_length=1.0):
    """Energy-pumping swing-up with cart centring, then linear balancing near the top; obs (N, 5)."""
    obs = np.asarray(obs, dtype=np.float64)
    x, xd, c, s, w = obs.T
    theta = np.arctan2(s, c)
    inertia = pole_mass * pole_length**2 / 3
    energy = 0.5 * inertia * w**2 + pole_mass * 9.81 * pole_length / 2 * (c - 1.0)  # 0 upright at rest
    pump = 40.0 * energy * w * c - 0.3 * x - 0.3 * xd
    balance = 0.1 * x + 0.25 * xd + 2.5 * theta + 0.5 * w
    return np.clip(np.where(c > 0.9, balance, pump), -1.0, 1.0)[:, None].astype(np.float32)
