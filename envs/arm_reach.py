"""ArmReach-v0: the 7-joint arm of Gymnasium's Pusher reaches a random 3-D target.

Scene (:func:`pusher_arm_scene`): Gymnasium's ``pusher.xml`` as MuJoCo compiles it
  (``Scene.from_mjcf``) without the bodies ``object`` and ``goal`` (and their four slides) and
  without contacts (``ignore_contacts=True``: the file lets the wrist's capsules touch the table,
  and abd_gym has no contacts): seven links (0.005–7.3 kg) on the hinges
  ``r_shoulder_pan_joint`` (+z), ``r_shoulder_lift_joint`` (+y), ``r_upper_arm_roll_joint`` (+x),
  ``r_elbow_flex_joint`` (+y), ``r_forearm_roll_joint`` (+x), ``r_wrist_flex_joint`` (+y) and
  ``r_wrist_roll_joint`` (+x) (axes at the zero pose: the arm straight along +x from the shoulder
  at (0, −0.6, 0)), each with the file's range as a limit; damping 1 N·m·s/rad on the two
  shoulder joints and 0.1 on the others, armature 0.04 kg·m² on all; no gravity (the file's).
Drives (``drive``): ``"effort"`` (default): the file's seven motors (gear 1, ctrlrange ±2),
  torque u = 2·a [N·m].  ``"position"``: the motors made MuJoCo position servos (stiffness
  ``POSITION_KP`` N·m/rad, damping ``POSITION_KV`` N·m·s/rad, torque limited to the motors' ±2 N·m)
  whose target is an angle in the joint's range: u = mid + half·a [rad] (mid, half: the range's
  middle and half-width).
Coordinates: MuJoCo's qpos: the seven joint angles [rad] in the file's order.
Action: Box(-1, 1, (7,)).
Observation: Box(20,) float32 [q (7), q̇ (7), target (3), fingertip − target (3)] (rad, rad/s, m);
  bounds ±(π, 100 rad/s, 2.5 m, 2.5 m): beyond every range, any rate the drives reach (2 N·m
  over 0.1 N·m·s/rad of damping is 20 rad/s), the targets (within 1.03 m of the shoulder at
  (0, −0.6, 0)) and the tip–target distance (at most 2.06 m).  The fingertip is the centre of
  mass of the file's body ``tips_arm`` (Gymnasium's Pusher reads ``get_body_com("tips_arm")``),
  0.1 m beyond the wrist roll axis.
Reward (Reacher-v5's): r = −‖fingertip − target‖ − w·‖a‖² with w = ``reward_control_weight``
  (default 0.1 with effort drives: Pusher-v5's weight, on actions normalised to ±1, so 0.025 per
  (N·m)² of torque; 0 with position drives, whose action is a pose, not an effort): per step in
  [−2.76, 0].
Termination: none (Reacher-v5's); truncation at 50 steps (2.5 s); ``reward_threshold`` −15.
  Over 1,024 episodes zero torque scores −45 and random actions −53; the scripted
  Jacobian-transpose controller below −22 (it ends 2 cm from the target, but slowly); PPO
  policies at −14.6 end about 12 cm from it, at −13.1 about 4 cm (three in four within 5 cm).
Reset (Reacher-v5's noise): q ~ U(−0.1, 0.1) within each joint's range (the elbow and wrist flex
  ranges end at 0), q̇ ~ U(−0.005, 0.005); the target is the fingertip of a pose drawn uniformly
  in the joint ranges, so it is reachable (reset option ``target`` = (x, y, z) fixes it).
Step: dt = 0.05 s, one simulator step per env step (20 Hz, Pusher-v5's control period, which
  Gymnasium takes as 5 steps of the file's 0.01 s for MuJoCo's explicit Euler); abd_gym's implicit
  BDF2 at 0.05 s follows MuJoCo's RK4 within 0.01 rad over 1 s under the drives
  (tests/test_arm_reach.py).
"""
from __future__ import annotations

