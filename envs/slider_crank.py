"""SliderCrank-v0: drive a crank so the piston of a slider-crank tracks a moving target position.

Scene (x–z plane, gravity −z; a closed loop: three revolute joints about −y, counter-clockwise in
  the x-right / z-up view, and a prismatic joint): the fixed ground; crank OB (0.1 m, 0.1 kg)
  hinged at O = (0, 0); connecting rod BC (0.3 m, 0.2 kg); piston (0.5 kg) hinged to the rod at C
  and sliding along +x on the ground, with prismatic limits (UID 669) that keep it inside
  [−0.06, 0.09] m of its zero-pose position: narrower than the crank's kinematic stroke
  [−0.083, 0.117] m, so the limits engage before either dead centre and the crank rocks in the
  upper half plane instead of turning over.  Joints: 0 ground–crank at O (effort drive,
  |τ| ≤ 0.5 N·m), 1 crank–rod at B, 2 rod–piston at C, 3 ground–piston slider (closes the loop).
  Zero pose: crank straight up (φ = π/2).

Coordinates: φ [rad] crank angle from +x, counter-clockwise (joint 0's coordinate + π/2);
  s [m] piston displacement along +x from the zero pose (joint 3's coordinate).
Target: s*(t) = s_mid + A·sin(ω t + ψ), s_mid the centre of the limited stroke, A ~ U(0.01, 0.06) m,
  ω ~ U(1, 4) rad/s, ψ ~ U(−π, π): always inside the limits.
Action: Box(-1, 1, (1,)): crank torque a × 0.5 N·m.
Observation: Box(8,) float32 [cos φ, sin φ, φ̇, s, ṡ, s*, ṡ*, s − s*] (rad/s, m, m/s); bounds
  ±(1, 1, 100, 0.25, 100, 0.25, 100, 0.5).
Reward: r = 1 − min(|s − s*| / 0.05 m, 1) − 0.01·a²: per step in [−0.01, 1], episode return in
  [−2, 200].
Termination: none (a world whose solve fails is terminated by the base env); truncation at
  200 steps (4 s); ``reward_threshold`` 150.
Reset: crank angle uniform over the range the limits allow (with a 0.05 rad margin), crank rate
  U(−0.5, 0.5) rad/s; the rod and piston follow from the kinematics.
Step: dt = 0.01 s, two simulator steps per env step (0.02 s, 50 Hz).
"""
from __future__ import annotations

import math

import numpy as np

import abd_gym as ag
from abd_gym.vector.vector_env import ABDEnv, ABDVectorEnv

AXIS = (0.0, -1.0, 0.0)  # counter-clockwise in the x–z view

REWARD_RANGE = (-0.01, 1.0)  # per step


def piston_x(xp, phi, r, L):
    """Piston pin position along x [m] for crank angle(s) phi (pin on the x axis)."""
    return r * xp.cos(phi) + xp.sqrt(L**2 - (r * xp.sin(phi)) ** 2)


