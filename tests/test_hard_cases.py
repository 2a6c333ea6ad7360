"""Numerical stability on hard cases, under implicit Euler and BDF2: each must finish with no NaN,
no energy gain (both integrators only dissipate here), a bounded joint residual, and Newton
converged in every world.

The hard-case suite (the cases of ``python -m abd_gym.bench robustness``, 8 worlds each, every
integrator and dtype, default settings) asserts what a user must be able to rely on: every step
converged or its world reported, no silent energy gain above 5% of a world's swing energy in a
conservative scene, joint gaps in millimetres, limits that hold, no failure on 1:1000 mass
ratios in float32, and settings or states that cannot work announced."""
import functools

import numpy as np
import pytest

import abd_gym as ag
from abd_gym.bench import robustness as rb
from abd_gym.sim import mechanisms


def _total_energy(sim):
    return sum(sim.energies().values())


def _run(scene, x0, dt, steps, dtype="float32", **kw):
    sim = ag.Simulator(scene, num_worlds=len(x0), dt=dt, dtype=dtype, **kw)
    sim.set_joint_state(x0)
    e0 = _total_energy(sim)
    gain, residual, converged = -np.inf, 0.0, True
    for _ in range(steps):
        sim.step()
        gain = np.maximum(gain, _total_energy(sim) - e0)
        residual = max(residual, sim.joint_violation().max())
        converged &= bool(sim.converged().all())
    assert sim.failed_worlds().size == 0
    assert np.isfinite(sim.body_q()).all()
    return sim, np.max(gain), residual, converged, np.abs(e0).max()


INTEGRATORS = pytest.mark.parametrize("integrator", ["implicit_euler", "bdf2"])


@INTEGRATORS
@pytest.mark.parametrize("masses", [(0.01, 10.0), (10.0, 0.01)])
def test_mass_ratio_1_to_1000(masses, integrator):
    """A 10 g link hanging from a 10 kg one and the reverse: K = strength_ratio·(m_i + m_j) keeps
    the light link's joint as tight as the heavy one's; residual under 0.2 mm, no energy gain."""
    _, gain, residual, converged, e0 = _run(mechanisms.chain(2, masses=list(masses)), [[1.0, 0.5]], 0.01, 150,
                                            integrator=integrator)  # fmt: skip
    assert gain <= 1e-4 * e0
    assert residual < 2e-4
    assert converged


@INTEGRATORS
def test_twenty_link_chain(integrator):
    """A 20-link chain (240 unknowns per world, one dense solve) released at 0.3 rad per joint."""
    sim, gain, residual, converged, e0 = _run(mechanisms.chain(20, length=0.1), [[0.3] * 20], 0.01, 40, integrator=integrator)
    assert gain <= 1e-4 * e0
    assert residual < 5e-4
    assert converged


def test_mixed_mass_3d_chain_converges_at_the_defaults():
    """A 30-link chain with hinges about +y and +x in turn and link masses from 1e-3 to 1e2 kg
    (mechanisms.mixed_masses; joint K/m up to 2e7): its light links carry loads far beyond their own
    weight, and Newton with the orthogonality Hessian's PSD part converges only linearly there.  At
    the defaults (a budget that follows the stiffest joint, conditioning.default_max_iterations;
    the exact Hessian after a linearly converging iteration) every world's BDF2 step converges
    (float64, dt 0.01, 8 worlds from random states; with 50 iterations and the PSD Hessian alone
    one world's 8th step was rejected), joints within 1 mm, and the trajectory is the staged
    kernels' (the PSD Hessian alone, within the same budget) to 1e-6; a budget the user sets is
    kept."""
    from abd_gym.sim import conditioning

    scene = mechanisms.alternating_chain(30, length=0.1, masses=mechanisms.mixed_masses(30))
    with pytest.warns(RuntimeWarning, match="float32 solves reliably"):
        ag.Simulator(scene, num_worlds=1, dtype="float32")  # (no kernel built: the warning only)
    q = {}
    for fused in (True, False):
        sim = ag.Simulator(scene, num_worlds=8, dt=0.01, dtype="float64", integrator="bdf2", plan=dict(fused=fused))
        assert sim.model.stiff and sim.solver.settings.max_iterations == conditioning.default_max_iterations(scene)
        rng = np.random.default_rng(0)
        sim.set_joint_state(rng.uniform(-1, 1, (8, 30)), rng.uniform(-2, 2, (8, 30)))
        most = 0
        for _ in range(10):
            sim.step()
            assert sim.failed_worlds().size == 0 and sim.converged().all()
            assert sim.joint_violation().max() <= 1e-3
            most = max(most, sim.newton_iterations().max())
        assert most > 30  # (the hard steps are taken)
        q[fused] = sim.body_q()
    assert conditioning.default_max_iterations(scene) == 215
    np.testing.assert_allclose(q[True], q[False], rtol=0, atol=1e-6)
    assert ag.Simulator(scene, num_worlds=1, dtype="float64", max_iterations=7).solver.settings.max_iterations == 7
    assert ag.Simulator(mechanisms.chain(30, length=0.1), num_worlds=1).solver.settings.max_iterations == 50