import math
import warnings

import numpy as np

import abd_gym as ag
from abd_gym.core.affine import axis_rotations
from abd_gym.vector.render import Renderer
from abd_gym.vector.vector_env import ABDEnv

from abd_gym.envs.gymnasium_mjcf import GymnasiumMjcfEnv, asset_path

ASSET = "pusher.xml"
EXCLUDE = ("object", "goal")
FINGERTIP_BODY = "tips_arm"
DRIVES = ("effort", "position")
POSITION_KP = 50.0  # N·m/rad
POSITION_KV = 5.0  # N·m·s/rad
REACH = 1.03  # m: the fingertip's largest distance from the shoulder pan axis's origin (0, -0.6, 0)
REWARD_RANGE = (-(2 * REACH + 0.1 * 7 * 1.0), 0.0)  # per step, effort drives' default weight


def pusher_arm_model(drive: str = "effort"):
    """``mujoco.MjModel`` of Gymnasium's ``pusher.xml`` with its motors as they are (``"effort"``)
    or made position servos (``"position"``: kp ``POSITION_KP``, kv ``POSITION_KV``, force range
    the motors' ±2 N·m, control range the joint's range), and a site ``"fingertip"`` at the centre
    of mass of the body ``tips_arm`` (Gymnasium's Pusher reads ``get_body_com("tips_arm")``).  The
    bodies ``object`` and ``goal`` stay in the model (the import excludes them)."""
    import mujoco

    if drive not in DRIVES:
        raise ValueError(f"drive must be one of {DRIVES}, got {drive!r}")
    spec = mujoco.MjSpec.from_file(str(asset_path(ASSET)))
    com = spec.compile().body(FINGERTIP_BODY).ipos  # inertiafromgeom: known once compiled
    spec.body(FINGERTIP_BODY).add_site(name="fingertip", pos=com)
    if drive == "position":
        for act in spec.actuators:
            joint = spec.joint(act.target)
            bound = float(act.ctrlrange[1]) * float(act.gear[0])
            act.set_to_position(kp=POSITION_KP, kv=POSITION_KV)
            act.forcelimited, act.forcerange = 1, [-bound, bound]
            act.ctrllimited, act.ctrlrange = 1, list(joint.range)
    return spec.compile()


