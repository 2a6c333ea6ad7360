"""The energy test's allowance is the rounding of what it compares (solver/energy_gain.py): a
float32 world at rest or in slow motion, with and without gravity, gains nothing beyond the
rounding of q, q̇ and its energies, and is neither retried nor flagged; the gains the test exists
for (the robustness report's double pendulums at dt 0.1 s, the four-bar at dt 0.1 s) are still
retried away in float32 as in float64."""
import warnings

import numpy as np
import pytest

import abd_gym as ag
from abd_gym.bench import robustness as rb
from abd_gym.envs.reacher import ReacherVectorEnv
from abd_gym.sim import mechanisms

W, STEPS = 8, 60


def _quiet(scene, x, v, dt=0.01, integrator="bdf2"):
    """(retried world-steps, flagged world-steps) of STEPS float32 steps with the test at its
    default tolerance, asked for at any dt."""
    sim = ag.Simulator(scene, num_worlds=W, dt=dt, integrator=integrator, dtype="float32", energy_gain=0.05)
    assert sim.solver.retry.energy is not None  # the scene is tested
    sim.set_joint_state(x, v)
    retried = flagged = 0
    for _ in range(STEPS):
        sim.step()
        retried += int((sim.substeps() > 1).sum())
        flagged += int(sim.energy_gained().sum())
    return retried, flagged


@pytest.fixture(scope="module")
def reacher():
    """TwoLinkReacher-v0's scene (no gravity) and its reset draws."""
    env = ReacherVectorEnv(num_envs=1)
    x, v = env.initial_state(W, np.random.default_rng(0), {})
    return env.scene, np.asarray(x, np.float64), np.asarray(v, np.float64)


@pytest.mark.parametrize("integrator", ["bdf2", "implicit_euler"])
def test_reacher_resets_in_float32_are_not_retried(reacher, integrator):
    """Its reset draws (swing energies 1e-10 to 1e-7 J, which q̇'s float32 rounding reaches)."""
    scene, x, v = reacher
    assert _quiet(scene, x, v, integrator=integrator) == (0, 0)


@pytest.mark.parametrize("gravity", [(0.0, 0.0, 0.0), (0.0, 0.0, -9.81)], ids=["no_gravity", "gravity"])
@pytest.mark.parametrize("rate", [0.0, 1e-3], ids=["rest", "slow"])
def test_float32_rest_and_slow_motion_are_not_retried(gravity, rate):
    """A double pendulum hanging at rest, or turning at 1e-3 rad/s, in float32."""
    scene = mechanisms.double_pendulum(gravity=gravity)
    x = np.zeros((W, 2))
    v = np.full((W, 2), rate) * np.linspace(-1.0, 1.0, W)[:, None]
    assert _quiet(scene, x, v) == (0, 0)


@pytest.fixture(scope="module")
def large_dt():
    case = rb.case("large_dt")
    return case, case.scene()


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_large_steps_gains_are_still_caught(large_dt, dtype):
    """Double pendulums released from ±2.5 rad at dt 0.1 s (BDF2) gain over 5% of their swing
    energy in a step without the test; with it no world does, in either dtype."""
    case, scene = large_dt
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plain = rb.run_case(case, 0.1, "bdf2", dtype, worlds=16, scene=scene, energy_gain=0.0)
        tested = rb.run_case(case, 0.1, "bdf2", dtype, worlds=16, scene=scene)
    assert plain["step_gain_worlds"] > 0 and plain["worst_step_gain"] > 0.1
    assert tested["step_gain_worlds"] == 0 and tested["kept_gain"] == 0
    assert tested["substeps"][2] > 0


def test_fourbar_gains_are_still_caught_in_float32():
    """FourBar-v0's linkage at dt 0.1 s (BDF2, float32): worlds gaining over 5% in a step
    without the test, none with it."""
    case = rb.case("fourbar")
    scene = case.scene()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plain = rb.run_case(case, 0.1, "bdf2", "float32", worlds=64, scene=scene, energy_gain=0.0)
        tested = rb.run_case(case, 0.1, "bdf2", "float32", worlds=64, scene=scene)
    assert plain["step_gain_worlds"] > 0
    assert tested["step_gain_worlds"] == 0 and tested["kept_gain"] == 0