class SliderCrankVectorEnv(ABDVectorEnv):
    """Batched SliderCrank-v0 (see the module docstring)."""

    # per-world target s*(t) = mid + amp·sin(omega·t + phase) [m], drawn per episode (_draw_task)
    task_state = (("target_mid", 1), ("target_amp", 1), ("target_omega", 1), ("target_phase", 1))

    dt, frame_skip = 0.01, 2
    render_center, render_width, render_size = (0.15, 0.0), 0.7, (480, 320)
    phi_ref = math.pi / 2
    tolerance = 0.05  # m

    def __init__(self, num_envs=1, *, crank=0.1, rod=0.3, masses=(0.1, 0.2, 0.5), max_torque=0.5,
                 stroke=(-0.06, 0.09), limit_strength=1e3, **kwargs):  # fmt: skip
        self.r, self.L, self.masses, self.max_torque = crank, rod, masses, max_torque
        self.stroke, self.limit_strength = stroke, limit_strength
        self.x_ref = float(piston_x(np, self.phi_ref, crank, rod))
        lo, hi = self.x_ref + stroke[0], self.x_ref + stroke[1]
        if not (rod - crank < lo < hi < rod + crank):
            raise ValueError(f"stroke {stroke} must lie inside the kinematic stroke "
                             f"[{rod - crank - self.x_ref:.4f}, {rod + crank - self.x_ref:.4f}] m")  # fmt: skip
        # crank angles where the piston meets the limits (upper half plane: x decreases with φ)
        grid = np.linspace(0.0, math.pi, 20001)
        x = piston_x(np, grid, crank, rod)
        self.phi_range = (float(grid[np.argmin(np.abs(x - hi))]), float(grid[np.argmin(np.abs(x - lo))]))
        super().__init__(num_envs, **kwargs)

    def build_scene(self):
        r = self.r
        B = (r * math.cos(self.phi_ref), r * math.sin(self.phi_ref))
        C = (self.x_ref, 0.0)
        scene = ag.Scene(gravity=(0.0, 0.0, -9.81))
        ground = scene.add_body(ag.Box(half_extents=(0.3, 0.02, 0.01)), mass=1.0, position=(0.15, 0.0, -0.04),
                                fixed=True, name="ground")  # fmt: skip
        crank = _box_along(scene, (0.0, 0.0), B, self.masses[0], "crank")
        rod = _box_along(scene, B, C, self.masses[1], "rod")
        piston = scene.add_body(ag.Box(half_extents=(0.03, 0.02, 0.02)), mass=self.masses[2], position=(C[0], 0, 0),
                                name="piston")  # fmt: skip
        j0 = scene.add_revolute_joint(ground, crank, anchor=(0, 0, 0), axis=AXIS, name="O")
        scene.add_revolute_joint(crank, rod, anchor=(B[0], 0, B[1]), axis=AXIS, name="B")
        scene.add_revolute_joint(rod, piston, anchor=(C[0], 0, 0), axis=AXIS, name="C")
        slide = scene.add_prismatic_joint(ground, piston, anchor=(C[0], 0, 0), axis=(1, 0, 0), name="slider")
        scene.add_prismatic_limit(slide, self.stroke[0], self.stroke[1], strength=self.limit_strength)
        scene.add_drive(j0, mode="effort", max_effort=self.max_torque)
        return scene

    def joint_state(self, phi):
        """Joint coordinates (n, 4) of the closed loop at crank angles phi (n,) (host NumPy)."""
        r, L = self.r, self.L
        x = piston_x(np, phi, r, L)
        rod = np.arctan2(-r * np.sin(phi), x - r * np.cos(phi))  # direction B → C
        rod0 = math.atan2(-r * math.sin(self.phi_ref), self.x_ref - r * math.cos(self.phi_ref))
        return np.stack([phi - self.phi_ref, (rod - phi) - (rod0 - self.phi_ref), rod0 - rod, x - self.x_ref], axis=1)

    def observation_high(self):
        return np.array([1, 1, self.velocity_bound, 0.25, self.velocity_bound, 0.25, self.velocity_bound, 0.5])

    def initial_state(self, n, rng, options):
        lo, hi = self.phi_range
        phi = rng.uniform(lo + 0.05, hi - 0.05, size=n)
        rate = rng.uniform(-0.5, 0.5, size=n)
        eps = 1e-5
        qd = (self.joint_state(phi + eps * rate) - self.joint_state(phi - eps * rate)) / (2 * eps)
        return self.joint_state(phi), qd

    def draw_task(self, n, rng, options):
        lo, hi = self.stroke
        return {"target_mid": np.full(n, 0.5 * (lo + hi)), "target_amp": rng.uniform(0.01, 0.06, size=n),
                "target_omega": rng.uniform(1.0, 4.0, size=n), "target_phase": rng.uniform(-math.pi, math.pi, size=n)}

    def target(self):
        """(N,) target displacement s* [m] and its rate [m/s]."""
        xp = self.xp
        arg = self.target_omega * self.episode_time() + self.target_phase
        return self.target_mid + self.target_amp * xp.sin(arg), self.target_amp * self.target_omega * xp.cos(arg)

    def observe(self):
        xp, q, v = self.xp, self.coords(), self.velocities()
        phi = q[:, 0] + self.phi_ref
        s_star, v_star = self.target()
        return xp.stack([xp.cos(phi), xp.sin(phi), v[:, 0], q[:, 3], v[:, 3], s_star, v_star, q[:, 3] - s_star], axis=1)

    def reward(self, obs, actions):
        xp = self.xp
        return 1.0 - xp.clip(xp.abs(obs[:, 7]) / self.tolerance, 0.0, 1.0) - 0.01 * actions[:, 0] ** 2

    def info(self, obs):
        return {"error": self.xp.abs(obs[:, 7])}

    def render_extras(self, canvas, world):
        lo, hi = self.stroke
        for s in (lo, hi):  # where the limits engage (piston centre)
            canvas.segment((self.x_ref + s, 0, -0.03), (self.x_ref + s, 0, -0.05), 0.004, (0, 0, 0))
        s_star = float(np.asarray(self.target()[0][world].tolist()))
        canvas.segment((self.x_ref + s_star, 0, -0.035), (self.x_ref + s_star, 0, 0.035), 0.006, (220, 50, 50))


def _box_along(scene, p0, p1, mass, name, width=0.02):
    """A box link from p0 to p1 ((x, z) pairs) in the x–z plane (local +x along the link)."""
    dx, dz = p1[0] - p0[0], p1[1] - p0[1]
    length, ang = math.hypot(dx, dz), math.atan2(dz, dx)
    R = np.array([[math.cos(ang), 0, -math.sin(ang)], [0, 1, 0], [math.sin(ang), 0, math.cos(ang)]])
    mid = ((p0[0] + p1[0]) / 2, 0.0, (p0[1] + p1[1]) / 2)
    return scene.add_body(ag.Box(half_extents=(length / 2, width / 2, width / 2)), mass=mass, position=mid,
                          rotation=R, name=name)  # fmt: skip


class SliderCrankEnv(ABDEnv):
    """Single-world SliderCrank-v0."""

    vector_class = SliderCrankVectorEnv


def scripted_policy(env: SliderCrankVectorEnv, kp=400.0, kd=20.0):
    """PD on the piston error mapped to a crank torque through the crank-to-piston gearing ds/dφ
    (uses the env's target: privileged); normalised torque."""
    phi = env.sim.joint_coordinates()[:, 0] + env.phi_ref
    s, v = env.sim.joint_coordinates()[:, 3], env.sim.joint_velocities()[:, 3]
    s_star, v_star = (np.asarray(t.tolist()) for t in env.target())
    r, L = env.r, env.L
    ds_dphi = -r * np.sin(phi) * (1 + r * np.cos(phi) / np.sqrt(L**2 - (r * np.sin(phi)) ** 2))
    force = kp * (s_star - s) + kd * (v_star - v)  # [N] wanted on the piston
    return np.clip(force * ds_dphi / env.max_torque, -1.0, 1.0)[:, None].astype(np.float32)
