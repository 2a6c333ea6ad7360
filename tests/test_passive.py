"""Passive joint terms (constitutions.passive): damping and armature on a joint's coordinate.

The reference's derivatives against differences, the Warp term against the reference, closed-form
motion (an exponentially damped spin, a pendulum's period with armature, a slider's constant
acceleration), energy with armature, and the same trajectory on every execution path."""
import math

import numpy as np
import pytest

import abd_gym as ag
from abd_gym.core import angles
from abd_gym.constitutions import passive
from abd_gym.sim.shapes import Box
from abd_gym.solver.terms import joint_terms, term_counts
from abd_gym.core.warp_ops import GRADIENT, HESSIAN

# every subsystem hangs on the fixed base: a link spinning about +z (gravity acts along the axis, so
# only the passive terms act on its angle) with damping and armature, one with damping only, a
# pendulum about +y with armature only, and a block on a slider along +x with armature and a motor
LINK, MASS = 0.5, 1.0
D_SPIN, A_SPIN, D_SPIN0, A_SWING, A_SLIDE, M_SLIDE = 0.1, 0.05, 0.08, 0.05, 0.5, 1.5
SPIN, SPIN0, SWING, SLIDE = 0, 1, 2, 3
# the link's inertia about its end, for a box of LINK × 0.04 × 0.04 m
I_END = MASS * ((LINK**2 + 0.04**2) / 12 + (LINK / 2) ** 2)


def passive_scene():
    scene = ag.Scene()
    base = scene.add_body(Box(half_extents=(0.05, 0.05, 0.05)), fixed=True, name="base")
    for y, name in ((0.0, "spin"), (1.0, "spin0")):
        link = scene.add_body(Box(half_extents=(LINK / 2, 0.02, 0.02)), mass=MASS, position=(LINK / 2, y, 0), name=name)
        scene.add_revolute_joint(base, link, anchor=(0, y, 0), axis=(0, 0, 1), name=name)
    pend = scene.add_body(Box(half_extents=(0.02, 0.02, LINK / 2)), mass=MASS, position=(0, 2.0, -LINK / 2), name="pend")
    scene.add_revolute_joint(base, pend, anchor=(0, 2.0, 0), axis=(0, 1, 0), name="swing")
    block = scene.add_body(Box(half_extents=(0.05, 0.05, 0.05)), mass=M_SLIDE, position=(0, -1.0, 0), name="block")
    slide = scene.add_prismatic_joint(base, block, anchor=(0, -1.0, 0), axis=(1, 0, 0), name="slide")
    scene.add_drive(slide, mode="effort")
    scene.set_joint_passive("spin", damping=D_SPIN, armature=A_SPIN)
    scene.set_joint_passive("spin0", damping=D_SPIN0)
    scene.set_joint_passive("swing", armature=A_SWING)
    scene.set_joint_passive("slide", armature=A_SLIDE)
    return scene


@pytest.fixture(scope="module")
def scene():
    return passive_scene()


def simulator(scene, dtype="float64", integrator="bdf2", plan=None, W=2, dt=0.002, device=None):
    return ag.Simulator(scene, num_worlds=W, dt=dt, dtype=dtype, integrator=integrator, plan=plan, device=device)


# ============================================================================ the reference
def fd(f, x, h=1e-6):
    """Central differences of f at x (1-D)."""
    out = []
    for k in range(len(x)):
        e = np.zeros_like(x)
        e[k] = h
        out.append((np.asarray(f(x + e)) - np.asarray(f(x - e))) / (2 * h))
    return np.array(out).T


