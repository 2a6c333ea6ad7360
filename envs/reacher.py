"""TwoLinkReacher-v0: move the tip of a two-link planar arm to a random target (as MuJoCo's Reacher).

Scene (x–y plane, no gravity: a table-top arm seen from above; zero pose = arm straight along
  +x): a fixed base; link 1 (0.1 kg, 0.1 m) on the shoulder hinge about +z, with a revolute limit
  ±3.05 rad (±175°, UID 670: the arm can point almost straight back); link 2 (0.1 kg, 0.11 m) on
  the elbow hinge about +z, limit ±2.8 rad.  Each joint has an effort drive (|τ| ≤ 0.2 N·m) and a
  velocity drive with target 0 acting as joint damping (0.02 N·m·s/rad).

Coordinates: θ1 [rad] shoulder from +x, θ2 [rad] elbow relative to link 1, positive
  counter-clockwise seen from +z.  Tip: l1·(cos θ1, sin θ1) + l2·(cos(θ1+θ2), sin(θ1+θ2)) [m].
Action: Box(-1, 1, (2,)): shoulder and elbow torques a × 0.2 N·m.
Observation: Box(10,) float32 [cos θ1, cos θ2, sin θ1, sin θ2, target x, target y, θ̇1, θ̇2,
  tip x − target x, tip y − target y] (m, rad/s); bounds ±(1, 1, 1, 1, 0.25, 0.25, 100, 100,
  0.5, 0.5).
Reward: r = −d − 0.1·‖a‖² with d the tip–target distance [m] (≤ 0.2 + 0.21): per step in
  [−0.61, 0], episode return in [−30.5, 0].
Termination: none; truncation at 50 steps (1 s); ``reward_threshold`` −5 (the scripted
  Jacobian-transpose controller below scores about −5, zero torque −11, random −14).
Reset: θ1, θ2 ~ U(−0.1, 0.1), θ̇ ~ U(−0.005, 0.005); target uniform (by area) in the annulus
  0.03 m ≤ r ≤ 0.2 m around the shoulder (reset options ``target`` = (x, y) fixes it).
Step: dt = 0.01 s, two simulator steps per env step (0.02 s, 50 Hz).
"""
from __future__ import annotations

import math

import numpy as np

import abd_gym as ag
from abd_gym.vector.vector_env import ABDEnv, ABDVectorEnv


REWARD_RANGE = (-0.61, 0.0)  # per step


def build_reacher_scene(lengths=(0.1, 0.11), masses=(0.1, 0.1), max_torque=0.2, damping=0.02,
                        shoulder_limit=3.05, elbow_limit=2.8, limit_strength=1e3) -> ag.Scene:  # fmt: skip
    scene = ag.Scene(gravity=(0.0, 0.0, 0.0))
    base = scene.add_body(ag.Cylinder(radius=0.015, half_height=0.01), mass=1.0, fixed=True, name="base")
    l1, l2 = lengths
    link1 = scene.add_body(ag.Box(half_extents=(l1 / 2, 0.01, 0.01)), mass=masses[0], position=(l1 / 2, 0, 0),
                           name="link1")  # fmt: skip
    link2 = scene.add_body(ag.Box(half_extents=(l2 / 2, 0.01, 0.01)), mass=masses[1], position=(l1 + l2 / 2, 0, 0),
                           name="link2")  # fmt: skip
    shoulder = scene.add_revolute_joint(base, link1, anchor=(0, 0, 0), axis=(0, 0, 1), name="shoulder")
    elbow = scene.add_revolute_joint(link1, link2, anchor=(l1, 0, 0), axis=(0, 0, 1), name="elbow")
    scene.add_revolute_limit(shoulder, -shoulder_limit, shoulder_limit, strength=limit_strength)
    scene.add_revolute_limit(elbow, -elbow_limit, elbow_limit, strength=limit_strength)
    for j in (shoulder, elbow):
        scene.add_drive(j, mode="effort", max_effort=max_torque)
    for j in (shoulder, elbow):  # joint damping: velocity drives whose target stays 0
        scene.add_drive(j, mode="velocity", damping=damping, max_effort=10 * max_torque)
    return scene