def pusher_arm_scene(drive: str = "effort") -> ag.Scene:
    """The 7-joint arm of Gymnasium's ``pusher.xml`` (see the module docstring and
    :func:`pusher_arm_model`): imported with ``exclude=("object", "goal")`` and
    ``ignore_contacts=True`` (the file's wrist capsules and table could touch; the task models no
    contacts, so the import's warning about it is silenced here), its joint ranges as limits."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="imported without contacts", category=RuntimeWarning)
        return ag.Scene.from_mjcf(pusher_arm_model(drive), exclude=EXCLUDE, ignore_contacts=True)


class ArmKinematics:
    """Forward kinematics of a serial chain of hinges from its zero pose (the product of
    exponentials): joint k turns everything after it by q_k about its zero-pose axis through its
    zero-pose anchor.  Host NumPy, float64: the task's targets are fingertips of random poses, and
    the scripted policy needs the fingertip's Jacobian."""

    def __init__(self, scene: ag.Scene):
        if scene.imported is None or "fingertip" not in scene.imported.sites:
            raise ValueError("ArmKinematics: the scene has no imported site 'fingertip' (pusher_arm_scene adds it)")
        body, local = scene.imported.sites["fingertip"]
        bodies, joints = scene.bodies, scene.joints
        chain = [joints[0].body_a] + [j.body_b for j in joints]
        if any(j.kind != "revolute" for j in joints) or [j.body_a for j in joints] != chain[:-1] or chain[-1] != body:
            raise ValueError("ArmKinematics: the scene's joints must be hinges of one serial chain, each on the "
                             "previous one's child, ending at the fingertip's body")  # fmt: skip
        self.anchors = np.array([j.anchor for j in joints], dtype=np.float64)
        self.axes = np.array([j.frame[0] for j in joints], dtype=np.float64)
        self.tip0 = bodies[body].position + bodies[body].rotation @ local
        self.lower = np.array([j.attributes["limit/lower"] for j in joints])
        self.upper = np.array([j.attributes["limit/upper"] for j in joints])

    def fingertip(self, q):
        """(n, 3) fingertip [m] at joint angles q (n, 7)."""
        x = np.broadcast_to(self.tip0, (len(q), 3)).copy()
        for k in reversed(range(len(self.axes))):
            x = np.einsum("nij,nj->ni", axis_rotations(self.axes[k], q[:, k]), x - self.anchors[k]) + self.anchors[k]
        return x

    def jacobian(self, q):
        """(fingertip (n, 3), d fingertip / d q (n, 3, 7)): column k is axis_k × (tip − anchor_k) with
        the axis and anchor moved by the joints before k."""
        n, nj = len(q), len(self.axes)
        rot, shift = np.broadcast_to(np.eye(3), (n, 3, 3)).copy(), np.zeros((n, 3))  # x ↦ rot·x + shift
        axes, anchors = np.zeros((n, nj, 3)), np.zeros((n, nj, 3))
        for k in range(nj):
            axes[:, k] = rot @ self.axes[k]
            anchors[:, k] = rot @ self.anchors[k] + shift
            r = axis_rotations(self.axes[k], q[:, k])
            # x ↦ rot·(r·(x − a) + a) + shift: the joints up to k
            shift = np.einsum("nij,nj->ni", rot, self.anchors[k] - r @ self.anchors[k]) + shift
            rot = rot @ r
        tip = rot @ self.tip0 + shift
        return tip, np.cross(axes, tip[:, None, :] - anchors).transpose(0, 2, 1)


