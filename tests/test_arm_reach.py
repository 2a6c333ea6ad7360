"""ArmReach-v0 and its mechanism, the 7-joint arm of Gymnasium's pusher.xml.

The import (structure, both drive modes), its kinematics against MuJoCo's and the task's own
forward kinematics, its motion against MuJoCo C's RK4 (float64, CPU) from the same states, the
bench case, and the task's options, reset and rendering.  Gymnasium's and SB3's checkers, the
reward range and the scripted policy run for every registered task in tests/test_envs.py.
"""
import warnings

import gymnasium as gym
import numpy as np
import pytest

mujoco = pytest.importorskip("mujoco")

import abd_gym as ag  # noqa: E402
from abd_gym.envs import arm_reach  # noqa: E402
from abd_gym.envs.gymnasium_mjcf import asset_path  # noqa: E402
from mujoco_reference import rk4_qpos  # noqa: E402

JOINTS = ["r_shoulder_pan_joint", "r_shoulder_lift_joint", "r_upper_arm_roll_joint", "r_elbow_flex_joint",
          "r_forearm_roll_joint", "r_wrist_flex_joint", "r_wrist_roll_joint"]  # fmt: skip
# states inside every range (none reaches a limit in 1 s unactuated), qpos and qvel (3, 7)
QPOS = np.array([[0.1, 0.2, 0.3, -0.8, 0.2, -0.4, 0.3], [-0.5, 0.5, -0.3, -1.5, -0.6, -0.6, -0.5],
                 [0.8, 0.0, 0.8, -0.5, 0.8, -0.3, 1.0]])  # fmt: skip
QVEL = np.array([[0.5, -0.3, 0.4, 0.2, -0.5, 0.3, 1.0], [-0.2, 0.2, 0.0, -0.3, 0.5, 0.0, -0.6],
                 [0.0, 0.1, -0.5, 0.4, 0.3, -0.2, 0.2]])  # fmt: skip


@pytest.fixture(scope="module")
def scenes():
    return {drive: arm_reach.pusher_arm_scene(drive) for drive in arm_reach.DRIVES}


def mujoco_run(drive, ctrl=None, duration=1.0):
    """(3, 7) qpos of MuJoCo C RK4 (dt 1e-4 s) after ``duration`` from QPOS, QVEL (object and goal
    at rest: their slides are the model's last four coordinates)."""
    m = arm_reach.pusher_arm_model(drive)
    pad = np.zeros((len(QPOS), m.nq - 7))
    return rk4_qpos(m, np.c_[QPOS, pad], np.c_[QVEL, pad], ctrl, duration)[:, :7]


def ours_run(scene, dt, ctrl=None, duration=1.0):
    sim = ag.Simulator(scene, num_worlds=len(QPOS), dt=dt, dtype="float64", device="cpu")
    sim.set_joint_state(QPOS, QVEL)
    if ctrl is not None:
        sim.set_controls(np.broadcast_to(scene.imported.ctrl_scale * ctrl, QPOS.shape))
    sim.step(round(duration / dt))
    return sim.joint_angles_unwrapped()


# ---------------------------------------------------------------------------------- the import
def test_pusher_arm_structure(scenes):
    scene = scenes["effort"]
    m = mujoco.MjModel.from_xml_path(str(asset_path("pusher.xml")))
    assert scene.imported.joint_names == JOINTS == [j.name for j in scene.joints]
    assert [b.name for b in scene.bodies][0] == "world" and scene.num_bodies == 8  # 7 links, no object/goal
    assert "object" not in scene.imported.frames and "goal" not in scene.imported.frames
    for j, joint in zip(JOINTS, scene.joints):
        assert joint.kind == "revolute" and joint.has_limit
        lower, upper = m.joint(j).range
        assert (joint.attributes["limit/lower"], joint.attributes["limit/upper"]) == (lower, upper)
        assert joint.damping == m.dof_damping[m.joint(j).dofadr[0]] and joint.armature == pytest.approx(0.04)
    np.testing.assert_array_equal(scene.gravity, [0.0, 0.0, 0.0])
    assert [(d.mode, d.joint, d.max_effort) for d in scene.drives] == [("effort", k, 2.0) for k in range(7)]
    np.testing.assert_array_equal(scene.imported.ctrl_scale, np.ones(7))
    body, pos = scene.imported.sites["fingertip"]
    assert body == scene.body_index("r_wrist_roll_link")
    np.testing.assert_allclose(pos, [0.1, 0.0, 0.0], atol=1e-12)  # between the two tip spheres


def test_position_drives_are_torque_limited_servos(scenes):
    scene = scenes["position"]
    assert [(d.mode, d.stiffness, d.damping, d.max_effort) for d in scene.drives] == \
        [("position", arm_reach.POSITION_KP, arm_reach.POSITION_KV, 2.0)] * 7  # fmt: skip
    np.testing.assert_array_equal(scene.imported.ctrl_scale, np.ones(7))  # u = ctrl: a target angle [rad]
    lower = [j.attributes["limit/lower"] for j in scene.joints]
    np.testing.assert_array_equal(scene.imported.ctrlrange[:, 0], lower)