def test_float32_rest_on_a_limit_is_not_retried():
    """A double pendulum whose hinges gravity presses onto their lower bound (0.3 rad), settling
    there in float32: the limit's physical energy (E(x)/dt²) at rest moves within the allowance."""
    scene = mechanisms.chain(2, limit=(0.3, 0.6, 1e3))
    x = np.tile([0.31, 0.31], (W, 1)) + np.linspace(0.0, 0.01, W)[:, None]
    assert _quiet(scene, x, np.zeros((W, 2))) == (0, 0)


def test_the_report_allows_the_tests_rounding(reacher):
    """Simulator.energy_allowance is the allowance the energy test keeps for a state (State.energy
    column 3 after a kept step), bit for bit: one function for both."""
    scene, x, v = reacher
    sim = ag.Simulator(scene, num_worlds=W, dt=0.01, integrator="bdf2", dtype="float32", energy_gain=0.05)
    sim.set_joint_state(x, v)
    for _ in range(3):
        sim.step()
        kept = sim.state.energy.numpy()[:, 3]
        assert (sim.substeps() == 1).all()
        np.testing.assert_array_equal(sim.energy_allowance(), kept.astype(np.float64))
        assert (kept > 0).all()


def test_the_report_counts_no_float32_rounding_as_a_gain(reacher):
    """The Reacher's reset draws in float32 (swing energies 1e-10 to 1e-7 J): the report's step
    gain (bench/robustness.py) counts no world above 5% once the allowance is taken off, while
    the raw rises of E it leaves out do reach 5% of some worlds' swing energy."""
    scene, x, v = reacher
    sim = ag.Simulator(scene, num_worlds=W, dt=0.01, integrator="bdf2", dtype="float32", energy_gain=0.0)
    sim.set_joint_state(x, v)
    e = sum(sim.energies().values())
    swing, raw = e.copy(), np.zeros(W)
    for _ in range(STEPS):
        sim.step()
        e_next = sum(sim.energies().values())
        raw, e = np.maximum(raw, e_next - e), e_next
    assert ((raw / swing) > rb.GAIN_LIMIT).any()
    sim.set_joint_state(x, v)
    row = rb._measure(sim, scene, STEPS, dict(conservative=True))
    assert row["step_gain_worlds"] == 0 and row["gain_worlds"] == 0


def _column(sim, q, name):
    """(E, R) [J] of the column ``name`` that the energy test measures at body states q (float64
    (W, bodies, 12), cast to the simulator's dtype), each times the column's scale."""
    sim.state.q.assign(q.astype(sim.model.np_dtype))
    check = sim.solver.retry.energy
    check.measure(sim.state, sim.solver.all_active)
    E, col = check.E.numpy().astype(np.float64), sim.solver.report_cols[name]
    scale = sim.solver.report_scale[col]
    return E[:, col] * scale, E[:, check.roff + col] * scale


def _float32_within_allowance(sims, q, name) -> int:
    """Asserts the column ``name`` of the float32 simulator at ``q`` equals its energies() report
    bit for bit, has a positive R in every world, and is within its allowance 1000 eps |E| +
    2 sqrt(E R) + R of the float64 energy; returns how many worlds are off by more than the sums'
    term 1000 eps |E| alone."""
    e64, _ = _column(sims["float64"], q, name)
    e32, r32 = _column(sims["float32"], q, name)
    np.testing.assert_array_equal(e32, sims["float32"].energies()[name])  # the report's, bit for bit
    assert (r32 > 0).all()
    err = np.abs(e32 - e64)
    sums = 1000.0 * np.finfo(np.float32).eps * np.abs(e32)
    assert (err <= sums + 2.0 * np.sqrt(np.abs(e32) * r32) + r32).all()
    return int((err > sums).sum())


def test_a_prismatic_joints_rounding_bounds_its_float32_energy():
    """A slider's prismatic joint in float32 (the block moved 1e-7 to 1e-3 off its rail, its
    frame turned as much): the joint energy at the float32 state, in float32, differs from the
    float64 energy of the exact state by less than its allowance 1000 eps |E| + 2 sqrt(E R) + R
    (R the energy of the four residuals' rounding), where the sums' term alone falls short."""
    n = 16
    scene = mechanisms.slider()
    sims = {d: ag.Simulator(scene, num_worlds=n, dt=0.01, dtype=d, energy_gain=0.05) for d in ("float32", "float64")}
    rng = np.random.default_rng(1)
    sims["float64"].set_joint_state(rng.uniform(-1.0, 1.0, (n, 1)), rng.uniform(-3.0, 3.0, (n, 1)))
    sims["float64"].step()
    q = sims["float64"].state.q.numpy().copy()
    off = np.logspace(-7, -3, n)[:, None]
    q[:, 1] += rng.normal(0.0, 1.0, (n, 12)) * off  # the block (body 1) off its rail
    assert _float32_within_allowance(sims, q, "prismatic_joint") >= n // 2


