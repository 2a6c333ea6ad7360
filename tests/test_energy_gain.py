"""A converged step that gains energy in a conservative world is retried as substeps
(solver/energy_gain.py, solver/retry.py): the robustness report's double pendulums at dt 0.1 s
BDF2 gain more than 5% of their swing energy in a step without the test and not with it; a
retried step is the substeps' step from the state before it; a world whose drive pushes is not
tested, nor a scene with a position drive; a step still gaining at 4 substeps is kept and flagged,
in the vector env's info too."""
import numpy as np
import pytest

import abd_gym as ag
from abd_gym.bench import robustness as rb
from abd_gym.sim import conditioning, mechanisms
from abd_gym.solver.kernels import RESTART

W, DT = 16, 0.1
# dt 0.1 s turns these links more than 1 rad a step: the build warns (conditioning.step_too_large)
pytestmark = pytest.mark.filterwarnings("ignore:dt 0.1 s is beyond what body")


@pytest.fixture(scope="module")
def large_dt():
    case = rb.case("large_dt")
    return case, case.scene()


def _run(large_dt, energy_gain):
    case, scene = large_dt
    return rb.run_case(case, DT, "bdf2", "float64", worlds=W, scene=scene, energy_gain=energy_gain)


def test_no_world_gains_more_than_five_percent_in_a_step(large_dt):
    """The report's step gain (the largest rise of E in one OK step over the run's swing energy)."""
    plain, tested = _run(large_dt, 0.0), _run(large_dt, 0.05)
    assert plain["reported"] == tested["reported"] == 0
    assert plain["step_gain_worlds"] >= 2 and plain["worst_step_gain"] > 0.1
    assert plain["substeps"] == {2: 0, 4: 0}
    assert tested["step_gain_worlds"] == 0 and tested["worst_step_gain"] <= 0.05
    assert tested["substeps"][2] > 0 and tested["kept_gain"] == 0


def _sim(scene, dt=DT, **kw):
    kw.setdefault("retry", True)  # the default on the CPU; on a GPU the retry is asked for
    sim = ag.Simulator(scene, num_worlds=W, dt=dt, integrator="bdf2", dtype="float64", **kw)
    rng = np.random.default_rng(0)
    sim.set_joint_state(rng.uniform(-2.5, 2.5, (W, 2)))
    return sim


def test_a_gaining_step_is_retried_from_the_state_before_it(large_dt):
    """A world retried as 2 substeps ends where a simulator of dt/2 ends after 2 implicit Euler
    steps (fresh RESTART) from the state before the step, to Newton's stop, its joints at strength
    γ/4 (a substep keeps the joints' stiffness of the step it replaces: constitutions/_joint_step.py);
    the other worlds step bit for bit as without the test."""
    scene = large_dt[1]
    sim, plain = _sim(scene), _sim(scene, energy_gain=0)
    for _ in range(20):
        saved = sim.get_state()
        sim.step()
        plain.step()
        worlds = np.flatnonzero(sim.substeps() == 2)
        if len(worlds):
            break
        np.testing.assert_array_equal(sim.body_q(), plain.body_q())
    assert len(worlds) and (sim.world_status() == ag.WorldStatus.OK).all()
    others = np.setdiff1d(np.arange(W), worlds)
    np.testing.assert_array_equal(sim.body_q()[others], plain.body_q()[others])
    ref = ag.Simulator(scene, num_worlds=W, dt=DT / 2, integrator="bdf2", dtype="float64", retry=False)
    ref.set_joint_strength(np.tile(scene.strength_ratios() / 4, (W, 1)))
    saved["fresh"][:] = RESTART
    ref.set_state(saved)
    ref.step(2)
    np.testing.assert_allclose(sim.body_q()[worlds], ref.body_q()[worlds], rtol=0, atol=1e-5)
    assert not np.allclose(sim.body_q()[worlds], plain.body_q()[worlds], rtol=0, atol=1e-3)


def test_a_step_still_gaining_at_four_substeps_is_kept_and_flagged(large_dt):
    """A world whose energy before the step is set 1 J low (get_state/set_state) gains at every
    attempt: it takes 4 substeps, keeps their result and is flagged; the next step, from a known
    energy, is not."""
    sim = _sim(large_dt[1])
    sim.step()
    state = sim.get_state()
    state["energy"][:2, 0] -= 1.0
    sim.set_state(state)
    before = sim.body_q()
    sim.step()
    flagged = sim.energy_gained()
    np.testing.assert_array_equal(np.flatnonzero(flagged), [0, 1])
    np.testing.assert_array_equal(sim.substeps()[:2], [4, 4])
    assert (sim.world_status() == ag.WorldStatus.OK).all()
    assert not np.allclose(sim.body_q()[:2], before[:2])  # the 4 substeps' step, kept
    sim.step()
    assert not sim.energy_gained()[:2].any()