class ReacherVectorEnv(ABDVectorEnv):
    """Batched TwoLinkReacher-v0 (see the module docstring)."""

    dt, frame_skip = 0.01, 2
    reset_option_keys = ("target",)
    render_plane, render_center, render_width, render_size = "xy", (0.0, 0.0), 0.5, (400, 400)
    target_radius = (0.03, 0.2)  # m
    task_state = (("target", 2),)  # (N, 2) [m], drawn per episode (draw_task)

    def __init__(self, num_envs=1, *, lengths=(0.1, 0.11), masses=(0.1, 0.1), max_torque=0.2, damping=0.02, **kwargs):
        self.lengths, self.masses, self.max_torque, self.damping = lengths, masses, max_torque, damping
        super().__init__(num_envs, **kwargs)

    def build_scene(self):
        return build_reacher_scene(self.lengths, self.masses, self.max_torque, self.damping)

    @property
    def action_dim(self):
        return 2  # the two effort drives; the damping drives get target velocity 0

    def controls(self, actions):
        return self.xp.concatenate([actions * self.max_effort[:2], 0.0 * actions], axis=1)

    def observation_high(self):
        return np.array([1, 1, 1, 1, 0.25, 0.25, self.velocity_bound, self.velocity_bound, 0.5, 0.5])

    def initial_state(self, n, rng, options):
        return rng.uniform(-0.1, 0.1, size=(n, 2)), rng.uniform(-0.005, 0.005, size=(n, 2))

    def draw_task(self, n, rng, options):
        lo, hi = self.target_radius
        r = np.sqrt(rng.uniform(lo**2, hi**2, size=n))
        phi = rng.uniform(-math.pi, math.pi, size=n)
        target = np.stack([r * np.cos(phi), r * np.sin(phi)], axis=1)
        if "target" in options:
            target[:] = np.asarray(options["target"], dtype=np.float64).reshape(2)
        return {"target": target}

    def tip(self, q):
        """(N, 2) tip position [m] from the joint angles (N, 2)."""
        xp, (l1, l2) = self.xp, self.lengths
        a12 = q[:, 0] + q[:, 1]
        return xp.stack([l1 * xp.cos(q[:, 0]) + l2 * xp.cos(a12), l1 * xp.sin(q[:, 0]) + l2 * xp.sin(a12)], axis=1)

    def observe(self):
        xp, q, v = self.xp, self.coords(), self.velocities()
        tip = self.tip(q)
        return xp.concatenate([xp.cos(q), xp.sin(q), self.target, v, tip - self.target], axis=1)

    def reward(self, obs, actions):
        xp = self.xp
        dist = xp.sqrt(obs[:, 8] ** 2 + obs[:, 9] ** 2)
        return -dist - 0.1 * (actions**2).sum(axis=1)

    def info(self, obs):
        return {"distance": self.xp.sqrt(obs[:, 8] ** 2 + obs[:, 9] ** 2)}

    def render_extras(self, canvas, world):
        t = np.asarray(self.target[world].tolist())
        canvas.circle((t[0], t[1], 0.0), 0.012, (220, 50, 50))


class ReacherEnv(ABDEnv):
    """Single-world TwoLinkReacher-v0."""

    vector_class = ReacherVectorEnv


def scripted_policy(obs, lengths=(0.1, 0.11), max_torque=0.2, kp=40.0, kd=0.02):
    """Jacobian-transpose PD on the tip, τ = Jᵀ·kp·(target − tip) − kd·θ̇ (normalised) for obs (N, 10)."""
    obs = np.asarray(obs, dtype=np.float64)
    c1, c2, s1, s2 = obs[:, 0], obs[:, 1], obs[:, 2], obs[:, 3]
    err = -obs[:, 8:10]  # target − tip [m]
    l1, l2 = lengths
    c12, s12 = c1 * c2 - s1 * s2, s1 * c2 + c1 * s2
    # J = d tip / d(θ1, θ2): rows x, y
    J = np.stack([np.stack([-l1 * s1 - l2 * s12, -l2 * s12], 1), np.stack([l1 * c1 + l2 * c12, l2 * c12], 1)], 1)
    tau = kp * np.einsum("nij,ni->nj", J, err) - kd * obs[:, 6:8]
    return np.clip(tau / max_torque, -1.0, 1.0).astype(np.float32)
