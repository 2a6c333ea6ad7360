"""InvertedPendulum-v5: Gymnasium's MuJoCo cart-pole, built from its own ``inverted_pendulum.xml``.

Scene: the file as MuJoCo compiles it (``Scene.from_mjcf``): a cart (10.47 kg) on the slider
  ``slider`` along +x, range ±1 m; a pole (5.02 kg, 0.6 m capsule) on the hinge ``hinge`` about
  +y, range ±90°; damping 1 on both joints; gravity −9.81 m/s² along z.  The motor ``slide``
  (gear 100) pushes the cart.
Coordinates: MuJoCo's qpos: x [m] cart, θ [rad] pole (0 upright, positive tipping towards +x).
Action: Box(-3, 3, (1,)) (the motor's ctrlrange): the cart force u = 100 · a [N].
Observation: Box(4,) float32 [x, θ, ẋ, θ̇] (qpos, qvel) in m, rad, m/s, rad/s; bounds
  ±(2, π, 100, 100): beyond the slider's range, the hinge's range and any rate the task reaches
  (Gymnasium: float64, ±inf).
Reward: 1 while the pole is upright, 0 in the step that ends the episode: per step in [0, 1],
  episode return in [0, 1000].
Termination: |θ| > 0.2 rad (or a non-finite observation: a failed world).  Truncation at 1000
  steps; ``reward_threshold`` 950.
Reset: qpos, qvel ~ U(−0.01, 0.01) each (``reset_noise_scale``).
Step: dt = 0.02 s (the file's timestep), frame_skip 2 (0.04 s, 25 Hz).

Differs from Gymnasium: the physics (abd_gym's affine bodies and implicit BDF2 against MuJoCo's
RK4 with soft joint limits; the limits are abd_gym's cubic limit energies), float32 observations
with finite bounds, and the reset draws, which come from abd_gym's generator (same distribution,
another stream).
"""
from __future__ import annotations

import math

import numpy as np

from abd_gym.vector.task import float32_of
from abd_gym.vector.vector_env import ABDEnv

from abd_gym.envs.gymnasium_mjcf import GymnasiumMjcfEnv

REWARD_RANGE = (0.0, 1.0)  # per step

# LQR gains on (x, θ, ẋ, θ̇) of MuJoCo's linearisation at upright, control a = −K·s (ctrl units)
LQR_GAINS = np.array([-0.7415, -6.0275, -0.8673, -1.0079])


def draw_rail(canvas, half_length=1.0):
    """The file's rail (a world geom, 0.02 m capsule along x) that the cart runs on."""
    canvas.segment((-half_length, 0, 0), (half_length, 0, 0), 0.04, (77, 77, 179))


class InvertedPendulumVectorEnv(GymnasiumMjcfEnv):
    """Batched InvertedPendulum-v5 (see the module docstring)."""

    asset = "inverted_pendulum.xml"
    dt, frame_skip = 0.02, 2
    render_center, render_width, render_size = (0.0, 0.1), 3.0, (600, 400)
    theta_threshold = 0.2  # rad

    def __init__(self, num_envs=1, *, reset_noise_scale=0.01, **kwargs):
        self.reset_noise_scale = reset_noise_scale
        super().__init__(num_envs, **kwargs)

    def observation_high(self):
        return np.array([2.0, math.pi, self.velocity_bound, self.velocity_bound])

    def initial_state(self, n, rng, options):
        s = self.reset_noise_scale
        x = rng.uniform(-s, s, size=(2, n, 2))  # the coordinates' draws, then the rates'
        return x[0], x[1]

    def observe(self):
        return self.xp.concatenate([self.coords(), self.velocities()], axis=1)

    def terminated(self, obs):
        return self.xp.abs(obs[:, 1]) > self.theta_threshold

    def reward(self, obs, actions):
        return self.f32(~self.terminated(obs))

    def world_observation(self, q, v):
        return q + v

    def world_terminated(self, obs):
        return abs(obs[1]) > float32_of[self.theta_threshold]

    def world_reward(self, obs, action):
        return 0.0 if self.world_terminated(obs) else 1.0

    def render_extras(self, canvas, world):
        draw_rail(canvas)


class InvertedPendulumEnv(ABDEnv):
    """Single-world InvertedPendulum-v5."""

    vector_class = InvertedPendulumVectorEnv


def scripted_policy(obs):
    """LQR balancer a = −K·(x, θ, ẋ, θ̇), clipped to ±3, for observations (N, 4)."""
    obs = np.asarray(obs, dtype=np.float64)
    return np.clip(-obs @ LQR_GAINS, -3.0, 3.0)[:, None].astype(np.float32)