def test_the_import_warns_about_no_contacts_itself_but_the_scene_builder_does_not():
    with pytest.warns(RuntimeWarning, match="imported without contacts"):
        ag.Scene.from_mjcf(asset_path("pusher.xml"), exclude=arm_reach.EXCLUDE, ignore_contacts=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        arm_reach.pusher_arm_scene()
    with pytest.raises(ValueError, match="drive must be one of"):
        arm_reach.pusher_arm_scene("torque")


# ---------------------------------------------------------------------------------- kinematics
def test_body_frames_and_fingertip_match_mujoco(scenes):
    scene = scenes["effort"]
    m = arm_reach.pusher_arm_model()
    kin = arm_reach.ArmKinematics(scene)
    q = np.random.default_rng(4).uniform(kin.lower, kin.upper, size=(4, 7))
    sim = ag.Simulator(scene, num_worlds=len(q), dt=0.01, dtype="float64", device="cpu")
    sim.set_joint_state(q)
    positions, rotations = sim.body_positions(), sim.body_rotations()
    d = mujoco.MjData(m)
    body, local = scene.imported.sites["fingertip"]
    for w in range(len(q)):
        d.qpos[:7] = q[w]
        mujoco.mj_kinematics(m, d)
        for name, (k, pos, rot) in scene.imported.frames.items():
            b = m.body(name).id if name != "world" else 0
            np.testing.assert_allclose(positions[w, k] + rotations[w, k] @ pos, d.xpos[b], atol=1e-12)
            np.testing.assert_allclose(rotations[w, k] @ rot, d.xmat[b].reshape(3, 3), atol=1e-12)
        tip = d.xipos[m.body("tips_arm").id]  # Pusher's get_body_com("tips_arm")
        np.testing.assert_allclose(positions[w, body] + rotations[w, body] @ local, tip, atol=1e-12)
        np.testing.assert_allclose(kin.fingertip(q[w : w + 1])[0], tip, atol=1e-12)


def test_jacobian_is_the_fingertips_derivative(scenes):
    kin = arm_reach.ArmKinematics(scenes["effort"])
    q = np.random.default_rng(5).uniform(kin.lower, kin.upper, size=(3, 7))
    tip, J = kin.jacobian(q)
    np.testing.assert_allclose(tip, kin.fingertip(q), atol=1e-14)
    h = 1e-6
    fd = np.stack([(kin.fingertip(q + h * e) - kin.fingertip(q - h * e)) / (2 * h) for e in np.eye(7)], axis=2)
    np.testing.assert_allclose(J, fd, atol=1e-9)


# ---------------------------------------------------------------------------------- motion
def test_free_motion_matches_mujoco(scenes):
    """0.5 s unactuated from QPOS, QVEL (damping and armature act, no limit is reached): BDF2 at
    0.01 s, the file's timestep, within 1e-4 rad of MuJoCo's RK4 (measured 2.6e-5)."""
    ours = ours_run(scenes["effort"], 0.01, duration=0.5)
    assert np.abs(ours - mujoco_run("effort", duration=0.5)).max() < 1e-4


@pytest.mark.parametrize("drive, ctrl", [("effort", [1.0, -1.0, 0.5, 0.5, -0.5, 0.3, 0.2]),
                                         ("position", [0.3, 0.4, 0.2, -1.0, 0.3, -0.5, 0.4])])  # fmt: skip
def test_driven_motion_at_the_tasks_step_matches_mujoco(scenes, drive, ctrl):
    """1 s under a constant ctrl at the task's dt (0.05 s): within 0.01 rad of MuJoCo's RK4, the
    bound tests/test_mjcf.py holds imports to (measured 6.5e-3 with the motors, which drive five
    joints into their limits, where MuJoCo's soft limits and abd_gym's cubic ones differ; 6e-3
    with the servos)."""
    ctrl = np.array(ctrl)
    dt = arm_reach.ArmReachVectorEnv.dt
    assert np.abs(ours_run(scenes[drive], dt, ctrl) - mujoco_run(drive, ctrl)).max() < 0.01


def test_bench_case_is_the_tasks_arm(scenes):
    from abd_gym.bench.cases import CASES

    case = CASES["pusher_arm"]
    assert case.tasks == ("ArmReach-v0",) and case.qpos_of_joint == tuple(range(7)) and case.nq == 7
    m = mujoco.MjModel.from_xml_string(case.xml(0.01))
    assert m.nbody == 11 and m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT
    assert [m.joint(k).name for k in range(m.njnt)] == JOINTS
    q, qd = case.states(8, 0)
    kin = arm_reach.ArmKinematics(scenes["effort"])
    assert np.all((q > kin.lower) & (q < kin.upper)) and np.abs(qd).max() <= 0.5


# ---------------------------------------------------------------------------------- the task
@pytest.fixture(scope="module")
def env():
    e = arm_reach.ArmReachVectorEnv(4, render_mode="rgb_array")
    yield e
    e.close()


def test_reset_noise_stays_in_the_ranges_and_targets_are_reachable(env):
    obs, _ = env.reset(seed=1)
    kin = env.kinematics
    q = obs[:, :7]
    assert np.all(q >= np.maximum(kin.lower, -0.1) - 1e-6) and np.all(q <= np.minimum(kin.upper, 0.1) + 1e-6)
    assert np.abs(obs[:, 7:14]).max() <= 0.005 + 1e-6
    draws = env.draw_task(2000, np.random.default_rng(0), {})["target"]
    shoulder = env.scene.joints[0].anchor
    assert np.linalg.norm(draws - shoulder, axis=1).max() < arm_reach.REACH
    np.testing.assert_allclose(obs[:, 17:20], np.asarray(env.fingertip()) - obs[:, 14:17], atol=1e-6)


def test_target_option_and_reward(env):
    target = (0.5, -0.4, 0.1)
    obs, _ = env.reset(seed=2, options={"target": target})
    np.testing.assert_allclose(obs[:, 14:17], np.broadcast_to(target, (4, 3)), atol=1e-6)
    a = np.full((4, 7), 0.5, dtype=np.float32)
    obs, reward, terminated, truncated, info = env.step(a)
    dist = np.linalg.norm(np.asarray(env.fingertip()) - np.asarray(target), axis=1)
    np.testing.assert_allclose(info["distance"], dist, rtol=1e-5)
    np.testing.assert_allclose(reward, -dist - 0.1 * 7 * 0.25, rtol=1e-5)
    assert not terminated.any() and not truncated.any()


def test_position_drive_actions_are_joint_targets():
    env = arm_reach.ArmReachVectorEnv(2, drive="position")
    env.reset(seed=0)
    kin = env.kinematics
    np.testing.assert_allclose(env.controls(-np.ones((1, 7))), kin.lower[None], atol=1e-6)
    np.testing.assert_allclose(env.controls(np.ones((1, 7))), kin.upper[None], atol=1e-6)
    goal = np.array([0.3, 0.4, 0.2, -1.0, 0.3, -0.5, 0.4])
    a = ((goal - 0.5 * (kin.upper + kin.lower)) / (0.5 * (kin.upper - kin.lower))).astype(np.float32)
    for _ in range(60):  # 3 s: the servos settle
        obs, reward, *_ = env.step(np.broadcast_to(a, (2, 7)))
    np.testing.assert_allclose(obs[:, :7], np.broadcast_to(goal, (2, 7)), atol=2e-3)
    assert env.reward_control_weight == 0.0
    np.testing.assert_allclose(reward, -np.linalg.norm(obs[:, 17:20], axis=1), rtol=1e-5)
    with pytest.raises(ValueError, match="drive must be one of"):
        arm_reach.ArmReachVectorEnv(1, drive="torque")


def test_position_drive_env_passes_gymnasiums_checker():
    """The default (effort) env passes both checkers in tests/test_envs.py; the position drives
    change the scene and the controls, not the spaces."""
    from gymnasium.utils.env_checker import check_env

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(gym.make("abd_gym/ArmReach-v0", drive="position").unwrapped)


def test_render_shows_the_arm_and_the_target_from_above_and_the_side(env):
    env.reset(seed=3)
    frames = env.render()
    assert len(frames) == 4 and frames[0].shape == (400, 800, 3)
    for w, frame in enumerate(frames):
        for view in (frame[:, :400], frame[:, 400:]):
            red = (view[..., 0] == 230) & (view[..., 1] == 51) & (view[..., 2] == 51)
            arm = (view != 255).any(axis=2) & ~red
            assert red.sum() > 20 and arm.mean() > 0.01  # the target's dot and the links
    # the top view's target dot at the target's (x, y), the side view's at its (x, z)
    t = np.asarray(env.target[0])
    rows, cols = np.nonzero((frames[0][..., 0] == 230) & (frames[0][..., 1] == 51))
    top = cols < 400
    scale, (cx, cy, cz) = 400 / env.render_width, env.render_center
    u = 200 + (t[0] - cx) * scale  # the target's column in either view
    assert abs(cols[top].mean() - u) < 3 and abs(rows[top].mean() - (200 - (t[1] - cy) * scale)) < 3
    assert abs(cols[~top].mean() - 400 - u) < 3 and abs(rows[~top].mean() - (200 - (t[2] - cz) * scale)) < 3


def test_kinematics_refuses_a_scene_that_is_not_one_chain():
    from abd_gym.sim import mechanisms

    scene = arm_reach.pusher_arm_scene()
    scene.joints[3], scene.joints[4] = scene.joints[4], scene.joints[3]
    with pytest.raises(ValueError, match="one serial chain"):
        arm_reach.ArmKinematics(scene)
    with pytest.raises(ValueError, match="no imported site 'fingertip'"):
        arm_reach.ArmKinematics(mechanisms.chain(3, length=0.1))
