"""FourBar-v0: drive the crank of a four-bar linkage so a coupler point tracks a moving target.

Scene (x–z plane, gravity −z; a closed loop of four revolute joints, all about −y so angles are
  counter-clockwise in the x-right / z-up view): the fixed ground with pivots A = (0, 0) and
  D = (0.4, 0) m; crank AB (0.1 m, 0.1 kg), coupler BC (0.35 m, 0.2 kg), rocker DC (0.3 m,
  0.2 kg).  Grashof crank-rocker: the crank turns fully, the rocker swings.  Joints: 0 ground–crank
  at A (effort drive, |τ| ≤ 1 N·m), 1 crank–coupler at B, 2 coupler–rocker at C, 3 rocker–ground
  at D (closes the loop).  Zero pose: crank straight up (φ = π/2), C on the upper branch.

Coupler point P: on the coupler, 0.15 m from B along BC and 0.1 m to its left (upwards).
Target: P*(t) = P(φ*(t)), the coupler point of the crank phase φ*(t) = φ0 + ω t with
  φ0 ~ U(−π, π), |ω| ~ U(1, 3) rad/s and a random sign: a point running around the coupler curve.
Coordinates: φ [rad] crank angle from +x, counter-clockwise (joint 0's coordinate + π/2).
Action: Box(-1, 1, (1,)): crank torque a × 1 N·m.
Observation: Box(9,) float32 [cos φ, sin φ, φ̇, P − P* (x, z), P* (x, z), Ṗ* (x, z)] (m, rad/s,
  m/s); bounds ±(1, 1, 100, 1, 1, 1, 1, 100, 100).
Reward: r = 1 − min(‖P − P*‖ / 0.1 m, 1) − 0.01·a²: per step in [−0.01, 1], episode return in
  [−2, 200].
Termination: none (a world whose solve fails is terminated by the base env); truncation at
  200 steps (4 s); ``reward_threshold`` 150.
Reset: crank phase φ ~ U(−π, π), crank rate U(−1, 1) rad/s (the loop's other joints follow from
  the kinematics), target phase and speed as above.
Step: dt = 0.01 s, two simulator steps per env step (0.02 s, 50 Hz).
"""
from __future__ import annotations

import math

import numpy as np

import abd_gym as ag
from abd_gym.vector.vector_env import ABDEnv, ABDVectorEnv

AXIS = (0.0, -1.0, 0.0)  # counter-clockwise in the x–z view

REWARD_RANGE = (-0.01, 1.0)  # per step


def fourbar_points(xp, phi, a, b, c, d, coupler_point):
    """B, C and the coupler point P (each (x, z) pairs) of crank angle(s) ``phi`` (upper branch)."""
    bx, bz = a * xp.cos(phi), a * xp.sin(phi)
    ex, ez = d - bx, -bz  # B → D
    L = xp.sqrt(ex**2 + ez**2)
    along = (b**2 - c**2 + L**2) / (2 * L)
    h = xp.sqrt(xp.clip(b**2 - along**2, 0.0, None))
    ux, uz = ex / L, ez / L
    cx, cz = bx + along * ux - h * uz, bz + along * uz + h * ux  # C left of B → D (upper branch)
    wx, wz = (cx - bx) / b, (cz - bz) / b
    p_along, p_left = coupler_point
    px, pz = bx + p_along * wx - p_left * wz, bz + p_along * wz + p_left * wx
    return (bx, bz), (cx, cz), (px, pz)


def _box_along(scene, p0, p1, mass, name, width=0.02, fixed=False):
    """A box link from p0 to p1 ((x, z) pairs) in the x–z plane."""
    dx, dz = p1[0] - p0[0], p1[1] - p0[1]
    length, ang = math.hypot(dx, dz), math.atan2(dz, dx)
    # rotation by ang about −y: local +x → (cos ang, 0, sin ang)
    R = np.array([[math.cos(ang), 0, -math.sin(ang)], [0, 1, 0], [math.sin(ang), 0, math.cos(ang)]])
    mid = ((p0[0] + p1[0]) / 2, 0.0, (p0[1] + p1[1]) / 2)
    return scene.add_body(ag.Box(half_extents=(length / 2, width / 2, width / 2)), mass=mass, position=mid,
                          rotation=R, name=name, fixed=fixed)  # fmt: skip


