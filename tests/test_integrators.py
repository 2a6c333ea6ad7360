"""BDF2 (second order, in incremental-potential form) against implicit Euler: less numerical
damping and a smaller trajectory error, stable on a hard case, and identical fused and staged."""
import math

import numpy as np
import pytest

import abd_gym as ag
from abd_gym.sim import mechanisms


def _swing(integrator, dt=0.01, steps=300, fused=True):
    sim = ag.Simulator(mechanisms.pendulum(), num_worlds=1, dt=dt, dtype="float64", integrator=integrator,
                       plan=ag.ExecutionPlan(fused=fused))  # fmt: skip
    sim.set_joint_state([[0.3]])
    e0 = sum(sim.energies().values())[0]
    xs = []
    for _ in range(steps):
        sim.step()
        xs.append(sim.joint_coordinates()[0, 0])
    return np.array(xs), sum(sim.energies().values())[0] - e0


def test_bdf2_damps_far_less_than_implicit_euler():
    """3 s of a pendulum at dt = 0.01: implicit Euler loses a visible share of its swing energy;
    BDF2 loses at least 20x less, and both keep the period within 0.3% of the closed form
    (with the finite-amplitude factor 1 + θ0²/16 + 11θ0⁴/3072 for θ0 = 0.3 rad)."""
    loss = {}
    for integrator in ("implicit_euler", "bdf2"):
        xs, drift = _swing(integrator)
        assert drift < 0  # neither creates energy
        loss[integrator] = -drift
        t = np.arange(1, len(xs) + 1) * 0.01
        k = np.flatnonzero((xs[:-1] > 0) & (xs[1:] <= 0))
        period = np.diff(t[k] + 0.01 * xs[k] / (xs[k] - xs[k + 1])).mean()
        inertia = 1.0 / 3 * (0.02**2 + 0.25**2) + 0.25**2
        closed = 2 * math.pi * math.sqrt(inertia / (9.81 * 0.25)) * (1 + 0.3**2 / 16 + 11 * 0.3**4 / 3072)
        assert abs(period - closed) / closed < 3e-3, (integrator, period, closed)
    assert loss["bdf2"] * 20 < loss["implicit_euler"]


def test_bdf2_fused_matches_staged_and_is_stable_at_large_steps():
    a, _ = _swing("bdf2", steps=50, fused=True)
    b, _ = _swing("bdf2", steps=50, fused=False)
    np.testing.assert_allclose(a, b, atol=1e-10)
    sim = ag.Simulator(mechanisms.double_pendulum(), num_worlds=1, dt=0.05, integrator="bdf2")
    sim.set_joint_state([[2.0, 1.0]])
    e0 = sum(sim.energies().values())[0]
    for _ in range(60):
        sim.step()
        assert sum(sim.energies().values())[0] <= e0 + 1e-4 * abs(e0)
    assert sim.joint_violation()[0] < 1e-3 and sim.converged().all()


def _falling_box(dt, integrator="bdf2"):
    scene = ag.Scene(gravity=(0.0, 0.0, -9.81))
    scene.add_body(ag.Box(half_extents=(0.05, 0.05, 0.05)), fixed=True)
    scene.add_body(mechanisms.link_shape(0.5), mass=1.0, position=(0.0, 0.0, -0.25))
    return ag.Simulator(scene, num_worlds=1, dt=dt, dtype="float64", tol=1e-12, integrator=integrator)


def test_bdf2_free_fall_keeps_second_order_from_a_set_state():
    """A box falling from rest: BDF2 (first step implicit Euler, as after any set state) stays within
    g·h² of z0 − g t²/2 for 100 steps, where a BDF2 first step from an invented constant-velocity
    past would lag by g·h·t/2 (first order, 50x more here); its affine block stays the identity to
    float64 rounding (a literal 1.0/3.0 in a kernel is a float32 quotient: 3e-8 a step).  Setting
    a state again makes the next step an implicit Euler one again (Δz = g h², not (2/3)² g h²)."""
    h, g = 0.01, 9.81
    sim = _falling_box(h)
    z0 = sim.body_q()[0, 1, 2]
    for n in range(1, 101):
        sim.step()
        assert abs(sim.body_q()[0, 1, 2] - (z0 - 0.5 * g * (n * h) ** 2)) < g * h * h, n
    q = sim.state.q.numpy()[0, 1]
    np.testing.assert_allclose(q[3:], np.eye(3).ravel(), rtol=0, atol=1e-14)
    sim.set_body_states(positions=[[[0, 0, 0], [0, 0, -0.25]]], rotations=[[np.eye(3)] * 2])
    sim.step()
    assert sim.body_q()[0, 1, 2] == pytest.approx(-0.25 - g * h * h, abs=1e-13)


def test_bdf2_is_second_order_and_implicit_euler_first():
    """Pendulum from 0.5 rad, 0.5 s, float64: halving dt divides BDF2's angle error by about 4 and
    implicit Euler's by about 2 (each against its own run at dt/8 of the finest)."""
    def angle(integrator, dt):
        sim = ag.Simulator(mechanisms.pendulum(), num_worlds=1, dt=dt, dtype="float64", tol=1e-10,
                           integrator=integrator)  # fmt: skip
        sim.set_joint_state([[0.5]])
        sim.step(int(round(0.5 / dt)))
        return sim.joint_coordinates()[0, 0]

    for integrator, lo, hi in (("bdf2", 3.3, 5.0), ("implicit_euler", 1.7, 2.4)):
        ref = angle(integrator, 0.00125)
        e1, e2 = (abs(angle(integrator, dt) - ref) for dt in (0.02, 0.01))
        assert lo < e1 / e2 < hi, (integrator, e1, e2)


def _guess_error(integrator, dt, t_end=0.2):
    """max |q⁽⁰⁾ − q| of a swinging double pendulum's step at t_end (float64, staged): Newton's
    initial guess against the step's converged solution."""
    sim = ag.Simulator(mechanisms.double_pendulum(), num_worlds=1, dt=dt, dtype="float64", integrator=integrator,
                       plan=ag.ExecutionPlan(fused=False, use_graph=False))  # fmt: skip
    sim.set_joint_state([[0.6, -0.4]], [[2.0, 1.0]])
    sim.step(round(t_end / dt))
    solver, guess = sim.solver, {}
    open_step = solver.open_step

    def record(state):
        open_step(state)
        guess["q"] = state.q.numpy().copy()

    solver.open_step = record
    sim.step()
    return np.abs(guess["q"] - sim.state.q.numpy()).max()


@pytest.mark.parametrize("integrator", ["bdf2", "implicit_euler"])
def test_initial_guess_is_third_order(integrator):
    """Newton's initial guess extrapolates the motion exactly to second order, whichever velocity
    the integrator keeps (BDF2's slope at tⁿ, implicit Euler's mean slope of the last step): its
    distance to the step's solution falls at least ~8x when dt halves (a guess exact only to first
    order, off by ~h²q̈/2 as q̃ is, 4x) and at dt = 0.005 s stays under 2e-5 m, a tenth of h²q̈/2
    for the links' ~10 m/s² accelerations."""
    e = [_guess_error(integrator, dt) for dt in (0.01, 0.005)]
    assert e[0] / e[1] > 6.0, e
    assert e[1] < 2e-5, e