def test_mixed_mass_3d_chain_converges_in_float32():
    """The same chain in float32 (its K/m past what float32 solves reliably: the simulator warns),
    BDF2, 16 worlds, 25 steps: every step converges, a world whose iterates from the guess end
    where no Hessian's step finds a decrease starting again from the prediction q̃ (from seed 4,
    worlds 1 and 15 take that retry, at steps 2 and 5)."""
    scene = mechanisms.alternating_chain(30, length=0.1, masses=mechanisms.mixed_masses(30))
    with pytest.warns(RuntimeWarning, match="float32 solves reliably"):
        sim = ag.Simulator(scene, num_worlds=16, dt=0.01, integrator="bdf2")
    rng = np.random.default_rng(4)
    sim.set_joint_state(rng.uniform(-1, 1, (16, 30)), rng.uniform(-2, 2, (16, 30)))
    retried = np.zeros(16, bool)
    for _ in range(25):
        sim.step()
        assert sim.failed_worlds().size == 0 and sim.converged().all()
        assert sim.joint_violation().max() <= 1e-3
        retried |= sim.newton_retried()
    assert retried.any()


@INTEGRATORS
def test_large_step_dt_0_05(integrator):
    """dt = 0.05 on a double pendulum released at (2, 1) rad: stable, residual under 1 mm."""
    _, gain, residual, converged, e0 = _run(mechanisms.double_pendulum(), [[2.0, 1.0]], 0.05, 60, integrator=integrator)
    assert gain <= 1e-4 * e0
    assert residual < 1e-3
    assert converged


@INTEGRATORS
@pytest.mark.parametrize("reuse", [False, True])
def test_hard_steps_take_few_iterations(integrator, reuse):
    """dt = 0.05, 32 double pendulums released at random angles up to 2.5 rad, float32, with and
    without factor reuse: no step's Newton solve takes more than 25 iterations.  A reused factor
    whose step was rejected ends reuse for the rest of the step; when reuse and refactoring
    alternated, one step took 46 iterations under implicit Euler, near the cap of 50 (and reached
    it on an H100)."""
    x0 = np.random.default_rng(0).uniform(-2.5, 2.5, (32, 2))
    sim = ag.Simulator(mechanisms.double_pendulum(), num_worlds=32, dt=0.05, integrator=integrator,
                       reuse_factor=reuse)  # fmt: skip
    sim.set_joint_state(x0)
    most = 0
    for _ in range(100):
        sim.step()
        assert sim.converged().all()
        most = max(most, int(sim.newton_iterations().max()))
    assert most <= 25


@INTEGRATORS
@pytest.mark.parametrize("ratio,bound,dtype", [(1.0, 1e-2, "float32"), (1e2, 1e-4, "float32"), (1e4, 1e-6, "float32"),
                                               (1e5, 1e-6, "float32"), (1e6, 1e-6, "float64")])  # fmt: skip
