"""Scene.from_mjcf / from_urdf against MuJoCo itself, on Gymnasium's bundled MJCF files and a URDF arm.

Motion is compared over 1 s (float64, BDF2) with MuJoCo's RK4 at a 1e-4 s step as the reference.
The ``*_passive_*`` comparisons run the files as they are, joint damping and armature included;
the others zero both in the compiled model, so they test the mapping without the passive terms.
"""
import math
import os
import warnings

import numpy as np
import pytest

mujoco = pytest.importorskip("mujoco")
gym_mujoco = pytest.importorskip("gymnasium.envs.mujoco")

import abd_gym as ag  # noqa: E402
from abd_gym.mjcf import compare_with_mujoco, importer as mjcf  # noqa: E402
from mujoco_reference import rk4_qpos  # noqa: E402

ASSETS = os.path.join(os.path.dirname(gym_mujoco.__file__), "assets")
FILES = ("inverted_pendulum.xml", "inverted_double_pendulum.xml", "reacher.xml")
# max |qpos − qpos_ref| over 1 s [rad or m]: MuJoCo-imported models should stay within a few hundredths of a radian
BOUND = 0.01

# initial (qpos, qvel) per file, 3 worlds each, chosen so that no limit is reached within 1 s
# (MuJoCo's soft limits and abd_gym's cubic ones stop a joint differently)
STATES = {
    "inverted_pendulum.xml": ([[0.0, 0.01], [0.2, -0.02], [-0.3, 0.0]], [[0.0, 0.0], [0.1, 0.05], [0.3, -0.05]]),
    "inverted_double_pendulum.xml": ([[0.0, 0.05, 0.0], [0.1, 3.0, 0.2], [0.0, math.pi, 0.0]],
                                     [[0.0, 0.0, 0.0], [0.0, 0.5, -0.5], [0.2, 1.0, 0.0]]),  # fmt: skip
    "reacher.xml": ([[0.0, 0.0, 0.1, -0.1], [1.0, -1.0, 0.0, 0.0], [-2.0, 2.0, 0.05, 0.05]],
                    [[1.0, -1.0, 0.05, 0.05], [0.0, 2.0, 0.0, 0.0], [-2.0, 1.0, -0.1, 0.1]]),  # fmt: skip
}

ARM_URDF = """<robot name="arm">
  <link name="base"><inertial><mass value="1"/><inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="carriage"><inertial><mass value="1"/><inertia ixx="0.002" iyy="0.003" izz="0.004" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="upper"><inertial><origin xyz="0 0 -0.15"/><mass value="0.5"/>
    <inertia ixx="0.004" iyy="0.004" izz="0.0005" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="fore"><inertial><origin xyz="0.02 0 -0.12" rpy="0 0.3 0"/><mass value="0.3"/>
    <inertia ixx="0.002" iyy="0.0018" izz="0.0003" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <joint name="rail" type="prismatic"><parent link="base"/><child link="carriage"/><origin xyz="0 0 1"/>
    <axis xyz="1 0 0"/><limit lower="-1" upper="1" effort="10" velocity="1"/></joint>
  <joint name="shoulder" type="continuous"><parent link="carriage"/><child link="upper"/><axis xyz="0 1 0"/></joint>
  <joint name="elbow" type="revolute"><parent link="upper"/><child link="fore"/><origin xyz="0 0 -0.3" rpy="0.2 0 0"/>
    <axis xyz="1 0 1"/><limit lower="-2.5" upper="2.5" effort="10" velocity="10"/></joint>
</robot>
"""
ARM_STATES = ([[0.0, 0.3, 0.5], [0.1, -1.0, -0.5], [-0.2, 2.0, -0.5]], [[0.0, 0.0, 0.0], [0.2, 1.0, -1.0], [-0.1, 0.5, 0.0]])


def asset(name):
    return os.path.join(ASSETS, name)


def model(name, passive=True):
    m = mujoco.MjModel.from_xml_path(name if os.path.isabs(name) else asset(name))
    if not passive:
        m.dof_damping[:] = 0.0
        m.dof_armature[:] = 0.0
    return m


def mujoco_qpos(m, qpos, qvel, ctrl=None, duration=1.0):
    """(worlds, nq) qpos after ``duration`` [s] of MuJoCo RK4 at REFERENCE_DT from each state."""
    return rk4_qpos(m, qpos, qvel, ctrl, duration)