@pytest.fixture(scope="module")
def fourbar():
    case = rb.case("fourbar")
    return case, case.scene()


def _fourbar_sim(fourbar, torque, **kw):
    case, scene = fourbar
    kw.setdefault("retry", True)  # the default on the CPU; on a GPU the retry is asked for
    sim = ag.Simulator(scene, num_worlds=W, dt=0.05, integrator="bdf2", dtype="float64", **kw)
    sim.set_joint_state(*case.state(np.random.default_rng(0), W))
    sim.set_controls(np.full((W, 1), torque))
    return sim


def test_a_world_whose_drive_pushes_is_not_tested(fourbar):
    """FourBar-v0's linkage at dt 0.05 s BDF2: with its crank's effort drive at 0 the test retries
    steps besides the failed ones; with a torque, only the failed ones, and the worlds step bit
    for bit as without the test."""
    idle, idle_plain = _fourbar_sim(fourbar, 0.0), _fourbar_sim(fourbar, 0.0, energy_gain=0)
    pushed, plain = _fourbar_sim(fourbar, 0.5), _fourbar_sim(fourbar, 0.5, energy_gain=0)
    extra = 0
    for _ in range(20):
        for sim in (idle, idle_plain, pushed, plain):
            sim.step()
        extra += int((idle.substeps() > 1).sum() - (idle_plain.substeps() > 1).sum())
        np.testing.assert_array_equal(pushed.substeps(), plain.substeps())
        np.testing.assert_array_equal(pushed.body_q(), plain.body_q())
    assert extra > 0


@pytest.mark.parametrize("worlds", [1, 3])
def test_the_test_is_skipped_while_every_drive_pushes(worlds):
    """A pushed step is not tested and leaves every energy unknown (NaN), to be computed before the
    next tested step; one world with one drive (its own host check) as several; the steps are
    the plain ones bit for bit."""
    scene = mechanisms.pendulum()
    scene.add_drive(scene.joints[0].name, mode="effort", max_effort=5.0)
    sims = [ag.Simulator(scene, num_worlds=worlds, dt=0.01, dtype="float64", energy_gain=g, retry=True) for g in (0.05, 0)]
    for sim in sims:
        sim.set_joint_state(np.linspace(0.5, 1.5, worlds)[:, None])
    for control, tested in ((1.0, False), (0.0, True), (-0.5, False)):
        for sim in sims:
            sim.set_controls(np.full((worlds, 1), control))
            sim.step()
        energy = sims[0].state.energy.numpy()[:, 0]
        assert sims[0].solver.retry.testing == tested
        assert np.isfinite(energy).all() if tested else np.isnan(energy).all()
        np.testing.assert_array_equal(sims[0].body_q(), sims[1].body_q())


def test_a_scene_with_a_position_drive_is_not_tested():
    scene = mechanisms.double_pendulum()
    scene.add_drive(scene.joints[0].name, mode="position", stiffness=10.0)
    assert ag.Simulator(scene, num_worlds=2, energy_gain=0.05, retry=True).solver.retry.energy is None
    assert ag.Simulator(mechanisms.double_pendulum(), num_worlds=2, energy_gain=0.05, retry=True).solver.retry.energy is not None
    assert ag.Simulator(mechanisms.double_pendulum(), num_worlds=2, energy_gain=0, retry=True).solver.retry.energy is None
    with pytest.raises(ValueError, match="energy_gain"):
        ag.Simulator(mechanisms.double_pendulum(), num_worlds=2, energy_gain=-0.1)