def test_strength_ratios_1_to_1e6(ratio, bound, dtype, integrator):
    """Joint strength ratio over six decades: the residual falls with strength (to float32's floor)
    and Newton converges.  float32 holds to 1e5; at 1e6 its Cholesky factor breaks down in some
    worlds (256 double pendulums from (2, 1) ± 0.3 rad, 100 steps: 1 world under implicit Euler, 19
    under BDF2 end FAILED), so 1e6 is a float64 case (none fail there, at most 5 iterations)."""
    _, gain, residual, converged, e0 = _run(mechanisms.double_pendulum(strength_ratio=ratio), [[2.0, 1.0]], 0.01, 100,
                                            dtype=dtype, integrator=integrator)  # fmt: skip
    assert gain <= 1e-4 * e0
    assert residual < bound
    assert converged


def test_default_tolerance_matches_exact_implicit_euler():
    """The default Newton stop leaves trajectories indistinguishable from implicit Euler solved to
    1e-10: 1 s of a double pendulum agrees to 1e-6 rad in float64 (measured 1.5e-8 on the CPU,
    1.1e-7 on an H100: where the stop falls differs with rounding) and to 5e-3 rad in float32
    (float32 rounding; implicit Euler's own error against the true motion here is ~0.07 rad)."""

    def trajectory(dtype, tol):
        sim = ag.Simulator(mechanisms.double_pendulum(), num_worlds=2, dt=0.01, dtype=dtype, tol=tol,
                           integrator="implicit_euler")
        sim.set_joint_state([[1.0, -0.5], [2.0, 1.0]])
        out = []
        for _ in range(100):
            sim.step()
            out.append(sim.joint_coordinates())
        return np.array(out)

    exact = trajectory("float64", 1e-10)
    assert np.abs(trajectory("float64", 1e-5) - exact).max() < 1e-6
    assert np.abs(trajectory("float32", 1e-5) - exact).max() < 5e-3


def _forced_cartpoles(steps, **kw):
    """16 CartPole-v0 scenes at dt 0.02 under random cart forces (±10 N, new each step), every world
    converged each step: the mean Newton iterations a step and the final joint coordinates."""
    from abd_gym.envs.cartpole import build_cart_scene

    sim = ag.Simulator(build_cart_scene(), num_worlds=16, dt=0.02, integrator="implicit_euler", **kw)
    rng = np.random.default_rng(0)
    sim.set_joint_state(np.c_[np.zeros(16), rng.uniform(-0.2, 0.2, 16)])
    its = []
    for _ in range(steps):
        sim.set_controls(rng.uniform(-10, 10, (16, 1)))
        sim.step()
        assert sim.converged().all()
        its.append(sim.newton_iterations().mean())
    return np.mean(its), sim.joint_coordinates()


@pytest.mark.parametrize("dtype, most", [("float64", 3.4), ("float32", 4.0)])
def test_newton_follows_rotations(dtype, most):
    """A pole turning under random cart forces at dt 0.02 (the CartPole-v0 scene): the initial
    guess and the trial points rotate A along rotations (affine_body.retract) instead of lines
    that leave the rotations by ~(ωh)², where the stiff orthogonality energy makes Newton take
    several steps to turn the pole.  Measured on 16 worlds: 4.54 → 3.14 iterations a step
    (float64) and 5.91 → 3.62 (float32)."""
    assert _forced_cartpoles(40, dtype=dtype)[0] < most


def _pendulums(dtype="float32", steps=60, **kw):
    """16 float32 double pendulums at dt 0.01 from the bench's random states: joint coordinates
    over ``steps`` steps, mean Newton iterations, and the simulator."""
    from abd_gym.bench.compare import random_states

    sim = ag.Simulator(mechanisms.double_pendulum(), num_worlds=16, dt=0.01, dtype=dtype, integrator="implicit_euler",
                       **kw)
    sim.set_joint_state(random_states("double_pendulum", 16))
    out, its = [], []
    for _ in range(steps):
        sim.step()
        assert sim.converged().all()
        out.append(sim.joint_coordinates())
        its.append(sim.newton_iterations().mean())
    return np.array(out), float(np.mean(its[5:])), sim


