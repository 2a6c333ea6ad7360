"""Reacher-v5: Gymnasium's MuJoCo two-link reacher, built from its own ``reacher.xml``.

Scene: the file as MuJoCo compiles it (``Scene.from_mjcf``) without the body ``target`` (and its
  two slide joints), which the task keeps as its own state: link ``body0`` (0.036 kg, 0.1 m
  capsule) on the hinge ``joint0`` about +z (unlimited), link ``body1`` (0.1 m capsule with the
  ``fingertip`` sphere 0.11 m out) on ``joint1`` about +z (range ±3 rad); damping 1 N·m·s/rad
  and armature 1 kg·m² on both; gravity −9.81 m/s² along z (normal to the arm's plane).  Two
  motors (gear 200) drive the joints.
Coordinates: MuJoCo's qpos: θ0, θ1 [rad] (θ1 relative to link 0), counter-clockwise seen from +z.
Action: Box(-1, 1, (2,)) (the motors' ctrlrange): torques u = 200 · a [N·m].
Observation: Box(10,) float32 [cos θ0, cos θ1, sin θ0, sin θ1, target x, target y, θ̇0, θ̇1,
  fingertip x − target x, fingertip y − target y] (m, rad/s); bounds ±(1, 1, 1, 1, 0.25, 0.25,
  300, 300, 0.5, 0.5): beyond the target disc (r < 0.2 m), rates above gear · 1 / damping =
  200 rad/s (the rate full torque drives a joint towards) and the tip–target distance
  (< 0.21 + 0.2 m) (Gymnasium: float64, ±inf; its target entries are qpos[2:] of the target's
  joints, equal to the target's position).
Reward: r = −‖fingertip − target‖ − ‖a‖² (weights 1 and 1): per step in [−2.41, 0].
Termination: none; truncation at 50 steps (1 s); ``reward_threshold`` −3.75.
Reset: θ ~ U(−0.1, 0.1), θ̇ ~ U(−0.005, 0.005); target uniform in the disc r < 0.2 m around the
  shoulder (Gymnasium's rejection sampling of U(−0.2, 0.2)²; reset option ``target`` = (x, y)
  fixes it).
Step: dt = 0.01 s (the file's timestep), frame_skip 2 (0.02 s, 50 Hz).

Differs from Gymnasium: the physics (abd_gym's affine bodies and implicit BDF2 against MuJoCo's
RK4), the target (task state, not a body on two slide joints: it never moves, as in Gymnasium
where its joints get zero velocity and no force), the distance taken in the arm's plane (the
fingertip and the target lie at the same height in the file), float32 observations with finite
bounds, and the reset draws (abd_gym's generator: same distributions, another stream).
"""
from __future__ import annotations

import math

import numpy as np

from abd_gym.vector.vector_env import ABDEnv

from abd_gym.envs.gymnasium_mjcf import GymnasiumMjcfEnv

REWARD_RANGE = (-2.41, 0.0)  # per step


class ReacherV5VectorEnv(GymnasiumMjcfEnv):
    """Batched Reacher-v5 (see the module docstring)."""

    asset = "reacher.xml"
    exclude = ("target",)
    dt, frame_skip = 0.01, 2
    reset_option_keys = ("target",)
    render_plane, render_center, render_width, render_size = "xy", (0.0, 0.0), 0.7, (400, 400)
    velocity_bound = 300.0  # rad/s
    target_radius = 0.2  # m
    task_state = (("target", 2),)  # (N, 2) [m], drawn per episode (draw_task)

    def __init__(self, num_envs=1, *, reward_dist_weight=1.0, reward_control_weight=1.0, **kwargs):
        self.reward_dist_weight, self.reward_control_weight = reward_dist_weight, reward_control_weight
        super().__init__(num_envs, **kwargs)

    def observation_high(self):
        vb = self.velocity_bound
        return np.array([1, 1, 1, 1, 0.25, 0.25, vb, vb, 0.5, 0.5])

    def initial_state(self, n, rng, options):
        return rng.uniform(-0.1, 0.1, size=(n, 2)), rng.uniform(-0.005, 0.005, size=(n, 2))

    def draw_task(self, n, rng, options):
        r = self.target_radius * np.sqrt(rng.uniform(0.0, 1.0, size=n))
        phi = rng.uniform(-math.pi, math.pi, size=n)
        target = np.stack([r * np.cos(phi), r * np.sin(phi)], axis=1)
        if "target" in options:
            target[:] = np.asarray(options["target"], dtype=np.float64).reshape(2)
        return {"target": target}

    def fingertip(self):
        """(N, 2) the body frame ``fingertip``'s x and y [m] (Gymnasium's ``get_body_com``)."""
        return self.frame_point("fingertip")[:, :2]

    def observe(self):
        xp, q, v = self.xp, self.coords(), self.velocities()
        return xp.concatenate([xp.cos(q), xp.sin(q), self.target, v, self.fingertip() - self.target], axis=1)

    def reward(self, obs, actions):
        dist = self.xp.sqrt(obs[:, 8] ** 2 + obs[:, 9] ** 2)
        return -self.reward_dist_weight * dist - self.reward_control_weight * (actions**2).sum(axis=1)

    def info(self, obs):
        return {"distance": self.xp.sqrt(obs[:, 8] ** 2 + obs[:, 9] ** 2)}

    def render_extras(self, canvas, world):
        t = np.asarray(self.target[world].tolist())
        canvas.circle((t[0], t[1], 0.0), 0.009, (230, 51, 51))


class ReacherV5Env(ABDEnv):
    """Single-world Reacher-v5."""

    vector_class = ReacherV5VectorEnv


def scripted_policy(obs, lengths=(0.1, 0.11), gear=200.0, kp=400.0, kd=3.0):
    """Jacobian-transpose PD on the fingertip, τ = Jᵀ·kp·(target − tip) − kd·θ̇ [N·m], as controls
    τ / gear clipped to ±1, for observations (N, 10)."""
    obs = np.asarray(obs, dtype=np.float64)
    c1, c2, s1, s2 = obs[:, 0], obs[:, 1], obs[:, 2], obs[:, 3]
    err = -obs[:, 8:10]  # target − tip [m]
    l1, l2 = lengths
    c12, s12 = c1 * c2 - s1 * s2, s1 * c2 + c1 * s2
    # J = d tip / d(θ0, θ1): rows x, y
    J = np.stack([np.stack([-l1 * s1 - l2 * s12, -l2 * s12], 1), np.stack([l1 * c1 + l2 * c12, l2 * c12], 1)], 1)
    tau = kp * np.einsum("nij,ni->nj", J, err) - kd * obs[:, 6:8]
    return np.clip(tau / gear, -1.0, 1.0).astype(np.float32)