def test_a_prismatic_limits_rounding_bounds_its_float32_energy():
    """The slammer's block (a prismatic limit at ±0.25 m, strength 1e5) pressed 1e-6 to 1e-2 m past
    its bound, or 1e-7 m short of it: the limit's energy at the float32 state, in float32, differs
    from the float64 energy of the exact state by less than its allowance, where the sums' term
    alone falls short."""
    n = 16
    scene = rb.slammer()
    sims = {d: ag.Simulator(scene, num_worlds=n, dt=0.01, dtype=d, energy_gain=0.05) for d in ("float32", "float64")}
    past = np.concatenate([np.logspace(-6, -2, n - 2), [-1e-7, -1e-7]])
    x = (0.25 + past) * np.where(np.arange(n) % 2, 1.0, -1.0)
    sims["float64"].set_joint_state(x[:, None])
    q = sims["float64"].state.q.numpy().copy()
    q[:, 1, 3:] += np.random.default_rng(2).normal(0.0, 1e-6, (n, 9))  # its frame turned a little
    assert _float32_within_allowance(sims, q, "prismatic_limit") >= n // 4


def test_a_revolute_limits_rounding_bounds_its_float32_energy():
    """A pendulum pressed 1e-6 to 1e-2 rad past its hinge's bound (0.3 rad, strength 1e3), or 1e-7
    rad short of it, its link's frame turned by 1e-6: the limit's float32 energy within its
    allowance of the float64 one, where the sums' term alone falls short."""
    n = 16
    scene = mechanisms.chain(1, limit=(-0.3, 0.3, 1e3))
    sims = {d: ag.Simulator(scene, num_worlds=n, dt=0.01, dtype=d, energy_gain=0.05) for d in ("float32", "float64")}
    past = np.concatenate([np.logspace(-6, -2, n - 2), [-1e-7, -1e-7]])
    x = (0.3 + past) * np.where(np.arange(n) % 2, 1.0, -1.0)
    for sim in sims.values():  # (each with its own reference angle θ0, c_prev, s_prev)
        sim.set_joint_state(x[:, None])
    q = sims["float64"].state.q.numpy().copy()
    q[:, -1, 3:] += np.random.default_rng(3).normal(0.0, 1e-6, (n, 9))  # the link's frame turned a little
    assert _float32_within_allowance(sims, q, "revolute_limit") >= n // 4


def test_the_armature_has_its_rates_rounding():
    """CartPole's slider and hinge with armature 0.1 kg and 0.1 kg m²: the kinetic column (the
    armature's ½aẋ² included, by a kernel of its own) equals energies()'s bit for bit, and its R
    grows by the armature's ½a(δẋ)² over the same scene without armature, at rest and moving."""
    n = 8
    scenes = {}
    for armature in (0.0, 0.1):
        scene = mechanisms.cartpole()
        if armature:
            for joint in scene.joints:
                scene.set_joint_passive(joint.name, armature=armature)
        scenes[armature] = scene
    x = np.tile([0.1, 0.2], (n, 1))
    v = np.logspace(-4, 0, n)[:, None] * np.array([[1.0, -1.0]])
    rounding = {}
    for armature, scene in scenes.items():
        sim = ag.Simulator(scene, num_worlds=n, dt=0.01, dtype="float32", energy_gain=0.05)
        sim.set_joint_state(x, v)
        sim.step()
        check = sim.solver.retry.energy
        assert any(c.name == "passive" for c in check.parts) == bool(armature)
        check.measure(sim.state, sim.solver.all_active)
        E, col = check.E.numpy().astype(np.float64), sim.solver.report_cols["kinetic"]
        np.testing.assert_array_equal(E[:, col], sim.energies()["kinetic"])
        rounding[armature] = E[:, check.roff + col]
    assert (rounding[0.1] > rounding[0.0]).all()