def test_quadratic_stop_ends_on_one_newton_step():
    """quadratic_stop: a Newton step from a fresh factor, accepted whole, under 100x q's rounding
    floor ends the solve (its next step would be rounding: measured at most 1.3e-7 m after first
    steps up to 3e-4 m).  Float32 double pendulums then take 1.0 iterations a step instead of ~1.35,
    on the same trajectory to float32 rounding (0.6 s); the staged solver stops where the fused one
    does; float64, whose tolerance is far above its rounding, is unchanged; a negative or NaN
    setting is refused."""
    on, its_on, sim = _pendulums()
    off, its_off, _ = _pendulums(quadratic_stop=0.0)
    assert its_on < 1.1 and its_off > its_on + 0.2
    np.testing.assert_allclose(on, off, atol=2e-5)
    staged, its_staged, ref = _pendulums(plan=ag.ExecutionPlan(fused=False))
    np.testing.assert_allclose(staged, on, atol=2e-5)
    assert abs(its_staged - its_on) < 0.02
    f64 = [_pendulums("float64", 30, quadratic_stop=q) for q in (0.0, 100.0)]
    np.testing.assert_array_equal(f64[0][0], f64[1][0])
    for bad in (-1.0, float("nan")):
        with pytest.raises(ValueError, match="quadratic_stop"):
            ag.Simulator(mechanisms.double_pendulum(), quadratic_stop=bad)


@pytest.mark.parametrize("bad", [None, 1, "yes"])
def test_reuse_factor_must_be_a_bool(bad):
    """reuse_factor is True or False (default False); anything else is refused, naming the value."""
    assert ag.Simulator(mechanisms.pendulum()).solver.reuse_factor is False
    with pytest.raises(ValueError, match=f"reuse_factor must be True or False, got {bad!r}"):
        ag.Simulator(mechanisms.pendulum(), reuse_factor=bad)


def test_third_order_guess_only_under_a_steady_control():
    """Newton's initial guess extrapolates a body's velocity to third order where that would have
    guessed its last step better (State.order3) and the world's controls are those of its last two
    steps (State.calm, up to 2): smooth float32 cart-poles at dt 0.01 then take one Newton iteration
    a step.  A control that changes every step keeps calm at 0 (the second-order guess), and a
    reset starts a world with no past (order3 0, q̇ⁿ⁻² = q̇, calm 0 after its first step)."""
    from abd_gym.bench.compare import random_states

    sim = ag.Simulator(mechanisms.cartpole(), num_worlds=4, dt=0.01, integrator="implicit_euler")
    sim.set_joint_state(random_states("cartpole", 4))
    its = []
    for _ in range(40):
        sim.step()
        its.append(sim.newton_iterations().mean())
    assert np.mean(its[10:]) < 1.05
    assert sim.state.calm.numpy().tolist() == [2] * 4 and sim.state.order3.numpy().any()
    rng = np.random.default_rng(1)
    for k in range(3):
        u = np.zeros((4, 1))
        u[:2] = rng.uniform(-5, 5, (2, 1))  # worlds 0 and 1 change their force every step
        sim.set_controls(u)
        sim.step()
        assert sim.state.calm.numpy().tolist() == [0, 0, 2, 2]
    sim.reset(worlds=[2])
    assert not sim.state.order3.numpy()[2].any()
    np.testing.assert_array_equal(sim.state.qd_hist2.numpy()[2], sim.state.qd.numpy()[2])
    sim.step()
    assert sim.state.calm.numpy().tolist() == [1, 1, 0, 2]  # (held once; a world with no past counts from its first step)