def abd_qpos(scene, qpos, qvel, dt, controls=None, duration=1.0):
    sim = ag.Simulator(scene, num_worlds=len(qpos), dt=dt, dtype="float64")
    sim.set_joint_state(np.asarray(qpos, dtype=np.float64), np.asarray(qvel, dtype=np.float64))
    if controls is not None:
        sim.set_controls(np.broadcast_to(controls, (len(qpos), len(controls))))
    sim.step(round(duration / dt))
    return sim.joint_angles_unwrapped()


def motion_error(m, qpos, qvel, dt, ctrl=None):
    """The largest qpos difference after 1 s (abd_gym.mjcf.compare_with_mujoco)."""
    return compare_with_mujoco(m, (qpos, qvel), 1.0, dt, ctrl=ctrl).final_error


@pytest.fixture(scope="module")
def urdf_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("urdf") / "arm.urdf"
    path.write_text(ARM_URDF)
    return str(path)


# ---------------------------------------------------------------------------------- structure
def test_inverted_pendulum_structure():
    scene = ag.Scene.from_mjcf(asset("inverted_pendulum.xml"))
    info = scene.imported
    assert [b.name for b in scene.bodies] == ["world", "cart", "pole"]
    assert scene.bodies[0].fixed and not any(b.fixed for b in scene.bodies[1:])
    assert [(j.name, j.kind) for j in scene.joints] == [("slider", "prismatic"), ("hinge", "revolute")]
    np.testing.assert_allclose(scene.joints[0].frame[0], [1, 0, 0])
    np.testing.assert_allclose(scene.joints[1].frame[0], [0, 1, 0])
    hinge = scene.joints[1].attributes
    assert hinge["limit/lower"] == pytest.approx(-math.pi / 2) and hinge["limit/upper"] == pytest.approx(math.pi / 2)
    assert hinge["passive/damping"] == 1.0 and hinge["passive/armature"] == 0.0
    (drive,) = scene.drives
    assert (drive.name, drive.mode, drive.joint, drive.max_effort) == ("slide", "effort", 0, 300.0)
    np.testing.assert_array_equal(info.gear, [100.0])
    np.testing.assert_array_equal(info.ctrl_scale, [100.0])
    np.testing.assert_array_equal(info.ctrlrange, [[-3.0, 3.0]])
    np.testing.assert_array_equal(scene.gravity, [0, 0, -9.81])
    assert info.timestep == 0.02 and info.model_name == "inverted pendulum"
    m = model("inverted_pendulum.xml")
    for k, b in enumerate(("cart", "pole")):
        assert scene.bodies[k + 1].mass == pytest.approx(m.body_mass[m.body(b).id], rel=1e-12)
    assert "geom 'cpole'" in info.skipped


def test_double_pendulum_structure_and_margin():
    scene = ag.Scene.from_mjcf(asset("inverted_double_pendulum.xml"))
    info = scene.imported
    assert info.joint_names == ["slider", "hinge", "hinge2"] == [j.name for j in scene.joints]
    slider = scene.joints[0].attributes  # range ±1 with margin 0.01: MuJoCo pushes back from ±0.99
    assert (slider["limit/lower"], slider["limit/upper"]) == pytest.approx((-0.99, 0.99))
    assert not scene.joints[1].has_limit
    np.testing.assert_allclose(scene.joints[2].anchor, [0, 0, 0.6])
    assert info.sites["tip"][0] == scene.body_index("pole2")
    np.testing.assert_allclose(info.sites["tip"][1], [0, 0, 0.6])
    np.testing.assert_allclose(scene.gravity, [1e-5, 0, -9.81])
    assert info.timestep == 0.01


def test_rotated_mass_data_reaches_the_model_without_rounding_noise():
    """The capsules' fromto leaves ~1e-17 kg·m² where a second moment is exactly 0; the model stores
    0 there (float32 products of such entries are denormal, slow on a CPU) and every other entry
    as it was."""
    from abd_gym.sim.model import Model, without_rounding_noise

    scene = ag.Scene.from_mjcf(asset("inverted_double_pendulum.xml"))
    S = np.array([b.moments.second_moment for b in scene.bodies])
    noise = (S != 0) & (np.abs(S) < 1e-15)
    assert noise.any()  # the import's rounding, which this test is about
    m = Model(scene, 1, device="cpu")
    assert (m.base_S[noise] == 0).all()
    np.testing.assert_array_equal(m.base_S[~noise], S[~noise])
    # relative to the largest entry: a small but real moment stays
    x = np.array([[1.0, 1e-9, 0.0], [1e-9, 1.0, 2e-17], [0.0, 2e-17, 1e-3]])
    np.testing.assert_array_equal(without_rounding_noise(x), np.where(np.abs(x) < 1e-16, 0.0, x))
    # along an axis, each vector on its own: a short vector's own entries are its scale
    v = np.array([[1.0, 3e-17, 0.5], [1e-6, 2e-6, 4e-23]])
    np.testing.assert_array_equal(without_rounding_noise(v, axis=-1), [[1.0, 0.0, 0.5], [1e-6, 2e-6, 0.0]])


