"""CartPole-v0: balance a pole on a cart, with a continuous force (close to the classic task).

Scene (x–z plane, gravity −z; zero pose = pole upright, cart at the track centre):
  a fixed rail; a cart (1 kg, box 0.4×0.2×0.1 m) on a prismatic joint along +x with a prismatic
  limit at the track ends ±2.4 m (UID 669); a uniform pole (0.1 kg, 1 m) on a revolute joint
  about +y at the cart centre.  An effort drive on the slider pushes the cart.

Coordinates: x [m] cart displacement along +x; θ [rad] pole angle, positive for a right-hand
  rotation about +y, i.e. the pole's top leaning towards +x.
Action: Box(-1, 1, (1,)): the force on the cart, a × 10 N (clipped to [-1, 1]).
Observation: Box(4,) float32 [x, ẋ, θ, θ̇] in m, m/s, rad, rad/s; bounds ±(4.8, 100, 0.4, 100)
  (the classic: twice the termination thresholds).
Reward: 1 for every step, the terminating one included: per step r = 1, episode return in
  [1, 500].
Termination: |θ| > 0.2 rad or |x| > 2.4 m (the cart reaches the end stops).  Truncation at
  500 steps (registered ``max_episode_steps``); ``reward_threshold`` 475.
Reset: x, ẋ, θ, θ̇ ~ U(-0.05, 0.05) each (reset options ``low``/``high`` change the bounds).
Step: dt = 0.02 s, one simulator step per env step (50 Hz, as the classic).
"""
from __future__ import annotations

import numpy as np

import abd_gym as ag
from abd_gym.vector.task import float32_of
from abd_gym.vector.vector_env import ABDEnv, ABDVectorEnv


REWARD_RANGE = (1.0, 1.0)  # per step


def build_cart_scene(pole_lengths=(1.0,), pole_masses=(0.1,), cart_mass=1.0, track=2.4, force=10.0,
                     limit_strength=1e4, pole_width=0.04) -> ag.Scene:  # fmt: skip
    """Cart on a limited slider along +x with a chain of poles on hinges about +y, upright at zero.

    Joints: 0 the slider (limit ±track), 1.. the pole hinges (cart–pole 1, pole 1–pole 2, ...).
    Drive 0: effort on the slider, |force| ≤ ``force`` [N].
    """
    scene = ag.Scene(gravity=(0.0, 0.0, -9.81))
    rail = scene.add_body(ag.Box(half_extents=(track + 0.2, 0.01, 0.01)), mass=1.0, fixed=True, name="rail")
    cart = scene.add_body(ag.Box(half_extents=(0.2, 0.1, 0.05)), mass=cart_mass, name="cart")
    slide = scene.add_prismatic_joint(rail, cart, anchor=(0, 0, 0), axis=(1, 0, 0), name="slider")
    scene.add_prismatic_limit(slide, -track, track, strength=limit_strength)
    parent, top = cart, 0.0
    for k, (length, mass) in enumerate(zip(pole_lengths, pole_masses)):
        pole = scene.add_body(ag.Box(half_extents=(pole_width / 2, pole_width / 2, length / 2)), mass=mass,
                              position=(0, 0, top + length / 2), name=f"pole{k}")  # fmt: skip
        scene.add_revolute_joint(parent, pole, anchor=(0, 0, top), axis=(0, 1, 0), name=f"hinge{k}")
        parent, top = pole, top + length
    scene.add_drive(slide, mode="effort", max_effort=force)
    return scene


def draw_track(canvas, track):
    """End stops where the cart's limit engages (the cart's edge meets them at x = ±track)."""
    for s in (-1, 1):
        canvas.segment((s * (track + 0.22), 0, -0.08), (s * (track + 0.22), 0, 0.08), 0.04, (0, 0, 0))


class CartPoleVectorEnv(ABDVectorEnv):
    """Batched CartPole-v0 (see the module docstring)."""

    dt, frame_skip = 0.02, 1
    reset_option_keys = ("low", "high")
    render_center, render_width, render_size = (0.0, 0.5), 6.0, (600, 400)
    theta_threshold = 0.2  # rad
    x_threshold = 2.4  # m

    def __init__(self, num_envs=1, *, cart_mass=1.0, pole_mass=0.1, pole_length=1.0, force=10.0, **kwargs):
        self.cart_mass, self.pole_mass, self.pole_length, self.force = cart_mass, pole_mass, pole_length, force
        super().__init__(num_envs, **kwargs)

    def build_scene(self):
        return build_cart_scene((self.pole_length,), (self.pole_mass,), self.cart_mass, self.x_threshold, self.force)

    def observation_high(self):
        return np.array([2 * self.x_threshold, self.velocity_bound, 2 * self.theta_threshold, self.velocity_bound])

    def initial_state(self, n, rng, options):
        low, high = float(options.get("low", -0.05)), float(options.get("high", 0.05))
        s = rng.uniform(low, high, size=(n, 4))
        return s[:, 0::2], s[:, 1::2]

    def observe(self):
        q, v = self.coords(), self.velocities()
        return self.xp.concatenate([q, v], axis=1)[:, [0, 2, 1, 3]]  # x, ẋ, θ, θ̇

    def reward(self, obs, actions):
        return self.xp.ones_like(obs[:, 0])

    def terminated(self, obs):
        return (self.xp.abs(obs[:, 0]) > self.x_threshold) | (self.xp.abs(obs[:, 2]) > self.theta_threshold)

    def world_observation(self, q, v):
        return [q[0], v[0], q[1], v[1]]

    def world_reward(self, obs, action):
        return 1.0

    def world_terminated(self, obs):
        return abs(obs[0]) > float32_of[self.x_threshold] or abs(obs[2]) > float32_of[self.theta_threshold]

    def render_extras(self, canvas, world):
        draw_track(canvas, self.x_threshold)


class CartPoleEnv(ABDEnv):
    """Single-world CartPole-v0."""

    vector_class = CartPoleVectorEnv


def scripted_policy(obs):
    """A linear state-feedback balancer (normalised force) for observations (N, 4)."""
    obs = np.asarray(obs, dtype=np.float64)
    gains = np.array([0.1, 0.25, 2.5, 0.5])  # on x, ẋ, θ, θ̇ (times 10 N)
    return np.clip(obs @ gains, -1.0, 1.0)[:, None].astype(np.float32)