@INTEGRATORS
def test_pendulum_dropped_onto_its_limit(integrator):
    """InvertedPendulum-v5's pole dropped from rest at 0.2–1.4 rad onto its ±π/2 hinge limit (the
    cubic E = s e³, s = 64,042 J), 256 worlds, float32, dt 0.01, 1 s: every pole reaches the limit
    and rests there, every step converges within 5 Newton iterations (Newton from a start past
    the bound by e₀ needs ~log₂(e₀/e*) of them: the guess stops at the bound, limit_reach, and
    the line search models the cubic along the step, fused.limit_model.limit_step; measured 3
    with implicit Euler and 5 with BDF2, against 6 and 7 with halving alone), no world ends a step
    with more energy than it started with, and the overrun stays under 0.5 mrad (the seed's cubic
    at the impact's force)."""
    from abd_gym.bench.cases import CASES

    W = 256
    rng = np.random.default_rng(3)
    sim = ag.Simulator(CASES["inverted_pendulum_v5"].scene(), num_worlds=W, dt=0.01, device="cpu",
                       integrator=integrator)  # fmt: skip
    x0 = np.zeros((W, 2))
    x0[:, 1] = rng.uniform(0.2, 1.4, W) * rng.choice([-1.0, 1.0], W)
    sim.set_joint_state(x0, np.zeros((W, 2)))
    e0 = _total_energy(sim)
    worst, gain, overrun = 0, -np.inf, 0.0
    for _ in range(100):
        sim.step()
        assert sim.converged().all() and sim.failed_worlds().size == 0
        worst = max(worst, int(sim.newton_iterations().max()))
        gain = max(gain, float((_total_energy(sim) - e0).max()))
        overrun = max(overrun, float((np.abs(sim.joint_coordinates()[:, 1]) - np.pi / 2).max()))
    assert (np.abs(sim.joint_coordinates()[:, 1]) > np.pi / 2 - 1e-3).all()
    assert np.abs(sim.joint_velocities()[:, 1]).max() < 0.5
    assert worst <= 5
    assert gain <= 0.0
    assert 0.0 < overrun < 5e-4


def _rotor():
    """A 0.4 m, 1 kg arm on a vertical hinge (gravity exerts no torque about it), limited to ±0.5 rad
    (s = 1e3 J), with an effort drive."""
    scene = ag.Scene(gravity=(0, 0, -9.81))
    base = scene.add_body(ag.Box(half_extents=(0.05, 0.05, 0.05)), fixed=True)
    arm = scene.add_body(ag.Box(half_extents=(0.2, 0.02, 0.02)), mass=1.0, position=(0.2, 0, 0))
    hinge = scene.add_revolute_joint(base, arm, anchor=(0, 0, 0), axis=(0, 0, 1))
    scene.add_revolute_limit(hinge, lower=-0.5, upper=0.5, strength=1e3)
    scene.add_drive(hinge, mode="effort", max_effort=10.0)
    return scene


@INTEGRATORS
def test_limit_secant_leaves_a_limit_in_one_newton_step(integrator):
    """The rotor pressed onto its upper limit by torques of 0.5–8 N·m (16 worlds, float32, dt 0.01,
    0.6 s: each strikes, bounces and comes to rest on it), then the torque reversed.  With the
    limits' secant direction (ExecutionPlan.limit_secant, fused.limit_secant) every world leaves
    the limit in its first Newton step, and the step converges in 2 iterations (the step and the
    one that confirms it); with Newton's own direction, which keeps the limit's curvature 6s·r of
    the start and stops about halfway to the bound, in 3 (measured, float64: 4 and 5).  The strikes
    and bounces converge within 3 iterations (BDF2: 5 with Newton's direction).  Both then swing
    freely: 0.05 s after the reversal the arm turns at −τt/I to 1% (both integrators are exact under
    a constant torque; I = m(L²/3 + w²/12) about the hinge; measured 0.6%)."""
    W = 16
    tau = np.linspace(0.5, 8.0, W)[:, None]
    inertia = 1.0 * (0.4**2 / 3 + 0.04**2 / 12)
    first, worst = {}, {}
    for secant in (True, False):
        sim = ag.Simulator(_rotor(), num_worlds=W, dt=0.01, device="cpu", integrator=integrator,
                           plan=ag.ExecutionPlan(limit_secant=secant))  # fmt: skip
        sim.set_joint_state(np.zeros((W, 1)))
        sim.set_controls(tau)
        worst[secant] = 0
        for _ in range(60):
            sim.step()
            assert sim.converged().all()
            worst[secant] = max(worst[secant], int(sim.newton_iterations().max()))
        x_rest = sim.joint_coordinates()[:, 0].copy()
        assert ((x_rest > 0.5) & (x_rest < 0.5 + 1e-3)).all()  # resting on the limit, within its overrun
        assert np.abs(sim.joint_velocities()[:, 0]).max() < 1e-2
        sim.set_controls(-tau)
        sim.step()
        assert sim.converged().all() and (sim.joint_coordinates()[:, 0] < 0.5).all()
        first[secant] = int(sim.newton_iterations().max())
        sim.step(4)
        np.testing.assert_allclose(sim.joint_velocities()[:, 0], -tau[:, 0] / inertia * 0.05, rtol=0.01)
    assert first[True] <= 2 < first[False]
    assert worst[True] <= 3 and worst[True] <= worst[False]