def test_joint_frames_in_rotated_bodies_reach_the_model_without_rounding_noise():
    """The four-bar's links are rotated by trigonometry: its joints' local frames and points carry
    ~1e-17 where they are 0 until the model stores them."""
    from abd_gym.sim.model import Model
    from abd_gym.bench.cases import CASES

    scene = CASES["fourbar"].scene()
    assert any(((b.rotation != 0) & (np.abs(b.rotation) < 1e-15)).any() for b in scene.bodies)
    m = Model(scene, 1, device="cpu")
    for x in (m.base_frames, m.base_points):
        assert not ((x != 0) & (np.abs(x) < 1e-12)).any()
    # the frames stay unit vectors
    np.testing.assert_allclose(np.linalg.norm(m.base_frames[2:], axis=-1)[:, : m.num_joints], 1.0, atol=1e-15)


def test_reacher_structure_with_and_without_target():
    full = ag.Scene.from_mjcf(asset("reacher.xml"))
    info = full.imported
    assert info.joint_names == ["joint0", "joint1", "target_x", "target_y"]
    np.testing.assert_allclose(info.qpos0, [0, 0, 0.1, -0.1])  # the slides' ref
    # the target's two slides chain through one carrier at the target's frame
    assert [b.name for b in full.bodies] == ["world", "body0", "body1", "target/target_x", "target"]
    target = full.body_index("target")
    assert full.bodies[target - 1].mass == pytest.approx(mjcf.CARRIER_FRACTION * full.bodies[target].mass)
    assert [(full.bodies[j.body_a].name, full.bodies[j.body_b].name) for j in full.joints[2:]] == [
        ("world", "target/target_x"), ("target/target_x", "target")]  # fmt: skip
    np.testing.assert_allclose(full.bodies[target].position, [0, 0, 0.01])  # at qpos = 0, not at ref
    assert not full.joints[0].has_limit and full.joints[1].attributes["limit/upper"] == 3.0

    arm = ag.Scene.from_mjcf(asset("reacher.xml"), exclude=("target",))
    assert [b.name for b in arm.bodies] == ["world", "body0", "body1"]
    assert arm.imported.joint_names == ["joint0", "joint1"]
    # the fingertip body has no joint: merged into body1, its frame 0.11 m along body1's x
    k, pos, rot = arm.imported.frames["fingertip"]
    assert k == arm.body_index("body1")
    np.testing.assert_allclose(pos, [0.11, 0, 0])
    np.testing.assert_allclose(rot, np.eye(3))
    m = model("reacher.xml")
    assert arm.bodies[k].mass == pytest.approx(m.body_mass[m.body("body1").id] + m.body_mass[m.body("fingertip").id])
    assert [d.name for d in arm.drives] == ["actuator0", "actuator1"]
    np.testing.assert_array_equal(arm.imported.gear, [200.0, 200.0])
    assert all(d.max_effort == 200.0 for d in arm.drives)
    assert "target" not in arm.imported.frames


def test_imports_warn_nothing_for_drawing_only():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for name in FILES:
            ag.Scene.from_mjcf(asset(name))


def test_scene_default_has_no_import():
    assert ag.Scene().imported is None


# ---------------------------------------------------------------------------------- refusals
def _xml(body="", extra="", option=""):
    return f"""<mujoco model="probe"><option {option}/><worldbody>
      <body name="link" pos="0 0 1"><joint name="hinge" type="hinge" axis="0 1 0"/>
        <geom name="rod" type="capsule" fromto="0 0 0 0 0 -0.5" size="0.02" contype="0" conaffinity="0"/>
        {body}</body></worldbody>{extra}</mujoco>"""