def test_reference_is_the_formula_and_its_derivatives():
    """E = a/(2h²)(x − x̂ − h v̂)² + d/(2h)(x − x̂)², E′ and E″ against differences; E′ is the armature's
    a·(ẋ − v̂)/h plus the damper's d·ẋ at the step's rate ẋ = (x − x̂)/h."""
    h, xa, va = 2e-3 / 1.5, 0.3, -1.7
    for a, d in ((1.0, 0.0), (0.0, 1.0), (0.3, 0.05)):
        for x in (xa - 0.01, xa, xa + 0.004):
            e, de, dde = passive.passive_np(x, xa, va, a, d, h)
            rate = (x - xa) / h
            assert e == pytest.approx(a / (2 * h * h) * (x - xa - h * va) ** 2 + d / (2 * h) * (x - xa) ** 2, rel=1e-14)
            assert de == pytest.approx(a * (rate - va) / h + d * rate, rel=1e-12, abs=1e-9)
            assert dde == a / h**2 + d / h
            f = lambda z: passive.passive_np(z[0], xa, va, a, d, h)  # noqa: E731
            assert de == pytest.approx(fd(lambda z: [f(z)[0]], np.array([x]), 1e-7)[0, 0], rel=1e-6, abs=1e-6)
            assert dde == pytest.approx(fd(lambda z: [f(z)[1]], np.array([x]), 1e-7)[0, 0], rel=1e-7)


def _pair(q, j, m):
    return np.concatenate([q[m.body_a.numpy()[j]], q[m.body_b.numpy()[j]]])


def _frame(m, name, w, j):
    return getattr(m, name).numpy()[w, j].astype(np.float64)


def reference_in_q(m, w, j, qp, qp_prev, unwrapped, x_anchor, v_anchor, a, d, h):
    """ĥ²·(E, ∇E (24,), ∇²E (24, 24) exact, and the solver's E″∇x∇xᵀ) of joint j's passive term at
    the body pair qp (24,), float64."""
    if m.joint_kind_np[j] == 0:
        fr = tuple(_frame(m, n, w, j) for n in ("n_a", "b_a", "n_b", "b_b"))
        cs, cs_prev = (tuple(v[0] for v in angles.cos_sin_np(p, *fr)) for p in (qp, qp_prev))
        x = unwrapped + angles.delta_theta_np(cs, cs_prev)
        _, gx, Hx = angles.revolute_angle_np(qp, qp_prev, qp_prev, fr)
    else:
        x, gx, Hx = angles.prismatic_displacement_np(qp, *(_frame(m, n, w, j) for n in ("c_a", "c_b", "t_a")))
    e, de, dde = passive.passive_np(x, x_anchor, v_anchor, a, d, h)
    h2 = h * h
    return h2 * e, h2 * de * gx, h2 * (dde * np.outer(gx, gx) + de * Hx), h2 * dde * np.outer(gx, gx)


def test_reference_in_q_against_differences(scene):
    """The term in q: its gradient E′∇x and exact Hessian E″∇x∇xᵀ + E′∇²x against differences, for a
    hinge and a slider at a perturbed pose."""
    sim = simulator(scene, W=1)
    m = sim.model
    rng = np.random.default_rng(4)
    sim.set_joint_state([[0.4, -0.2, 0.3, 0.1]], [[1.0, 0.5, -2.0, 0.7]])
    q0 = sim.body_q()[0]
    for j in (SPIN, SLIDE):
        qp0 = _pair(q0, j, m)
        qp = qp0 + np.concatenate([np.zeros(12), rng.normal(0, 1e-2, 12)])  # the base is fixed

        def energy(z):
            return reference_in_q(m, 0, j, z, qp0, 0.3, 0.31, -0.8, 0.7, 0.2, 0.004)

        e, g, H, _ = energy(qp)
        assert np.abs(g[12:]).max() > 1e-4
        np.testing.assert_allclose(g, fd(lambda z: [energy(z)[0]], qp)[0], rtol=1e-6, atol=1e-9 * np.abs(g).max())
        np.testing.assert_allclose(H, fd(lambda z: energy(z)[1], qp), rtol=1e-5, atol=1e-7 * np.abs(H).max())


# ============================================================================ Warp against the reference
def _open(sim, steps):
    """``steps`` steps (world 1 from a different state), then the next step opened (the prediction,
    the anchors) as the staged step opens it, its q moved 1e-3 off Newton's initial guess."""
    sim.set_joint_state([[0.4, -0.2, 0.3, 0.1], [2.5, 0.1, -0.4, -0.2]], [[1.0, 0.5, -2.0, 0.7], [-3.0, 2.0, 1.0, -1.0]])
    sim.set_controls([[1.0], [-2.0]])
    rates = []
    for _ in range(steps):
        sim.step()
        rates.append(sim.joint_velocities())
    sim.solver.open_step(sim.state)
    q = sim.state.q.numpy()
    q[:, 1:] += np.random.default_rng(5).normal(0, 1e-3, q[:, 1:].shape)  # off the solution, off rigid
    sim.state.q.assign(q)
    return rates