@pytest.mark.parametrize("case", ["inverted_pendulum_v5", "slider_crank"])
def test_limit_secant_solves_the_same_steps(case):
    """The limits' secant direction changes the iterates, not the solutions (float64, BDF2, 16
    worlds, 0.6 s, with and without it): InvertedPendulum-v5's poles dropped onto their hinge limits
    (revolute) agree to 1e-8 rad (measured 4e-10), SliderCrank-v0's piston from the bench's starts
    striking and leaving its slide's limits (prismatic) too (measured 2.5e-9).  With it every step
    converges within 4 Newton iterations (5 and 6 with Newton's direction), 4-5% fewer in all."""
    from abd_gym.bench.cases import CASES

    W = 16
    c = CASES[case]
    if case == "inverted_pendulum_v5":
        rng = np.random.default_rng(3)
        x0 = np.zeros((W, 2))
        x0[:, 1] = rng.uniform(0.2, 1.4, W) * rng.choice([-1.0, 1.0], W)
        v0 = np.zeros((W, 2))
    else:
        x0, v0 = c.states(W, 0)
    runs = {}
    for secant in (True, False):
        sim = ag.Simulator(c.scene(), num_worlds=W, dt=0.01, device="cpu", dtype="float64",
                           plan=ag.ExecutionPlan(limit_secant=secant))  # fmt: skip
        sim.set_joint_state(x0, v0)
        its, worst, xs = 0, 0, []
        for _ in range(60):
            sim.step()
            assert sim.converged().all()
            its += int(sim.newton_iterations().sum())
            worst = max(worst, int(sim.newton_iterations().max()))
            xs.append(sim.joint_coordinates().copy())
        runs[secant] = (np.array(xs), its, worst)
    np.testing.assert_allclose(runs[True][0], runs[False][0], rtol=0, atol=1e-8)
    assert runs[True][2] <= 4 < runs[False][2] and runs[True][1] < runs[False][1]


def test_limit_line_search_lands_where_halving_does():
    """The fused step's line search, which models each limit's cubic along the Newton step
    (limit_step), and the staged step's, which only halves α, solve the same steps: 16
    InvertedPendulum-v5 poles dropped onto their limits, float64, BDF2, 0.6 s, agree to 1e-8 rad
    (measured 1e-10), and the fused solves take fewer Newton iterations in all."""
    from abd_gym.bench.cases import CASES

    W = 16
    rng = np.random.default_rng(3)
    x0 = np.zeros((W, 2))
    x0[:, 1] = rng.uniform(0.2, 1.4, W) * rng.choice([-1.0, 1.0], W)
    runs = {}
    for name, plan in (("fused", None), ("staged", ag.ExecutionPlan(fused=False))):
        sim = ag.Simulator(CASES["inverted_pendulum_v5"].scene(), num_worlds=W, dt=0.01, device="cpu",
                           dtype="float64", plan=plan)  # fmt: skip
        sim.set_joint_state(x0, np.zeros((W, 2)))
        its, xs = 0, []
        for _ in range(60):
            sim.step()
            assert sim.converged().all()
            its += int(sim.newton_iterations().sum())
            xs.append(sim.joint_coordinates().copy())
        runs[name] = (np.array(xs), its)
    assert (np.abs(runs["fused"][0][:, :, 1]).max(axis=0) > np.pi / 2).all()  # every pole struck its limit
    np.testing.assert_allclose(runs["fused"][0], runs["staged"][0], rtol=0, atol=1e-8)
    assert runs["fused"][1] < runs["staged"][1]