@pytest.mark.parametrize("xml, words", [
    (_xml('<body name="ball_body"><joint name="knob" type="ball"/><geom size="0.1" contype="0"/></body>'),
     ["ball", "'knob'", "'ball_body'"]),
    (_xml() .replace("<worldbody>", '<worldbody><body name="floater"><freejoint name="float"/><geom size="0.1" contype="0"/></body>'),
     ["free", "'float'", "'floater'"]),
    (_xml('<site name="s1"/>', '<tendon><spatial name="cable"><site site="s1"/><site site="s2"/></spatial></tendon>')
     .replace("<worldbody>", '<worldbody><site name="s2" pos="0 0 2"/>'), ["tendon"]),
    (_xml(extra='<actuator><motor name="lopsided" joint="hinge" ctrlrange="-1 2"/></actuator>'), ["'lopsided'", "asymmetric"]),
    (_xml('<body name="second" pos="0 0 -0.5"><joint name="knee" type="hinge" axis="0 1 0"/>'
          '<geom name="shin" size="0.05" contype="1" conaffinity="1"/></body>')
     .replace("<worldbody>", '<worldbody><geom name="floor" type="plane" size="1 1 1"/>'), ["'floor'", "'shin'", "ignore_contacts=True"]),
    (_xml(option='density="1.2"'), ["fluid"]),
    (_xml().replace('type="hinge" axis', 'type="hinge" stiffness="3" axis'), ["stiffness", "'hinge'"]),
    (_xml().replace('type="hinge" axis', 'type="hinge" range="-200 200" axis'), ["'hinge'", "[-pi, pi]"]),
    (_xml(extra='<actuator><cylinder name="piston" joint="hinge"/></actuator>'), ["'piston'"]),
], ids=["ball", "free", "tendon", "ctrlrange", "contact", "fluid", "stiffness", "range", "actuator"])  # fmt: skip
def test_refusals_name_the_element(xml, words):
    with pytest.raises(ValueError) as err:
        ag.Scene.from_mjcf(xml)
    for word in words:
        assert word in str(err.value)


def test_ignore_contacts_warns_once():
    xml = _xml('<body name="second" pos="0 0 -0.5"><joint name="knee" type="hinge" axis="0 1 0"/>'
               '<geom name="shin" size="0.05"/></body>').replace("<worldbody>", '<worldbody><geom name="floor" type="plane" size="1 1 1"/>')  # fmt: skip
    with pytest.warns(RuntimeWarning, match="without contacts") as record:
        scene = ag.Scene.from_mjcf(xml, ignore_contacts=True)
    assert len(record) == 1 and scene.num_joints == 2


def test_parent_and_child_geoms_do_not_count_as_contacts():
    # adjacent bodies are filtered by MuJoCo (filterparent), so colliding geoms there import silently
    xml = _xml('<body name="second" pos="0 0 -0.5"><joint name="knee" type="hinge" axis="0 1 0"/>'
               '<geom name="shin" size="0.05"/></body>').replace('contype="0" conaffinity="0"', "")  # fmt: skip
    assert ag.Scene.from_mjcf(xml).num_joints == 2


def test_unknown_exclude_is_refused():
    with pytest.raises(ValueError, match="'nothing'"):
        ag.Scene.from_mjcf(asset("reacher.xml"), exclude=("nothing",))