class ArmReachVectorEnv(GymnasiumMjcfEnv):
    """Batched ArmReach-v0 (see the module docstring)."""

    asset, exclude = ASSET, EXCLUDE
    dt, frame_skip = 0.05, 1
    reset_option_keys = ("target",)
    render_size = (800, 400)  # two views side by side: from above (x–y) and from the side (x–z)
    render_center, render_width = (0.1, -0.6, 0.0), 2.4  # (x, y, z) [m], each view's width [m]
    target_bound = 2.5  # m: observation bound of the target and of fingertip − target
    task_state = (("target", 3),)  # (N, 3) [m], drawn per episode (draw_task)

    def __init__(self, num_envs=1, *, drive="effort", reward_dist_weight=1.0, reward_control_weight=None,
                 reset_noise_scale=0.1, **kwargs):  # fmt: skip
        if drive not in DRIVES:
            raise ValueError(f"drive must be one of {DRIVES}, got {drive!r}")
        self.drive = drive
        default_weight = 0.1 if drive == "effort" else 0.0
        self.reward_dist_weight = reward_dist_weight
        self.reward_control_weight = default_weight if reward_control_weight is None else reward_control_weight
        self.reset_noise_scale = reset_noise_scale
        super().__init__(num_envs, **kwargs)

    def build_scene(self):
        scene = pusher_arm_scene(self.drive)
        self.imported = scene.imported
        self.kinematics = ArmKinematics(scene)
        self._points = {}  # frame_point's uploads
        self._mid = self._half = None  # position drives' range middle and half-width, uploaded on first use
        return scene

    def controls(self, actions):
        if self.drive == "effort":
            return actions * self.action_scale
        if self._mid is None:  # uploaded once (the first steps run before a step graph's capture)
            k = self.kinematics
            self._mid, self._half = self.asarray(0.5 * (k.upper + k.lower)), self.asarray(0.5 * (k.upper - k.lower))
        return self._mid + self._half * actions

    def observation_high(self):
        vb, tb = self.velocity_bound, self.target_bound
        return np.array([math.pi] * 7 + [vb] * 7 + [tb] * 6)

    def initial_state(self, n, rng, options):
        k, s = self.kinematics, self.reset_noise_scale
        q = rng.uniform(np.maximum(-s, k.lower), np.minimum(s, k.upper), size=(n, 7))
        return q, rng.uniform(-0.005, 0.005, size=(n, 7))

    def draw_task(self, n, rng, options):
        k = self.kinematics
        target = k.fingertip(rng.uniform(k.lower, k.upper, size=(n, 7)))
        if "target" in options:
            target[:] = np.asarray(options["target"], dtype=np.float64).reshape(3)
        return {"target": target}

    def fingertip(self):
        """(N, 3) the fingertip [m] (the site ``fingertip``)."""
        return self.frame_point("fingertip", site=True)

    def observe(self):
        return self.xp.concatenate([self.coords(), self.velocities(), self.target, self.fingertip() - self.target],
                                   axis=1)  # fmt: skip

    def reward(self, obs, actions):
        dist = self.xp.sqrt((obs[:, 17:20] ** 2).sum(axis=1))
        return -self.reward_dist_weight * dist - self.reward_control_weight * (actions**2).sum(axis=1)

    def info(self, obs):
        return {"distance": self.xp.sqrt((obs[:, 17:20] ** 2).sum(axis=1))}

    def render(self):
        """One frame per rendered world: the arm seen from above (x right, y up) beside the arm seen
        from the side (x right, z up), the target a red dot and the fingertip a black one."""
        if self.render_mode is None:
            return super().render()
        if self._renderer is None:
            w, h = self.render_size
            cx, cy, cz = self.render_center
            views = (("xy", (cx, cy)), ("xz", (cx, cz)))
            size = (w // 2, h)
            self._renderer = [Renderer(self.scene, plane=plane, center=center, width=self.render_width, size=size)
                              for plane, center in views]  # fmt: skip
        positions, rotations = self.sim.body_positions(), self.sim.body_rotations()
        tips, targets = np.asarray(self.fingertip().tolist()), np.asarray(self.target.tolist())

        def marks(canvas, world):
            canvas.circle(targets[world], 0.03, (230, 51, 51))
            canvas.circle(tips[world], 0.015, (20, 20, 20))

        frames = [r.frames(positions, rotations, self.render_worlds, marks) for r in self._renderer]
        return tuple(np.concatenate(pair, axis=1) for pair in zip(*frames))


class ArmReachEnv(ABDEnv):
    """Single-world ArmReach-v0."""

    vector_class = ArmReachVectorEnv


def scripted_policy(env, kp=100.0, kd=1.0, step=10.0):
    """Jacobian-transpose control of the fingertip towards the target, from the env's state (NumPy
    backend).  Effort drives: τ = Jᵀ·kp·(target − tip) − kd·q̇ [N·m] as actions τ / 2 clipped to
    ±1.  Position drives: the joint targets q + step·Jᵀ(target − tip)/‖J‖² [rad] (a damped
    resolved-rate step) as actions in the ranges."""
    q, qd = np.asarray(env.coords(), dtype=np.float64), np.asarray(env.velocities(), dtype=np.float64)
    tip, J = env.kinematics.jacobian(q)
    err = np.asarray(env.target, dtype=np.float64) - tip
    grad = np.einsum("nij,ni->nj", J, err)
    if env.drive == "effort":
        return np.clip((kp * grad - kd * qd) / 2.0, -1.0, 1.0).astype(np.float32)
    k = env.kinematics
    goal = q + step * grad / np.maximum((J**2).sum(axis=(1, 2)), 1e-9)[:, None]
    return np.clip((goal - 0.5 * (k.upper + k.lower)) / (0.5 * (k.upper - k.lower)), -1.0, 1.0).astype(np.float32)