@pytest.mark.parametrize("dtype, rtol", [("float64", 1e-10), ("float32", 2e-4)])
def test_warp_term_matches_the_reference(scene, dtype, rtol):
    """The staged kernel's energy, gradient and Hessian E″∇x∇xᵀ (E′∇²x dropped, as for drives) at a
    BDF2 step's initial guess against the reference, from the step's anchors; v̂ = (4ẋⁿ − ẋⁿ⁻¹)/3
    from the last two steps' rates."""
    sim = simulator(scene, dtype=dtype, plan=ag.ExecutionPlan(fused=False))
    rates = _open(sim, 3)
    st, m, s = sim.state, sim.model, sim.solver
    h = s.h_step.numpy().astype(np.float64)
    assert h == pytest.approx(2 * sim.dt / 3)
    v_anchor = st.v_anchor.numpy().astype(np.float64)[:, : m.num_joints]
    np.testing.assert_allclose(v_anchor, rates[-1] + (rates[-1] - rates[-2]) / 3, rtol=1e-5, atol=1e-6)
    s.E.zero_()
    s.g.zero_()
    s.H.zero_()
    passive.CONSTITUTION.launch(m, st, s, st.q, s.E, s.g, s.H, s.all_active, HESSIAN, s.cols)
    E = s.E.numpy()[:, s.cols["passive"]].astype(np.float64)
    g, H = s.gradient().astype(np.float64), s.hessian().astype(np.float64)
    q, q_prev = (a.numpy().astype(np.float64) for a in (st.q, st.q_prev))
    unwrapped, x_anchor = (a.numpy().astype(np.float64) for a in (st.unwrapped, st.x_anchor))
    dof = m.dof.numpy()
    for w in range(2):
        e_ref, g_ref, H_ref = 0.0, np.zeros(m.num_dofs), np.zeros((m.num_dofs, m.num_dofs))
        for k, j in enumerate(m.passive_joint.numpy()[: m.num_passive]):
            a, d = (getattr(m, f"passive_{n}").numpy()[w, k] for n in ("armature", "damping"))
            e, gq, _, Hs = reference_in_q(m, w, j, _pair(q[w], j, m), _pair(q_prev[w], j, m), unwrapped[w, j],
                                          x_anchor[w, j], v_anchor[w, j], a, d, h[w])  # fmt: skip
            o = dof[m.body_b.numpy()[j]]  # every joint's body_a is the fixed base
            e_ref += e
            g_ref[o : o + 12] += gq[12:]
            H_ref[o : o + 12, o : o + 12] += Hs[12:, 12:]
        assert np.abs(g_ref).max() > 1e-5  # the term pulls
        assert E[w] == pytest.approx(e_ref, rel=rtol, abs=1e-12)
        np.testing.assert_allclose(g[w], g_ref, rtol=rtol, atol=rtol * np.abs(g_ref).max())
        np.testing.assert_allclose(H[w], H_ref, rtol=rtol, atol=rtol * np.abs(H_ref).max())


def _fused_matches_staged(scene, plan):
    """The fused assembly (the passive terms folded into their joints' terms) at a step's initial
    guess against the staged kernels' (float64; on the CPU, as test_constitutions checks the fused
    assembly: gradient() and hessian() read the staged scratch, whose rows follow the plan's threads
    on CUDA)."""
    sim = simulator(scene, plan=plan, device="cpu")
    _open(sim, 3)
    s = sim.solver
    s.E.zero_()
    s.g.zero_()
    s.H.zero_()
    s.assemble(sim.state, sim.state.q, s.E, s.all_active, HESSIAN)
    E, g, H = s.E.numpy().sum(axis=1), s.gradient(), s.hessian()
    for derivs in (HESSIAN, GRADIENT):
        Ef, gf, Hf = s.fused_system(sim.state, derivs)
        np.testing.assert_allclose(Ef, E, rtol=1e-12)
        np.testing.assert_allclose(gf, g, rtol=1e-11, atol=1e-11 * np.abs(g).max())
        if derivs == HESSIAN:
            np.testing.assert_allclose(Hf, np.tril(H), rtol=1e-11, atol=1e-11 * np.abs(H).max())