# ---------------------------------------------------------------- the hard-case suite

SUITE_WORLDS = 8
SUITE_SECONDS = {"chain20": 2.0}  # shorter than the report's run, to keep the suite quick
# the report's runs at its largest steps, which compare the retry of failed steps with none, are
# tests/test_substeps.py's
RUNS = [(c.name, dt) for c in rb.cases() for dt in c.dts if dt < rb.NO_RETRY_DT]
GRID = [(name, dt, integrator, dtype) for name, dt in RUNS for integrator in rb.INTEGRATORS for dtype in rb.DTYPES]


def _ids(grid):
    return [f"{name}-dt{dt:g}-{integrator}-{dtype}" for name, dt, integrator, dtype in grid]


def suite(names=None, dtypes=rb.DTYPES, exclude=()):
    """Parametrise over the runs of the cases ``names`` (default: all) in ``dtypes``, less the
    (case, dt) pairs in ``exclude``."""
    grid = [g for g in GRID if (names is None or g[0] in names) and g[3] in dtypes and g[:2] not in exclude]
    return pytest.mark.parametrize("name,dt,integrator,dtype", grid, ids=_ids(grid))


@functools.lru_cache(maxsize=None)
def _scene(name):
    return rb.case(name).scene()


@functools.lru_cache(maxsize=None)
def _row(name, dt, integrator, dtype):
    """One run of the report's harness (shared by every assertion on it)."""
    seconds = SUITE_SECONDS.get(name)
    steps = None if seconds is None else int(round(seconds / dt))
    return rb.run_case(rb.case(name), dt, integrator, dtype, worlds=SUITE_WORLDS, steps=steps, scene=_scene(name))


def _describe(r):
    return rb.line(r)


@suite()
def test_no_step_is_committed_unconverged_and_unreported(name, dt, integrator, dtype):
    """Every world-step ends converged, or its world is reported (or the simulator refused the
    setting or the state when given it)."""
    r = _row(name, dt, integrator, dtype)
    assert r["refused"] or r["silent"] == 0, _describe(r)


CONSERVATIVE = [c.name for c in rb.cases() if c.conservative]


@suite(CONSERVATIVE)
def test_no_silent_energy_gain(name, dt, integrator, dtype):
    """In a scene where no force does work, no world that was not reported ends any step with
    more than 5% of its swing energy S = E(0) − min_t V_g(t) above its initial energy (limits
    engaging and releasing included)."""
    r = _row(name, dt, integrator, dtype)
    assert r["refused"] or r["gain_worlds"] == 0, _describe(r)


# The largest joint gap [mm] and limit overshoot (over its bound) each case reaches over the
# suite's runs (8 worlds, every dt, integrator and dtype, CPU), as measured.  The tests allow
# twice that (and never more than the 5 mm goal), so that a case whose worst run gets 3x worse
# fails.  dt 0.03 under a 1000:1 load and absurd rates are left out of the gaps: the 5 mm goal is
# set for the load at dt 0.01, and absurd rates must be refused or reported (below).
WORST_GAP_MM = {"light_under_heavy": 0.0396, "heavy_under_light": 0.0388, "chain20": 0.0270, "spin_into_limit": 0.188,
                "prismatic_slam": 0.00285, "strength_1": 3.11, "strength_100": 0.0307, "strength_10000": 3.06e-4,
                "strength_1e+06": 1.72e-4, "strength_1e+08": 1.13e-4, "large_dt": 0.488, "fourbar": 0.156,
                "slider_crank": 0.0644, "mixed_chain": 0.0645}  # fmt: skip