def test_missing_mujoco_says_how_to_install(monkeypatch):
    import builtins

    real_import = builtins.__import__

    def no_mujoco(name, *args, **kwargs):
        if name == "mujoco":
            raise ImportError("No module named 'mujoco'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_mujoco)
    with pytest.raises(ImportError, match=r'pip install "abd-gym\[mjcf\]"'):
        ag.Scene.from_mjcf(asset("reacher.xml"))


# ---------------------------------------------------------------------------------- kinematics
@pytest.mark.parametrize("name", FILES + ("arm.urdf",))
def test_body_frames_match_mujoco_kinematics(name, urdf_path):
    m = model(urdf_path if name == "arm.urdf" else name)
    scene = ag.Scene.from_mjcf(m)
    rng = np.random.default_rng(3)
    lo = np.where(m.jnt_limited, m.jnt_range[:, 0], -math.pi)
    hi = np.where(m.jnt_limited, m.jnt_range[:, 1], math.pi)
    qpos = rng.uniform(0.9 * lo, 0.9 * hi, size=(4, m.njnt))
    sim = ag.Simulator(scene, num_worlds=len(qpos), dt=0.002, dtype="float64")
    sim.set_joint_state(qpos)
    positions, rotations = sim.body_positions(), sim.body_rotations()
    d = mujoco.MjData(m)
    for w, q in enumerate(qpos):
        d.qpos[:] = q
        mujoco.mj_kinematics(m, d)
        for body, (k, pos, rot) in scene.imported.frames.items():
            b = m.body(body).id if body != "world" else 0
            np.testing.assert_allclose(positions[w, k] + rotations[w, k] @ pos, d.xpos[b], atol=1e-12)
            np.testing.assert_allclose(rotations[w, k] @ rot, d.xmat[b].reshape(3, 3), atol=1e-12)
    np.testing.assert_allclose(sim.joint_coordinates(), qpos, atol=1e-12)


# ---------------------------------------------------------------------------------- motion
@pytest.mark.parametrize("dt", [0.002, 0.001])
@pytest.mark.parametrize("name", FILES)
def test_motion_matches_mujoco_without_passive_terms(name, dt):
    qpos, qvel = STATES[name]
    assert motion_error(model(name, passive=False), qpos, qvel, dt) < BOUND


@pytest.mark.parametrize("dt", [0.002, 0.001])
@pytest.mark.parametrize("name", FILES)
def test_passive_motion_matches_mujoco(name, dt):
    """The files as they are: joint damping (all three) and armature (reacher) act."""
    qpos, qvel = STATES[name]
    assert motion_error(model(name), qpos, qvel, dt) < BOUND


def test_compare_with_mujoco_steps_both_engines_in_lockstep():
    """The public helper: per step and world the qpos difference, its last row the difference of
    the two engines run on their own (abd_gym's 500 steps in one call, MuJoCo's RK4 states), the
    same from a path, a compiled model or the imported scene; bad arguments are refused."""
    name = "inverted_double_pendulum.xml"
    qpos, qvel = STATES[name]
    m = model(name)
    result = compare_with_mujoco(asset(name), (qpos, qvel), 1.0, 0.002, ctrl=[0.02])
    assert result.errors.shape == (500, 3) and result.joint_names == ["slider", "hinge", "hinge2"]
    np.testing.assert_allclose(result.times[[0, -1]], [0.002, 1.0])
    scene = ag.Scene.from_mjcf(m)
    alone = np.abs(abd_qpos(scene, qpos, qvel, 0.002, scene.imported.ctrl_scale * 0.02)
                   - mujoco_qpos(model(name), qpos, qvel, [0.02]))  # fmt: skip
    np.testing.assert_array_equal(result.errors[-1], alone.max(axis=1))
    assert result.final_error == alone.max() and result.max_error >= result.final_error > 0
    np.testing.assert_array_equal(compare_with_mujoco(scene, (qpos, qvel), 1.0, 0.002, ctrl=[0.02]).errors,
                                  result.errors)  # fmt: skip
    one = compare_with_mujoco(m, (qpos[1], qvel[1]), 0.1, 0.002)  # one state, unactuated, a compiled model
    assert one.errors.shape == (50, 1) and one.qpos.shape == (1, 3)
    with pytest.raises(ValueError, match="states must be qpos"):
        compare_with_mujoco(m, ([0.0, 0.0], [0.0, 0.0]), 0.1, 0.002)
    with pytest.raises(ValueError, match="must divide dt"):
        compare_with_mujoco(m, (qpos, qvel), 0.1, 0.002, reference_dt=3e-4)
    with pytest.raises(ValueError, match="made by Scene.from_mjcf"):
        compare_with_mujoco(ag.Scene(), (qpos, qvel), 0.1, 0.002)


def test_driven_motion_matches_mujoco():
    """A constant ctrl on the cart's motor (u = gear·ctrl = 10 N) of the double pendulum."""
    qpos, qvel = STATES["inverted_double_pendulum.xml"]
    assert motion_error(model("inverted_double_pendulum.xml", passive=False), qpos, qvel, 0.002, ctrl=[0.02]) < BOUND


def test_passive_driven_motion_matches_mujoco():
    qpos, qvel = STATES["inverted_double_pendulum.xml"]
    assert motion_error(model("inverted_double_pendulum.xml"), qpos, qvel, 0.002, ctrl=[0.02]) < BOUND


def test_urdf_arm_structure_and_motion(urdf_path):
    scene = ag.Scene.from_urdf(urdf_path)
    assert [(j.name, j.kind, j.has_limit) for j in scene.joints] == [
        ("rail", "prismatic", True), ("shoulder", "revolute", False), ("elbow", "revolute", True)]  # fmt: skip
    assert [b.name for b in scene.bodies] == ["world", "carriage", "upper", "fore"]
    m = model(urdf_path)
    for dt in (0.002, 0.001):
        assert motion_error(m, *ARM_STATES, dt) < BOUND


# ---------------------------------------------------------------------------------- loops
FOURBAR = """<mujoco model="fourbar"><worldbody>
  <body name="crank"><joint name="crank" type="hinge" axis="0 1 0"/>
    <geom type="capsule" fromto="0 0 0 0 0 0.1" size="0.01" contype="0" conaffinity="0"/>
    <body name="coupler" pos="0 0 0.1"><joint name="coupler" type="hinge" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0.4 0 0.05" size="0.01" contype="0" conaffinity="0"/></body></body>
  <body name="rocker" pos="0.4 0 0"><joint name="rocker" type="hinge" axis="ROCKER_AXIS"/>
    <geom type="capsule" fromto="0 0 0 0 0 0.15" size="0.01" contype="0" conaffinity="0"/></body>
  </worldbody><equality><connect name="loop" body1="coupler" body2="rocker" anchor="0.4 0 0.05" solref="0.001 1"/>
  </equality></mujoco>"""


def test_planar_connect_closes_the_loop_with_a_hinge():
    """A Grashof four-bar whose crank turns a full revolution in 1 s under gravity (MuJoCo's connect
    stiffened to solref 0.001)."""
    m = mujoco.MjModel.from_xml_string(FOURBAR.replace("ROCKER_AXIS", "0 1 0"))
    scene = ag.Scene.from_mjcf(m)
    loop = scene.joints[3]
    assert (loop.name, loop.kind) == ("loop", "revolute")
    np.testing.assert_allclose(loop.anchor, [0.4, 0, 0.15])
    np.testing.assert_allclose(loop.frame[0], [0, 1, 0])
    qvel = [[0.5, -0.5, 1 / 3]]  # consistent with the loop: the coupler translates at first
    sim = ag.Simulator(scene, num_worlds=1, dt=0.001, dtype="float64")
    sim.set_joint_state(np.zeros((1, 4)), np.c_[qvel, [[0.0]]])
    sim.step(1000)
    reference = mujoco_qpos(m, [[0.0, 0.0, 0.0]], qvel)
    assert abs(reference[0, 0]) > 2 * math.pi - 0.1
    assert np.abs(sim.joint_angles_unwrapped()[:, :3] - reference).max() < BOUND


def test_non_planar_connect_is_refused():
    with pytest.raises(ValueError, match="connect 'loop'.*not parallel"):
        ag.Scene.from_mjcf(FOURBAR.replace("ROCKER_AXIS", "0 1 0.2"))


def test_weld_becomes_a_fixed_joint():
    xml = _xml().replace("</worldbody>", '<body name="free_link" pos="0.3 0 1"><joint name="swing" type="hinge" axis="0 1 0"/>'
                         '<geom size="0.05" contype="0" conaffinity="0"/></body></worldbody>'
                         '<equality><weld name="glue" body1="link" body2="free_link"/></equality>')  # fmt: skip
    scene = ag.Scene.from_mjcf(xml)
    assert [(j.name, j.kind) for j in scene.joints][-1] == ("glue", "fixed")
    assert scene.bodies[scene.joints[-1].body_b].name == "free_link"


def test_two_hinges_on_one_body_chain_through_a_carrier():
    """A pendulum on hinges about x then y (a Cardan joint): the carrier's 1e-3 of the bob's mass
    keeps its swing within BOUND of MuJoCo's over 1 s."""
    xml = """<mujoco><worldbody><body name="bob" pos="0 0 1">
      <joint name="ax" type="hinge" axis="1 0 0"/><joint name="ay" type="hinge" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0.05 0 -0.4" size="0.03" contype="0" conaffinity="0"/></body></worldbody></mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    scene = ag.Scene.from_mjcf(m)
    assert [b.name for b in scene.bodies] == ["world", "bob/ax", "bob"]
    qpos, qvel = [[0.5, 0.3], [-1.0, 0.8], [0.2, -1.2]], [[0.0, 1.0], [1.0, 0.0], [-1.0, 2.0]]
    assert np.abs(abd_qpos(scene, qpos, qvel, 0.002) - mujoco_qpos(m, qpos, qvel)).max() < BOUND