def test_fused_assembly_folds_the_passive_terms(scene):
    """Every passive term rides on its joint's term (none of its own), alone on a hinge (an angle
    term) and beside a drive on a slider; the fused assembly (one thread per world, and lanes) is
    the staged one."""
    sim = simulator(scene)
    jt = joint_terms(sim.model)
    assert term_counts(sim.model, jt)["passive"] == 0
    assert set(jt["folds"]["passive", "revolute"].tolist()) == {0, 1, 2}
    assert jt["folds"]["passive", "prismatic"].tolist() == [3] and jt["folds"]["drive", "prismatic"].tolist() == [0]
    _fused_matches_staged(scene, ag.ExecutionPlan(scratch="global", threads=2, one_launch=False))

    import warp as wp

    before = wp.config.enable_cpu_blocks
    wp.config.enable_cpu_blocks = True
    try:
        # (the lanes' step in one launch, as test_every_execution_path_gives_the_same_trajectory
        # builds it: the assembly is the same function either way)
        _fused_matches_staged(scene, ag.ExecutionPlan(scratch="lanes", block_dim=8))
    finally:
        wp.config.enable_cpu_blocks = before


# ============================================================================ closed forms
def _run(sim, x0, v0, seconds, control=0.0):
    sim.set_joint_state(x0, v0)
    sim.set_controls(np.full((sim.num_worlds, 1), control))
    xs, vs = [], []
    for _ in range(round(seconds / sim.dt)):
        sim.step()
        xs.append(sim.joint_coordinates())
        vs.append(sim.joint_velocities())
    assert (sim.world_status() == 0).all()
    return np.array(xs), np.array(vs)


# integrator -> relative tolerance at dt 0.002 over 1 s for the damped spin: implicit Euler's
# per-step factor 1/(1 + hλ) against exp(−hλ) errs by λ²h·t/2 ≈ 1e-3 (λ = d/(I + a) ≤ 1 /s), and
# its own dissipation of the link's circular motion takes ω²h·t/2 ≈ 9e-3 of ω at ω0 = 3 rad/s;
# BDF2's error is O(h²) (its first step implicit Euler's O(h²) one)
DECAY_TOL = {"implicit_euler": 1.5e-2, "bdf2": 3e-5}


@pytest.mark.parametrize("integrator", ["implicit_euler", "bdf2"])
@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_damped_spin_decays_exponentially(scene, integrator, dtype):
    """A free spin with damping d: ω(t) = ω0·exp(−d t/I), with armature a: exp(−d t/(I + a)), and the
    angle ω0·τ·(1 − exp(−t/τ)), τ = (I + a)/d; the pendulum and the slider stay at rest."""
    sim = simulator(scene, dtype=dtype, integrator=integrator)
    w0 = np.array([[2.0, -1.5, 0.0, 0.0], [-0.5, 3.0, 0.0, 0.0]])
    xs, vs = _run(sim, np.zeros((2, 4)), w0, 1.0)
    t = sim.dt * np.arange(1, len(xs) + 1)
    # float32: q's rounding, ~1e-7 a step, adds up over 500 steps (measured: 8e-4 of ω under BDF2)
    tol = DECAY_TOL[integrator] if dtype == "float64" else max(DECAY_TOL[integrator], 2e-3)
    for j, (d, a) in ((SPIN, (D_SPIN, A_SPIN)), (SPIN0, (D_SPIN0, 0.0))):
        tau = (I_END + a) / d
        for w in range(2):
            want_x = w0[w, j] * tau * (1 - np.exp(-t / tau))
            # the rate after step n is the step's (BDF2: its own derivative at tⁿ; implicit Euler: the
            # mean over the step, half a step behind); BDF2's first steps carry its implicit Euler
            # start's half-step lag, which its rate sheds in a few steps
            t_rate = t - (sim.dt / 2 if integrator == "implicit_euler" else 0.0)
            np.testing.assert_allclose(vs[5:, w, j], w0[w, j] * np.exp(-t_rate[5:] / tau), rtol=tol,
                                       atol=tol * abs(w0[w, j]))  # fmt: skip
            np.testing.assert_allclose(xs[:, w, j], want_x, rtol=tol, atol=tol * abs(want_x).max())
    assert np.abs(xs[:, :, SWING:]).max() < 1e-6


