"""to_mjcf: the exported MuJoCo model is the same mechanism as the abd_gym scene.

Structure: to_mjcf then Scene.from_mjcf gives back the masses, second moments, joint anchors, axes
and limits.  Motion: from random starts, 0.5 s of MuJoCo C (RK4, dt 1e-4 s) against abd_gym
(float64, BDF2, dt 1e-3 s); joint coordinates agree within 0.01 rad (or m), the bound
test_mjcf.py holds the importer to, and a loop's connect stays closed in MuJoCo.
"""
import numpy as np
import pytest

mujoco = pytest.importorskip("mujoco")

import abd_gym as ag  # noqa: E402
from abd_gym.sim import mechanisms  # noqa: E402
from abd_gym.mjcf.export import spanning_tree, to_mjcf  # noqa: E402
from abd_gym.bench.cases import CASES, connect_gap, with_integrator  # noqa: E402
from mujoco_reference import REFERENCE_DT, rk4_qpos  # noqa: E402

DURATION = 0.5


def run_mujoco(case, q, qd, ctrl=None, duration=DURATION):
    """(qpos (worlds, nq) at the end, largest connect gap [m] on the way) of MuJoCo C RK4."""
    m = mujoco.MjModel.from_xml_string(case.xml(REFERENCE_DT))
    gaps = [0.0]
    qpos = rk4_qpos(m, case.mujoco_qpos(q), case.mujoco_qpos(qd), ctrl, duration,
                    lambda d: gaps.append(float(connect_gap(m, d.xpos[None], d.xmat[None])[0])))  # fmt: skip
    return qpos, max(gaps)


def run_ours(case, q, qd, controls=None, dt=1e-3, duration=DURATION):
    sim = ag.Simulator(case.scene(), num_worlds=len(q), dt=dt, dtype="float64", integrator="bdf2")
    sim.set_joint_state(q, qd)
    if controls is not None:
        sim.set_controls(np.broadcast_to(controls, (len(q), len(controls))))
    sim.step(round(duration / dt))
    return sim.joint_angles_unwrapped()


@pytest.mark.parametrize("name", ["chain5", "alt_chain5", "fourbar", "slider_crank"])
def test_exported_model_moves_like_ours(name):
    case = CASES[name]
    q, qd = case.states(3, 1)
    theirs, gap = run_mujoco(case, q, qd)
    ours = case.ours_from_qpos(case.mujoco_qpos(run_ours(case, q, qd)))
    assert np.abs(ours - case.ours_from_qpos(theirs)).max() < 0.01
    assert gap < 1e-3  # m: MuJoCo's soft connect holds the loop


def test_limit_and_effort_drive_agree():
    """The cart pushed at its full 10 N from x = 2 m: the same motion up to the limit at 2.4 m
    (the motor's sign and scale), and both engines stop it within 3 cm beyond.  After the impact
    they differ by constitution: abd_gym's cubic limit energy is elastic (the cart rebounds),
    MuJoCo's soft limit constraint is damped (the cart rests at the limit)."""
    case = CASES["cartpole"]
    m = mujoco.MjModel.from_xml_string(with_integrator(case.xml(REFERENCE_DT), "RK4"))
    d = mujoco.MjData(m)
    d.qpos[0], d.ctrl[0] = 2.0, 10.0
    sim = ag.Simulator(case.scene(), num_worlds=1, dt=1e-3, dtype="float64", integrator="bdf2")
    sim.set_joint_state(np.array([[2.0, 0.0]]), np.zeros((1, 2)))
    sim.set_controls(np.array([[10.0]]))
    theirs, ours = [], []
    for _ in range(50):  # 10 ms each
        sim.step(10)
        for _ in range(100):
            mujoco.mj_step(m, d)
        ours.append(sim.joint_coordinates()[0, 0])
        theirs.append(d.qpos[0])
    ours, theirs = np.array(ours), np.array(theirs)
    np.testing.assert_allclose(ours[:25], theirs[:25], atol=1e-4)  # 0.25 s, 0.3 m of travel, both free
    assert 2.39 < ours.max() < 2.43 and 2.39 < theirs.max() < 2.43


@pytest.mark.parametrize("name", ["cartpole", "fourbar", "slider_crank", "reacher"])
def test_round_trip_keeps_the_mechanism(name):
    """to_mjcf then Scene.from_mjcf: same masses and second moments (in the same body frames),
    joint anchors, axes, limits, drives; the loop-closing joint comes back as a revolute joint."""
    scene = CASES[name].scene()
    back = ag.Scene.from_mjcf(to_mjcf(scene, 0.01).xml)
    moving = [b for b in scene.bodies if not b.fixed]
    assert [b.name for b in back.bodies if not b.fixed] == [b.name for b in moving]
    for b in moving:
        r = back.bodies[back.body_index(b.name)]
        assert r.mass == pytest.approx(b.mass, rel=1e-12)
        np.testing.assert_allclose(r.position, b.position, atol=1e-12)
        np.testing.assert_allclose(r.rotation, b.rotation, atol=1e-12)
        np.testing.assert_allclose(r.moments.second_moment, b.moments.second_moment, rtol=1e-9, atol=1e-15)
    assert sorted(j.name for j in back.joints) == sorted(j.name for j in scene.joints)
    for j in scene.joints:
        r = back.joints[back.joint_index(j.name)]
        assert r.kind == j.kind
        np.testing.assert_allclose(r.anchor, j.anchor, atol=1e-12)
        np.testing.assert_allclose(r.frame[0] * np.sign(r.frame[0] @ j.frame[0]), j.frame[0], atol=1e-12)
        for key in ("limit/lower", "limit/upper"):
            assert r.attributes.get(key) == pytest.approx(j.attributes.get(key))
    assert [(d.mode, d.max_effort) for d in back.drives] == [(d.mode, d.max_effort) for d in scene.drives]


def test_spanning_tree_closes_loops_at_revolute_joints():
    """The slider-crank's slider stays in the tree (MuJoCo has no sliding equality); the
    rod–piston hinge closes the loop."""
    scene = CASES["slider_crank"].scene()
    tree, loops = spanning_tree(scene)
    assert [scene.joints[k].name for k in loops] == ["C"] and len(tree) == 3


def test_refuses_what_mujoco_cannot_hold():
    scene = mechanisms.chain(2, length=0.1)
    scene.bodies[0].fixed = False
    with pytest.raises(ValueError, match="no fixed body"):
        to_mjcf(scene, 0.01)
    loop = ag.Scene()
    base = loop.add_body(ag.Box(half_extents=(0.05, 0.05, 0.05)), fixed=True)
    block = loop.add_body(ag.Box(half_extents=(0.05, 0.05, 0.05)), mass=1.0)
    arm = loop.add_body(ag.Box(half_extents=(0.05, 0.05, 0.05)), mass=1.0, position=(0.2, 0, 0))
    loop.add_prismatic_joint(base, block, anchor=(0, 0, 0), axis=(1, 0, 0))
    loop.add_prismatic_joint(base, arm, anchor=(0.2, 0, 0), axis=(1, 0, 0))
    loop.add_prismatic_joint(block, arm, anchor=(0.1, 0, 0), axis=(0, 0, 1), name="rail")
    with pytest.raises(ValueError, match="'rail' closes a loop"):
        to_mjcf(loop, 0.01)