WORST_OVERSHOOT = {"spin_into_limit": 0.0996, "prismatic_slam": 0.100, "slider_crank": 0.232}
MARGIN = 2.0
GAP_GOAL_MM = 5.0


def test_every_gap_case_has_a_measured_bound():
    assert set(WORST_GAP_MM) == {n for n in rb.CASE_NAMES if n != "absurd_rates"}


@suite(list(WORST_GAP_MM), exclude=[("heavy_under_light", 0.03)])
def test_joint_gaps_stay_near_their_measured_worst(name, dt, integrator, dtype):
    """Joints hold to millimetres in every hard case with default strengths, including a 1000 kg
    link hanging under a 1 kg one at dt 0.01 (the goal: ≤ 5 mm) and strength ratios down to 1;
    each case within twice its measured worst gap."""
    r = _row(name, dt, integrator, dtype)
    assert r["refused"] or r["gap_mm"] <= min(GAP_GOAL_MM, MARGIN * WORST_GAP_MM[name]), _describe(r)


@suite(list(WORST_OVERSHOOT))
def test_limits_hold(name, dt, integrator, dtype):
    """A joint that reaches its limit stops well within the overshoot estimate of docs/design.md
    §3.3 with the world's whole swing energy S arriving there: (S dt²/s)^(1/3) rad for a revolute
    limit, w·(S dt²/s)^(1/3) m for a prismatic one (a link spun at 50 rad/s must not pass through
    ±3.1 rad); each case within twice its measured worst fraction of that estimate."""
    r = _row(name, dt, integrator, dtype)
    assert r["refused"] or r["overshoot_over_bound"] <= MARGIN * WORST_OVERSHOOT[name], _describe(r)


@suite(["light_under_heavy", "heavy_under_light"], dtypes=("float32",))
def test_mass_ratio_1_to_1000_never_fails_in_float32(name, dt, integrator, dtype):
    """A 0.001 kg link under a 1 kg one and 1000 kg under 1 kg, at dt 0.01 and 0.03 in float32:
    no world fails (the goal for dt ≤ 0.03)."""
    r = _row(name, dt, integrator, dtype)
    assert r["refused"] is None and r["reported"] == 0, _describe(r)


@suite([n for n in rb.CASE_NAMES if n.startswith("strength_")])
def test_unworkable_strengths_are_announced(name, dt, integrator, dtype):
    """A strength ratio from 1 to 1e8 either steps every world or is announced when the
    simulator is built (a warning or an error): worlds that fail under a setting that was
    accepted in silence are not allowed."""
    r = _row(name, dt, integrator, dtype)
    assert r["refused"] or r["warnings"] or r["reported"] == 0, _describe(r)


@suite(["absurd_rates"])
def test_absurd_rates_are_refused_or_reported(name, dt, integrator, dtype):
    """Joint rates up to 1e9 rad/s cannot be stepped at dt 0.01 (10^7 rad a step): the state is
    refused, or every world is reported."""
    r = _row(name, dt, integrator, dtype)
    assert r["refused"] or r["reported"] == r["worlds"], _describe(r)


def test_float32_solve_ends_near_the_solution(script):
    """With the default settings, a float32 Newton solve ends within 5e-6 m of the float64 one from
    the same state (5-link chain of 0.1 m, 1 kg links, implicit Euler, 64 worlds × 10 steps from
    their random starts, scripts/solve_error.py; measured 7.3e-7 m at most, the float32 floor
    4·eps·(1 + ‖q‖∞) being ~1e-6 m).  A reused factor (reuse_factor=True) stops short: 7.2e-5 m."""
    (worst, _, _, iterations), = script("solve_error").solve_error("chain5", 64, 10, [(False, 100.0)]).values()
    assert worst < 5e-6
    assert iterations < 2.5