@pytest.mark.parametrize("integrator", ["implicit_euler", "bdf2"])
def test_pendulum_period_with_armature(scene, integrator):
    """Small swings of the pendulum with armature a: period 2π·sqrt((I_pivot + a)/(m g l)), from the
    zero crossings of 2.5 periods.  Both integrators err by O((ωh)²) ≈ 7e-5 in the period (implicit
    Euler's O(ωh) error is in the amplitude) and a 0.05 rad swing lengthens it by θ0²/16 ≈ 1.6e-4:
    tolerance 1e-3."""
    sim = simulator(scene, integrator=integrator)
    T = 2 * math.pi * math.sqrt((I_END + A_SWING) / (MASS * 9.81 * LINK / 2))
    x0 = np.zeros((2, 4))
    x0[:, SWING] = [0.05, -0.03]
    xs, _ = _run(sim, x0, np.zeros((2, 4)), 2.5 * T)
    t = sim.dt * np.arange(1, len(xs) + 1)
    for w in range(2):
        x = xs[:, w, SWING]
        k = np.flatnonzero(np.sign(x[1:]) != np.sign(x[:-1]))
        crossings = t[k] + sim.dt * x[k] / (x[k] - x[k + 1])  # linear interpolation
        assert len(crossings) >= 4
        period = 2 * np.mean(np.diff(crossings))
        assert period == pytest.approx(T, rel=1e-3)
        # without the armature the period would be 13% shorter
        assert abs(period - 2 * math.pi * math.sqrt(I_END / (MASS * 9.81 * LINK / 2))) > 0.1 * T


@pytest.mark.parametrize("integrator", ["implicit_euler", "bdf2"])
def test_slider_with_armature_accelerates_at_F_over_m_plus_a(scene, integrator):
    """A block of mass m with armature a pushed by a constant motor force F from rest: x(t) = F t²/(2(m
    + a)).  Implicit Euler's discrete solution is xₙ = (F/(m + a))·h²·n(n + 1)/2 exactly (to the
    Newton tolerance, 1e-5 m/s·h a step: 1e-4 relative); BDF2 is exact for constant acceleration
    after its first (implicit Euler) step, whose O(h²) error stays as an offset (2h²/t² = 2e-4 of x
    at t = 0.2 s): tolerance 1e-3 from there."""
    sim = simulator(scene, integrator=integrator)
    F = 2.0
    xs, _ = _run(sim, np.zeros((2, 4)), np.zeros((2, 4)), 1.0, control=F)
    n = np.arange(1, len(xs) + 1)
    t = sim.dt * n
    acc = F / (M_SLIDE + A_SLIDE)
    for w in range(2):
        if integrator == "implicit_euler":
            np.testing.assert_allclose(xs[:, w, SLIDE], acc * sim.dt**2 * n * (n + 1) / 2, rtol=1e-4)
        else:
            np.testing.assert_allclose(xs[100:, w, SLIDE], acc * t[100:] ** 2 / 2, rtol=1e-3)
        # the armature is no mass: without it the block would be 1.33x as far
        assert xs[-1, w, SLIDE] < 0.8 * F / M_SLIDE / 2


# ============================================================================ energy
def test_kinetic_energy_includes_the_armature(scene):
    """energies()["kinetic"] = Σ ½(I + a)ω² + ½(m + a)v² for the joints' rates just set."""
    sim = simulator(scene)
    v = np.array([[1.0, -2.0, 0.5, 0.3], [0.0, 0.0, 0.0, -1.0]])
    sim.set_joint_state(np.zeros((2, 4)), v)
    want = 0.5 * ((I_END + A_SPIN) * v[:, SPIN] ** 2 + I_END * v[:, SPIN0] ** 2 + (I_END + A_SWING) * v[:, SWING] ** 2
                  + (M_SLIDE + A_SLIDE) * v[:, SLIDE] ** 2)  # fmt: skip
    np.testing.assert_allclose(sim.energies()["kinetic"], want, rtol=1e-9)