class FourBarVectorEnv(ABDVectorEnv):
    """Batched FourBar-v0 (see the module docstring)."""

    # per-world target phase φ*(t) = phase0 + speed·t [rad], drawn per episode (draw_task)
    task_state = (("target_phase0", 1), ("target_speed", 1))

    dt, frame_skip = 0.01, 2
    render_center, render_width, render_size = (0.15, 0.1), 0.9, (480, 400)
    phi_ref = math.pi / 2  # crank angle of the zero pose
    coupler_point = (0.15, 0.1)  # along BC from B, to its left [m]
    tolerance = 0.1  # m: distance at which the tracking reward reaches 0

    def __init__(self, num_envs=1, *, lengths=(0.1, 0.35, 0.3, 0.4), masses=(0.1, 0.2, 0.2), max_torque=1.0,
                 speed_range=(1.0, 3.0), **kwargs):  # fmt: skip
        self.lengths, self.masses, self.max_torque, self.speed_range = lengths, masses, max_torque, speed_range
        s, l_ = min(lengths), max(lengths)
        if s != lengths[0] or s + l_ > sum(lengths) - s - l_:
            raise ValueError(f"lengths {lengths} are not a Grashof crank-rocker with the crank shortest")
        super().__init__(num_envs, **kwargs)

    # ---- kinematics
    def points(self, xp, phi):
        a, b, c, d = self.lengths
        return fourbar_points(xp, phi, a, b, c, d, self.coupler_point)

    def joint_angles(self, phi):
        """Joint coordinates (n, 4) of the closed loop at crank angles phi (n,) (host NumPy)."""
        (bx, bz), (cx, cz), _ = self.points(np, phi)
        d = self.lengths[3]
        crank, coupler, rocker = phi, np.arctan2(cz - bz, cx - bx), np.arctan2(cz, cx - d)
        (bx0, bz0), (cx0, cz0), _ = self.points(np, np.array([self.phi_ref]))
        c0, r0 = np.arctan2(cz0 - bz0, cx0 - bx0), np.arctan2(cz0, cx0 - d)
        wrap = lambda x: (x + math.pi) % (2 * math.pi) - math.pi  # noqa: E731
        return np.stack([wrap(crank - self.phi_ref), wrap((coupler - crank) - (c0 - self.phi_ref)),
                         wrap((rocker - coupler) - (r0 - c0)), wrap(r0 - rocker)], axis=1)  # fmt: skip

    def build_scene(self):
        a, b, c, d = self.lengths
        (bx, bz), (cx, cz), _ = self.points(np, np.array(self.phi_ref))
        B, C = (float(bx), float(bz)), (float(cx), float(cz))
        scene = ag.Scene(gravity=(0.0, 0.0, -9.81))
        ground = _box_along(scene, (0.0, -0.03), (d, -0.03), 1.0, "ground", fixed=True)
        crank = _box_along(scene, (0.0, 0.0), B, self.masses[0], "crank")
        coupler = _box_along(scene, B, C, self.masses[1], "coupler")
        rocker = _box_along(scene, (d, 0.0), C, self.masses[2], "rocker")
        j0 = scene.add_revolute_joint(ground, crank, anchor=(0, 0, 0), axis=AXIS, name="A")
        scene.add_revolute_joint(crank, coupler, anchor=(B[0], 0, B[1]), axis=AXIS, name="B")
        scene.add_revolute_joint(coupler, rocker, anchor=(C[0], 0, C[1]), axis=AXIS, name="C")
        scene.add_revolute_joint(rocker, ground, anchor=(d, 0, 0), axis=AXIS, name="D")
        scene.add_drive(j0, mode="effort", max_effort=self.max_torque)
        return scene

    # ---- task
    def observation_high(self):
        return np.array([1, 1, self.velocity_bound, 1, 1, 1, 1, self.velocity_bound, self.velocity_bound])

    def initial_state(self, n, rng, options):
        phi = rng.uniform(-math.pi, math.pi, size=n)
        rate = rng.uniform(-1.0, 1.0, size=n)
        eps = 1e-5
        q = self.joint_angles(phi)
        qd = (self.joint_angles(phi + eps * rate) - self.joint_angles(phi - eps * rate)) / (2 * eps)
        return q, qd

    def draw_task(self, n, rng, options):
        lo, hi = self.speed_range
        speed = rng.uniform(lo, hi, size=n) * rng.choice([-1.0, 1.0], size=n)
        return {"target_phase0": rng.uniform(-math.pi, math.pi, size=n), "target_speed": speed}

    def target_phase(self, dt=0.0):
        return self.target_phase0 + self.target_speed * (self.episode_time() + dt)

    def target(self):
        """(N, 2) target point P* [m] and (N, 2) its velocity [m/s], Ṗ* = (P(φ* + ε) − P(φ* − ε)) / (2ε)
        · ω with ε = 1e-3 rad, in float64: in float32 the difference's rounding (an ulp of P over
        2ε) reached 3e-5 m/s, so two float32 evaluations (Torch's and torch.compile's) disagreed
        there by far more than an ulp of the result."""
        xp, eps = self.xp, 1e-3
        phase = self.target_phase()
        _, _, (px, pz) = self.points(xp, phase)
        phase = phase.astype(np.float64) if xp is np else phase.double()
        _, _, (px1, pz1) = self.points(xp, phase + eps)
        _, _, (px0, pz0) = self.points(xp, phase - eps)
        rate = self.target_speed / (2 * eps)  # dφ*/dt = ω
        vel = xp.stack([(px1 - px0) * rate, (pz1 - pz0) * rate], axis=1)
        return xp.stack([px, pz], axis=1), self.f32(vel)

    def coupler_point_position(self):
        """(N, 2) coupler point P [m] from the coupler body's pose."""
        p, A = self.body_positions()[:, 2], self.body_rotations()[:, 2]
        half = self.lengths[1] / 2
        lx, lz = self.coupler_point[0] - half, self.coupler_point[1]  # in the coupler's frame (x along BC, z left)
        world = p + lx * A[:, :, 0] + lz * A[:, :, 2]
        return self.xp.stack([world[:, 0], world[:, 2]], axis=1)

    def observe(self):
        xp = self.xp
        phi = self.coords()[:, 0] + self.phi_ref
        rate = self.velocities()[:, 0]
        target, target_vel = self.target()
        P = self.coupler_point_position()
        return xp.concatenate([xp.stack([xp.cos(phi), xp.sin(phi), rate], axis=1), P - target, target, target_vel],
                              axis=1)  # fmt: skip

    def reward(self, obs, actions):
        xp = self.xp
        dist = xp.sqrt(obs[:, 3] ** 2 + obs[:, 4] ** 2)
        return 1.0 - xp.clip(dist / self.tolerance, 0.0, 1.0) - 0.01 * actions[:, 0] ** 2

    def info(self, obs):
        return {"distance": self.xp.sqrt(obs[:, 3] ** 2 + obs[:, 4] ** 2)}

    def render_extras(self, canvas, world):
        phi = np.linspace(-math.pi, math.pi, 90)
        _, _, (px, pz) = self.points(np, phi)
        for k in range(0, 90, 3):
            canvas.circle((px[k], 0.0, pz[k]), 0.002, (170, 170, 170))
        t = np.asarray(self.target()[0][world].tolist())
        P = np.asarray(self.coupler_point_position()[world].tolist())
        canvas.circle((P[0], 0.0, P[1]), 0.008, (40, 40, 40))
        canvas.circle((t[0], 0.0, t[1]), 0.012, (220, 50, 50))


class FourBarEnv(ABDEnv):
    """Single-world FourBar-v0."""

    vector_class = FourBarVectorEnv


def scripted_policy(env: FourBarVectorEnv, kp=4.0, kd=0.4):
    """PD on the crank phase towards the target's phase (uses the env's target phase: privileged)."""
    phi = env.sim.joint_coordinates()[:, 0] + env.phi_ref
    rate = env.sim.joint_velocities()[:, 0]
    phase = np.asarray(env.target_phase().tolist())
    speed = np.asarray(env.target_speed.tolist())
    err = (phase - phi + math.pi) % (2 * math.pi) - math.pi
    tau = kp * err + kd * (speed - rate)
    return np.clip(tau / env.max_torque, -1.0, 1.0)[:, None].astype(np.float32)