def test_the_tests_energies_are_the_reports_sum():
    """EnergyCheck.measure leaves the drives' launch out (a conservative scene's drives have no
    physical energy) and takes the point joints' energies without their derivatives: its
    columns, each times its scale to J, equal ``energies()``'s bit for bit, revolute and fixed
    joints, effort and velocity drives pushing or not."""
    scene = mechanisms.double_pendulum()
    weight = scene.add_body(ag.Box(half_extents=(0.05, 0.05, 0.05)), mass=0.5, position=(0.1, 0.0, -0.75))
    scene.add_fixed_joint("link1", weight)
    scene.add_drive(scene.joints[0].name, mode="effort", max_effort=5.0)
    scene.add_drive(scene.joints[1].name, mode="velocity", damping=2.0, max_effort=5.0)
    sim = ag.Simulator(scene, num_worlds=W, dt=0.01, integrator="bdf2", dtype="float64", energy_gain=0.05, retry=True)
    x = np.zeros((W, scene.num_joints))  # (the weld's coordinate 0)
    x[:, :2] = np.random.default_rng(0).uniform(-2.5, 2.5, (W, 2))
    sim.set_joint_state(x)
    sim.set_controls(np.tile([[0.0, 0.0], [1.5, -0.7]], (W // 2, 1)))
    for _ in range(3):
        sim.step()
    check = sim.solver.retry.energy
    assert {c.name for c in check.parts} >= {"revolute_joint", "fixed_joint"}
    assert all(c.name != "drive" for c in check.parts)
    check.measure(sim.state, sim.solver.all_active)
    measured, report = check.E.numpy(), sim.energies()
    assert set(report) == {name for name in sim.solver.report_cols if name != "scratch"}
    scale = check.scale.numpy()  # to J: a joint's column over ĥ₀², every other 1
    np.testing.assert_array_equal(scale, sim.solver.report_scale)
    for name, col in sim.solver.report_cols.items():
        if name != "scratch":
            np.testing.assert_array_equal(measured[:, col] * scale[col], report[name])
    assert not report["drive"].any()


def test_the_test_runs_by_default_at_large_steps_only():
    """energy_gain None: the test is built only where a step turns the fastest gravity mode past
    ENERGY_TEST_TURN (the double pendulum's links, 6.2 rad/s: dt 0.03 and 0.1, not 0.01 or 0.02),
    so that healthy worlds at ordinary steps pay nothing for it."""
    for dt, tested in ((0.01, False), (0.02, False), (0.03, True), (0.1, True)):
        sim = ag.Simulator(mechanisms.double_pendulum(), num_worlds=2, dt=dt)
        assert (sim.solver.retry.energy is not None) == tested, dt
        assert (conditioning.task_energy_gain(mechanisms.double_pendulum(), dt) > 0) == tested, dt


def test_a_parameter_change_is_not_a_gain(large_dt):
    """Doubling a world's masses doubles its energy between steps: the setter makes the energy
    before the next step be computed anew, so that step is not retried."""
    sim = _sim(large_dt[1], dt=0.01)
    sim.step()
    sim.set_body_mass(np.full((1, 3), 2.0), worlds=[3])
    sim.step()
    np.testing.assert_array_equal(sim.substeps(), np.ones(W))


def test_the_vector_env_reports_a_kept_gain():
    """FourBar-v0 (one physics step an env step, so that its last is the one set 1 J low) at zero
    torque: its info flags the world whose step was kept gaining."""
    from abd_gym.envs.fourbar import FourBarVectorEnv

    class OneStep(FourBarVectorEnv):
        frame_skip = 1

    env = OneStep(num_envs=2, dtype="float64", simulator_options={"energy_gain": 0.05})  # (dt 0.01: off by default)
    env.reset(seed=0)
    info = env.step(np.zeros((2, 1), dtype=np.float32))[4]
    np.testing.assert_array_equal(info["sim_energy_gained"], [False, False])
    state = env.sim.get_state()
    state["energy"][1, 0] -= 1.0
    env.sim.set_state(state)
    info = env.step(np.zeros((2, 1), dtype=np.float32))[4]
    np.testing.assert_array_equal(info["sim_energy_gained"], [False, True])
    np.testing.assert_array_equal(info["sim_substeps"], [1, 4])


@pytest.mark.parametrize("integrator", ["implicit_euler", "bdf2"])
def test_a_limits_energy_is_physical_in_the_test_and_the_report(integrator):
    """A limit's cubic sits outside ĥ² as a joint's penalty does: energies(), the energy test's
    measure and the robustness report count it as E(x)/dt² [J] (the stiffness of the implicit
    Euler step that follows a step ending on the limit), one scale for both."""
    case = rb.case("prismatic_slam")
    scene = case.scene()
    dt = 0.01
    sim = ag.Simulator(scene, num_worlds=4, dt=dt, integrator=integrator, dtype="float64", energy_gain=0.05)
    x, v = case.state(np.random.default_rng(0), 4)
    sim.set_joint_state(x, v)
    pressed = np.zeros(4, bool)
    for _ in range(40):  # until every block has been on its limit at the end of a step
        sim.step()
        pressed |= sim.energies()["prismatic_limit"] > 0
        if pressed.all():
            break
    assert pressed.any()
    col = sim.solver.report_cols["prismatic_limit"]
    assert sim.solver.report_scale[col] == 1.0 / dt**2
    check = sim.solver.retry.energy
    check.measure(sim.state, sim.solver.all_active)
    stored = check.E.numpy()[:, col]
    np.testing.assert_array_equal(stored * check.scale.numpy()[col], sim.energies()["prismatic_limit"])
    # (the seed's E(x)/dt² against a float64 reference: tests/test_constitutions.py)