@pytest.mark.parametrize("integrator, loss", [("implicit_euler", 0.1), ("bdf2", 2e-3)])
def test_armature_keeps_the_energy(scene, integrator, loss):
    """The pendulum with armature and no damping (the other joints at rest): the total energy,
    armature's ½aẋ² included, never grows; implicit Euler loses ω²h·t ≈ 5% of it over 1.5 s (ω² =
    mgl/(I + a) ≈ 18 /s²), BDF2 a small fraction of that."""
    sim = simulator(scene, integrator=integrator)
    x0 = np.zeros((2, 4))
    x0[:, SWING] = [0.5, 1.0]
    sim.set_joint_state(x0, np.zeros((2, 4)))
    sim.set_controls(np.zeros((2, 1)))
    e0 = sum(sim.energies().values())
    energy = []
    for _ in range(750):
        sim.step()
        energy.append(sum(sim.energies().values()))
    energy = np.array(energy)
    scale = MASS * 9.81 * LINK / 2 * (1 - np.cos(x0[:, SWING]))  # the swing's energy above its rest
    assert (energy <= e0 + 1e-6 * scale).all()
    assert (e0 - energy[-1] < loss * scale).all()
    assert (e0 - energy[-1] > 0).all()


# ============================================================================ execution paths
def _trajectory(scene, plan):
    """A float64 BDF2 run through a state set, a reset and a body-state set, on ``plan``."""
    sim = simulator(scene, plan=plan)
    rng = np.random.default_rng(7)
    sim.set_joint_state(rng.uniform(-0.5, 0.5, (2, 4)), rng.uniform(-2, 2, (2, 4)))
    out = []
    for i in range(60):
        sim.set_controls(rng.uniform(-3, 3, (2, 1)))
        if i == 20:
            sim.reset(worlds=[1])
        if i == 40:
            q = sim.body_q()[0]
            p, R = q[:, :3], q[:, 3:].reshape(-1, 3, 3)
            sim.set_body_states(p[None], R[None], linear_velocities=np.zeros((1, len(p), 3)), worlds=[0])
        sim.step()
        out.append(np.concatenate([sim.body_q().reshape(2, -1), sim.joint_coordinates(), sim.joint_velocities()], 1))
    return np.array(out)


def test_every_execution_path_gives_the_same_trajectory(scene):
    """The staged kernels, the fused thread per world (opened by the staged kernels or in its one
    launch) and the lane-split kernel step a passive scene alike."""
    import warp as wp

    ref = _trajectory(scene, ag.ExecutionPlan(fused=False))
    assert np.abs(ref[:, 1]).max() > 0
    for plan in (dict(scratch="global", one_launch=False), dict(scratch="global", one_launch=True)):
        np.testing.assert_allclose(_trajectory(scene, ag.ExecutionPlan(**plan)), ref, atol=1e-9, err_msg=str(plan))
    # cooperative CPU blocks for the lanes only (a thread per world's kernels are then the ones
    # test_fused_assembly_folds_the_passive_terms builds)
    before = wp.config.enable_cpu_blocks
    wp.config.enable_cpu_blocks = True
    try:
        plan = dict(scratch="lanes", block_dim=8)
        np.testing.assert_allclose(_trajectory(scene, ag.ExecutionPlan(**plan)), ref, atol=1e-9, err_msg=str(plan))
    finally:
        wp.config.enable_cpu_blocks = before


def test_passive_terms_take_no_control_column(scene):
    """Passive terms are no drives: the controls are the scene's drives' (one here), and a width
    counting the passive terms is refused."""
    sim = simulator(scene)
    assert sim.model.num_drives == 1 and sim.model.num_passive == 4
    sim.set_controls(np.ones((2, 1)))
    with pytest.raises(ValueError, match=r"controls must have shape \(2, 1\)"):
        sim.set_controls(np.ones((2, 5)))


def test_no_passive_terms_compile_nothing():
    """A scene without damping or armature (or with both set back to 0) has no passive term."""
    scene = passive_scene()
    for j in range(4):
        scene.set_joint_passive(j)
    sim = simulator(scene, W=1)
    assert sim.model.num_passive == 0 and "passive" not in sim.solver.cols
