#!/usr/bin/env python3
"""Does a constant, pre-factored system (M-ABD's co-rotational idea) pay for the seeds' penalty
joints?  A float64 study of the step's linear algebra against today's fresh-factor Newton.

The step is the library's own: a staged ``Simulator`` (``plan={"fused": False}``, float64, its
integrator BDF2 by default) opens each step (prediction, initial guess, the joints' references),
assembles the incremental potential's E, g and H at any q (``Solver.assemble``) and closes the step.
Only the direction of each iteration is this script's, so every method minimises the same E and
stops at the same test (‖Δq‖∞ < h·tol after an accepted step); the line search is Armijo's
(α halved), on the library's trial path (``affine_body.retract_np``).

Methods (``--methods``):

- ``newton``: Δq = −H(q)⁻¹g, a fresh factor every iteration (the driver's check: it matches the
  library's staged step to the tolerance);
- ``rest``: one constant factor of the Hessian at the scene's pose (world frame, no limits), shared
  by every world of the mechanism; active limits added through it as rank-one changes (Woodbury);
- ``corot``: one constant factor in each body's co-rotated frame, B = Tᵣ H(q_ref) Tᵣᵀ with
  T_b = diag(R_b, R_b ⊗ I₃) (R_b the polar rotation of A_b; dA = R dF, dp = R dp′): the direction
  is −T(q) B⁻¹ T(q)ᵀ g, limits as rank-one changes.  In these coordinates the mass matrix and the
  orthogonality Hessian at a rotation are constant (tests/test_co_rotation.py), and so are a
  joint's diagonal blocks; a joint's coupling of its two bodies holds their relative rotation and
  is not;
- ``step``: one fresh factor at the step's first iterate, reused for its later iterations
  (simplified Newton), limits as rank-one changes;
- ``corot_pcg``: inexact Newton, H(q)Δq = −g by conjugate gradients preconditioned by ``corot``
  (relative residual ``--cg-tol``), no factorisation;
- ``dual``: M-ABD's structure with the seeds' penalties: P = T(q) D T(q)ᵀ + the joints' and
  coordinate terms' exact Hessians at q, D the bodies' constant co-rotated blocks (inertia and
  orthogonality at a rotation, one factor a body for every world of the mechanism).  By Woodbury,
  P⁻¹ = D'⁻¹ − D'⁻¹Lᵀ(K⁻¹ + LD'⁻¹Lᵀ)⁻¹LD'⁻¹ with L the joints' rows: a dual system of the joints'
  rows, factored each iteration (``Work`` counts it so); the study solves P densely, the same
  direction.  It drops only the orthogonality's strain terms, so it converges linearly.

"Limits" above are every coordinate term with curvature (limits, passive terms, position drives):
E″∇x∇xᵀ, rank one each.

Against the library itself (fused, default plan, float64): ``lib_newton`` (defaults) and
``lib_reuse`` (``reuse_factor=True``); the references are the library's too, at tol ``--ref-tol``
(same dt, and dt/10).  ``dual_tight`` is ``dual`` at tol/100.

Per method and case: Newton iterations a step (mean, max), factorisations a step, CG iterations
a step, the step where a world first did not converge (the run stops there), the largest difference
of a step's solution from the same step solved tightly by Newton (``step_error``, driver methods),
the largest joint-coordinate error over the run [rad or m] against the tight reference (same dt)
and against one of dt/10 (both over the worlds whose references took every step whole: a retry's
substeps change a reference's path), the largest joint gap [m], the energy change over the run
[J], and the work a step in floating-point operations (``Work``: exact counts for the envelope
factors and solves, estimates for assembly, ``ASSEMBLY``).

    python scripts/constant_factor_study.py --out results/constant_factor_study_cpu.json
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import sys
import time
import warnings

# the systems are small (≤ 360 unknowns) and solved one world at a time: BLAS threads only contend
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402
import scipy.linalg as sla  # noqa: E402
import warp as wp  # noqa: E402

import abd_gym as ag  # noqa: E402
from abd_gym.bench.cases import CASES  # noqa: E402
from abd_gym.constitutions import affine_body  # noqa: E402
from abd_gym.core.warp_ops import GRADIENT, HESSIAN  # noqa: E402

CASE_NAMES = ("alt_chain5", "alt_chain10", "alt_chain20", "alt_chain30", "pusher_arm", "double_pendulum", "fourbar")
METHODS = ("newton", "rest", "corot", "step", "corot_pcg", "dual")
LIBRARY = ("lib_newton", "lib_reuse")


# ----------------------------------------------------------------------------- co-rotation
def polar_rotation(A: np.ndarray) -> np.ndarray:
    """The rotation R of A = R S (S symmetric positive definite): U Vᵀ of A's SVD."""
    U, _, Vt = np.linalg.svd(A)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        U[:, -1] *= -1
        R = U @ Vt
    return R


def body_frame(R: np.ndarray) -> np.ndarray:
    """T_b (12 × 12, orthogonal) of one body: q's increment (dp, rows of dA) from the co-rotated one
    (dp′, rows of dF) with dp = R dp′ and dA = R dF, i.e. diag(R, R ⊗ I₃) on (p, a₁, a₂, a₃)."""
    T = np.zeros((12, 12))
    T[:3, :3] = R
    T[3:, 3:] = np.kron(R, np.eye(3))
    return T


# ----------------------------------------------------------------------------- flop model
def envelope(H: np.ndarray) -> np.ndarray:
    """Each row's first column with a non-zero entry (an envelope: Cholesky fills nothing left of
    it); the dual system's, from its block pattern."""
    nz = np.abs(H) > 0
    n = len(H)
    first = np.array([int(np.argmax(nz[i, : i + 1])) for i in range(n)])
    return first


def factor_flops(first: np.ndarray) -> int:
    """Floating-point operations of the envelope Cholesky: entry (i, j) of L is a dot product over
    columns max(f_i, f_j) .. j−1 (2 flops each) and a division (a square root on the diagonal)."""
    total = 0
    for i in range(len(first)):
        for j in range(first[i], i + 1):
            total += 2 * (j - max(first[i], first[j])) + 1
    return int(total)


def solve_flops(first: np.ndarray) -> int:
    """A forward and a back substitution through the envelope factor: 2 flops an entry each way."""
    return int(4 * sum(i - f + 1 for i, f in enumerate(first)))


def matvec_flops(H: np.ndarray) -> int:
    """H v with H's non-zeros (symmetric, stored whole): 2 flops a non-zero."""
    return int(2 * np.count_nonzero(np.abs(H) > 0))


# Assembly estimates a term (flops): the energy, gradient and Hessian kernels' arithmetic, counted
# from their formulas (12-entry body terms, 24-entry joint terms), plus one add an entry written.
# A body: inertia ½dᵀMd and ‖AAᵀ − I‖² (AAᵀ 45 flops); its gradient Md and 4κv R A; its Hessian
# AᵀA, nine outer products, R⁺ in closed form and 144 entries.  A point (3 penalty rows, one end of
# a joint's gap): the gap from both bodies, K Jᵀ C, and K JᵀJ's 24 × 24 entries.  A coordinate term
# (limit, drive, passive): the angle from the frame vectors, ∇x (24 entries), E″∇x∇xᵀ (576).
# ``polar``: a body's polar rotation; ``rotate``: T and Tᵀ on its 12 entries (4 3 × 3 products each).
ASSEMBLY = {
    "body_energy": 130, "body_gradient": 160, "body_hessian": 500,
    "point_energy": 55, "point_gradient": 110, "point_hessian": 600,
    "coord_energy": 120, "coord_gradient": 150, "coord_hessian": 600,
    "polar": 200, "rotate": 2 * 4 * 15,
}  # fmt: skip


# ----------------------------------------------------------------------------- driver
class Driver:
    """The library's staged step with this script's direction (see the module docstring)."""

    def __init__(self, case, worlds, dt, tol, max_iterations=100, cg_tol=1e-3, check_step=True):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            self.sim = ag.Simulator(case.scene(), num_worlds=worlds, dt=dt, dtype="float64", tol=tol,
                                    plan={"fused": False})  # fmt: skip
        self.solver, self.model = self.sim.solver, self.sim.model
        m = self.model
        self.dof = m.dof.numpy()
        self.free = [b for b in range(m.num_bodies) if self.dof[b] >= 0]
        self.n = 12 * len(self.free)
        self.mass, self.mc = m.mass.numpy(), m.mc.numpy()
        parts = self.solver.parts
        # coordinate terms (limits, drives, passive terms): E″∇x∇xᵀ, a rank-one Hessian each
        self.coord_parts = [c for c in parts if c.kind == "coordinate"]
        self.joint_parts = [c for c in parts if c.kind == "joint"]
        self.h, self.tol, self.max_iterations, self.cg_tol, self.worlds = dt, tol, max_iterations, cg_tol, worlds
        self.check_step = check_step
        # the constant factors, from the scene's pose (every world's: they share the mechanism)
        q0 = self.sim.state.q.numpy()
        H0 = self.system(q0, parts=[c for c in parts if c not in self.coord_parts])[2][0]
        D0 = self.system(q0, parts=[c for c in parts if c.kind == "body"])[2][0]
        T0 = self.frames(q0[0])
        self.H_rest = H0
        self.B = _sym(T0.T @ H0 @ T0)  # the whole Hessian in the bodies' co-rotated frames
        self.BD = _sym(T0.T @ D0 @ T0)  # its block diagonal: each body's inertia and orthogonality
        self.chol = {"rest": sla.cho_factor(H0), "corot": sla.cho_factor(self.B)}
        self.first = m.first.numpy()[: self.n]  # the library's envelope: each row from its first coupled body
        # the joints of the coordinate terms with curvature: every limit (it acts near its bounds), and the
        # instances of the other terms whose Hessian is not 0 at the pose (a passive term, a position drive)
        self.curved = []
        for c in self.coord_parts:
            H = self.system(q0, parts=[c])[2][0]
            if "limit" in c.name or np.abs(H).max() > 0:
                self.curved += [int(j) for j in c.instances(m)]

    # --- the library's pieces
    def system(self, q, derivs=HESSIAN, parts=None, active=None):
        """(E (W,), g (W, n), H (W, n, n)) of the step's potential at q (W, bodies, 12), from the
        terms ``parts`` (default: all)."""
        s, state = self.solver, self.sim.state
        state.q.assign(q)
        s.E.zero_()
        s.g.zero_()
        s.H.zero_()
        act = s.all_active if active is None else active
        for c in parts if parts is not None else s.parts:
            c.launch(self.model, state, s, state.q, s.E, s.g, s.H, act, derivs, s.cols, False)
        E = s.E.numpy().sum(axis=1)
        g = s.gradient()[:, : self.n] if derivs >= GRADIENT else None
        H = _sym(s.hessian()[:, : self.n, : self.n]) if derivs >= HESSIAN else None
        return E, g, H

    def frames(self, qw) -> np.ndarray:
        """T (n × n, block-diagonal) of one world's bodies at their polar rotations."""
        T = np.zeros((self.n, self.n))
        for b in self.free:
            o = self.dof[b]
            T[o:o + 12, o:o + 12] = body_frame(polar_rotation(qw[b, 3:].reshape(3, 3)))
        return T

    def coordinate_terms(self, q):
        """Per world (U (n × k), c (k,)): the coordinate terms' Hessian at q, Σ c_l u_l u_lᵀ (its
        eigenvectors: one a term whose curvature is on)."""
        if not self.coord_parts:
            return [(np.zeros((self.n, 0)), np.zeros(0))] * self.worlds
        out = []
        for Hw in self.system(q, parts=self.coord_parts)[2]:
            lam, V = np.linalg.eigh(Hw)
            keep = lam > 1e-12 * max(1.0, lam.max(initial=0.0))
            out.append((V[:, keep], lam[keep]))
        return out

    def retract(self, qw, d, alpha):
        out = qw.copy()
        for b in self.free:
            o = self.dof[b]
            out[b] = affine_body.retract_np(qw[b], d[o:o + 12], alpha, self.mass[0, b], self.mc[0, b])
        return out

    # --- one step
    def step(self, method):
        """One step of every world by ``method``.  Returns per-world counts: iterations,
        factorisations (of the whole system), CG iterations, rank-one changes applied (coordinate
        terms through a reused factor), trial energies, and converged."""
        s, state, W = self.solver, self.sim.state, self.worlds
        s.open_step(state)
        q = state.q.numpy()
        q_open = q.copy()
        n = {k: np.zeros(W, int) for k in ("iterations", "factorizations", "cg", "rank_one", "trials")}
        done = np.zeros(W, bool)
        step_chol = [None] * W
        for it in range(self.max_iterations):
            fresh = method in ("newton", "corot_pcg") or (method == "step" and it == 0)
            E, g, H = self.system(q, HESSIAN if fresh else GRADIENT)
            if method == "step" and it == 0:
                HC = self.system(q, parts=self.coord_parts)[2] if self.coord_parts else 0 * H
                step_chol = [sla.cho_factor(H[w] - HC[w]) for w in range(W)]
                E, g, _ = self.system(q, GRADIENT)
            if method == "dual":
                HJ = self.system(q, parts=self.joint_parts)[2]
                HC = self.system(q, parts=self.coord_parts)[2] if self.coord_parts else 0 * HJ
                E, g, _ = self.system(q, GRADIENT)
            lim = self.coordinate_terms(q) if method in ("rest", "corot", "step", "corot_pcg") else None
            q_new = q.copy()
            for w in np.flatnonzero(~done):
                n["iterations"][w] += 1
                if method == "newton":
                    d = sla.cho_solve(sla.cho_factor(H[w]), -g[w])
                    n["factorizations"][w] += 1
                elif method == "dual":
                    T = self.frames(q[w])
                    d = np.linalg.solve(T @ self.BD @ T.T + HJ[w] + HC[w], -g[w])
                elif method == "corot_pcg":
                    d, k = self.pcg(H[w], g[w], self.apply("corot", q[w], None, lim[w]))
                    n["cg"][w] += k
                else:
                    if method == "step" and it == 0:
                        n["factorizations"][w] += 1
                    d = self.apply(method, q[w], step_chol[w], lim[w])(-g[w])
                    n["rank_one"][w] += lim[w][1].size
                q_new[w], trials, small = self.search(q, w, d, E[w], g[w])
                n["trials"][w] += trials
                done[w] |= small
            q = q_new
            if done.all():
                break
        n["step_error"] = self.step_error(q_open, q, done) if self.check_step else np.zeros(W)
        state.q.assign(q)
        s.close_step(state)
        state.time += self.h
        return n, done

    def step_error(self, q_open, q, done) -> np.ndarray:
        """Per world, ‖q − q*‖∞ of this step's solution q against q*, the same step solved by
        Newton (a fresh factor every iteration) to ``STEP_TOL`` from the same guess: the solve's own
        error, which a trajectory's divergence (a long chain's motion is chaotic) does not blur."""
        qt, W = q_open.copy(), self.worlds
        active = done.copy()
        for _ in range(50):
            E, g, H = self.system(qt)
            for w in np.flatnonzero(active):
                d = sla.cho_solve(sla.cho_factor(H[w]), -g[w])
                qt[w], _, small = self.search(qt, w, d, E[w], g[w], STEP_TOL)
                active[w] &= not small
            if not active.any():
                break
        return np.where(done, np.abs(q - qt).reshape(W, -1).max(axis=1), np.nan)

    def apply(self, method, qw, chol, lim):
        """v ↦ (P + U diag(c) Uᵀ)⁻¹ v for the method's matrix P (constant, co-rotated or the step's
        factor) and the coordinate terms (U, c), by Woodbury: each term one more solve through P."""
        if method == "corot":
            T = self.frames(qw)

            def solve(v):
                return T @ sla.cho_solve(self.chol["corot"], T.T @ v)
        else:
            factor = self.chol["rest"] if method == "rest" else chol

            def solve(v):
                return sla.cho_solve(factor, v)
        U, curvature = lim
        if not curvature.size:
            return solve
        Z = solve(U)
        C = np.diag(1.0 / curvature) + U.T @ Z

        def woodbury(v):
            x = solve(v)
            return x - Z @ np.linalg.solve(C, U.T @ x)
        return woodbury

    def pcg(self, H, g, precondition):
        """H d = −g by conjugate gradients, preconditioned, to a relative residual cg_tol."""
        b = -g
        x, r = np.zeros_like(b), b.copy()
        z = precondition(r)
        p, rz, nb = z.copy(), r @ z, np.linalg.norm(b)
        for k in range(1, 501):
            Hp = H @ p
            a = rz / (p @ Hp)
            x += a * p
            r -= a * Hp
            if np.linalg.norm(r) <= self.cg_tol * nb:
                return x, k
            z = precondition(r)
            rz, rz_old = r @ z, rz
            p = z + (rz / rz_old) * p
        return x, 500

    def search(self, q, w, d, E0, g, tol=None):
        """Armijo's backtracking on world w along the retraction (as the staged step's ``accept``):
        returns (q_w, trial energies, converged).  Converged: a step taken under h·tol (or q's
        rounding floor), or one the energy's rounding cannot judge within 1000× that."""
        floor = max(self.h * (self.tol if tol is None else tol), 4 * np.finfo(float).eps * (1 + np.abs(q[w]).max()))
        step, gd = np.abs(d).max(), g @ d
        if step < 10 * floor or -gd <= 1600 * np.finfo(float).eps * abs(E0):
            return self.retract(q[w], d, 1.0), 0, step < 1000 * floor
        active = wp.array((np.arange(self.worlds) == w).astype(np.int32), dtype=wp.int32, device=self.model.device)
        alpha, trial = 1.0, q.copy()
        for k in range(1, 13):
            trial[w] = self.retract(q[w], d, alpha)
            E1 = self.system(trial, 0, active=active)[0][w]
            if E1 <= E0 + 1e-4 * alpha * gd + 16 * np.finfo(float).eps * abs(E0):
                return trial[w], k, alpha * step < floor
            alpha *= 0.5
        return q[w], 12, step < 1000 * floor


def _sym(H):
    return 0.5 * (H + np.swapaxes(H, -1, -2))


# ----------------------------------------------------------------------------- work a step
FINE = 10  # the fine reference's steps a step
STEP_TOL = 1e-11  # the tolerance [m/s] of the Newton solve a driver step is checked against
ROWS = {"revolute": 6, "fixed": 12, "prismatic": 12}  # penalty rows a joint (3 a point; the prismatic's C₀…C₃)


class Work:
    """The floating-point work of one world's iteration of each method (see ``ASSEMBLY``)."""

    def __init__(self, scene, driver: Driver):
        a = ASSEMBLY
        nb = len(driver.free)
        free = set(driver.free)
        joints = [j for j in scene.joints if j.body_a in free or j.body_b in free]
        triples = sum(ROWS[j.kind] // 3 for j in joints)  # 3-row groups (a point's gap), counted on both ends
        ncoord = sum(len(c.instances(driver.model)) for c in driver.coord_parts)  # limits, drives, passive terms
        self.energy = nb * a["body_energy"] + triples * a["point_energy"] + ncoord * a["coord_energy"]
        self.gradient = nb * a["body_gradient"] + triples * a["point_gradient"] + ncoord * a["coord_gradient"]
        self.hessian = nb * a["body_hessian"] + triples * a["point_hessian"] + ncoord * a["coord_hessian"]
        self.factor = factor_flops(driver.first)
        self.solve = solve_flops(driver.first)
        self.matvec = matvec_flops(driver.H_rest)
        self.rotate = nb * (a["polar"] + a["rotate"])
        # the dual (constraint-space) system of the joints: a joint's penalty rows and one row for each
        # coordinate term with curvature on it (E″∇x∇xᵀ: a limit, a passive term, a position drive),
        # coupled where joints share a body
        index = {id(j): k for k, j in enumerate(scene.joints)}
        coord = [driver.curved.count(index[id(j)]) for j in joints]
        rows = [ROWS[j.kind] + c for j, c in zip(joints, coord)]
        offs = np.concatenate([[0], np.cumsum(rows)]).astype(int)
        S = np.zeros((offs[-1], offs[-1]), bool)
        per_body = {b: [] for b in free}
        for k, j in enumerate(joints):
            for b in (j.body_a, j.body_b):
                if b in free:
                    per_body[b].append(k)
        for ks in per_body.values():
            for k1 in ks:
                for k2 in ks:
                    S[offs[k1]:offs[k1 + 1], offs[k2]:offs[k2 + 1]] = True
        first = envelope(S.astype(float))
        body_solve = 4 * 78  # forward and back through a body's constant 12 × 12 factor
        # a body's point rows meet in 3 × 3 blocks: RᵦCRᵦᵀ of a constant C = J(x̄)Bᵦ⁻¹J(x̄′)ᵀ (90 flops); a
        # coordinate row's ∇x goes through the body's factor (turned in and out) and meets every row there
        self.dual_form = offs[-1]
        for ks in per_body.values():
            t = sum(ROWS[joints[k].kind] // 3 for k in ks)
            self.dual_form += 90 * t * (t + 1) // 2 + sum(coord[k] for k in ks) * (
                body_solve + a["rotate"] + 24 * sum(rows[k] for k in ks))
        self.dual_factor = factor_flops(first)
        point_rows = sum(ROWS[j.kind] for j in joints)
        self.dual_solve = (solve_flops(first) + 2 * nb * body_solve + 32 * point_rows + 96 * sum(coord)
                           + nb * a["rotate"])  # fmt: skip
        self.dual_rows = int(offs[-1])
        self.n = driver.n

    def per_step(self, method, c) -> float:
        """Mean flops a world-step from a run's counts c (means a world-step: iterations,
        factorizations, cg, rank_one, trials)."""
        it, fac, cg, r1, tr = (c.get(k, 0.0) for k in ("iterations", "factorizations", "cg", "rank_one", "trials"))
        base = it * self.gradient + tr * self.energy
        if method in ("newton", "lib_newton", "lib_tight"):
            return base + it * (self.hessian + self.factor + self.solve)
        if method == "lib_reuse" or method == "step":
            return base + fac * (self.hessian + self.factor) + (it + r1) * self.solve
        if method == "rest":
            return base + (it + r1) * self.solve
        if method == "corot":
            return base + it * self.rotate + (it + r1) * self.solve
        if method == "corot_pcg":
            cg_iteration = self.matvec + self.solve + self.rotate + 10 * self.n
            return base + it * (self.hessian + self.rotate) + cg * cg_iteration
        if method.startswith("dual"):
            return base + it * (self.rotate + self.dual_form + self.dual_factor + self.dual_solve)
        raise ValueError(method)


# ----------------------------------------------------------------------------- the runs
def start(sim, case, worlds, seed):
    coords, rates = case.states(worlds, seed)
    sim.set_joint_state(coords, rates)


def library_sim(case, worlds, dt, seed, **kw):
    """A library Simulator (float64, default plan) from the case's random starts."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        sim = ag.Simulator(case.scene(), num_worlds=worlds, dt=dt, dtype="float64", **kw)
    start(sim, case, worlds, seed)
    return sim


def total_energy(sim) -> np.ndarray:
    return sum(np.asarray(v, dtype=np.float64) for v in sim.energies().values())


def angle_error(a, b) -> float:
    """The largest |a − b| over worlds and joints, revolute angles compared modulo 2π."""
    d = np.asarray(a) - np.asarray(b)
    return float(np.abs((d + np.pi) % (2 * np.pi) - np.pi).max())


class Run:
    """One method's run of a case: a library simulator or the driver, stepped in lockstep with
    the reference; keeps its counts, its joint error against the reference, its gaps and energy."""

    def __init__(self, name, sim, driver=None, method=None):
        self.name, self.sim, self.driver, self.method = name, sim, driver, method
        self.fine_error, self.step_err = 0.0, None if driver is None else 0.0
        self.counts = {k: 0 for k in ("iterations", "factorizations", "cg", "rank_one", "trials")}
        self.max_iterations, self.steps, self.failed_at, self.error, self.gap = 0, 0, None, 0.0, 0.0
        self.E0 = total_energy(sim)

    def step(self, ref, fine, kept):
        if self.failed_at is not None:
            return
        if self.driver is None:
            self.sim.step()
            its = self.sim.newton_iterations()
            ok = self.sim.world_status() == 0
            c = {"iterations": its, "factorizations": self.sim.newton_factorizations(), "trials": its}
        else:
            c, ok = self.driver.step(self.method)
        if "step_error" in c:
            self.step_err = max(self.step_err, float(np.nanmax(c.pop("step_error"), initial=0.0)))
        for k, v in c.items():
            self.counts[k] += float(np.sum(v))
        self.max_iterations = max(self.max_iterations, int(np.max(c["iterations"])))
        self.steps += 1
        if not np.all(ok):
            self.failed_at = self.steps
            return
        if kept.any():
            coords = self.sim.joint_coordinates()[kept]
            self.error = max(self.error, angle_error(coords, ref.joint_coordinates()[kept]))
            self.fine_error = max(self.fine_error, angle_error(coords, fine.joint_coordinates()[kept]))
        self.gap = max(self.gap, float(self.sim.joint_violation().max()))

    def row(self, work: Work, worlds) -> dict:
        per = {k: v / max(1, self.steps * worlds) for k, v in self.counts.items()}
        r = dict(method=self.name, steps=self.steps, failed_at_step=self.failed_at,
                 iterations=per["iterations"], max_iterations=self.max_iterations,
                 factorizations=per["factorizations"], cg_iterations=per["cg"], rank_one=per["rank_one"],
                 trials=per["trials"], joint_error=self.error, fine_error=self.fine_error, step_error=self.step_err,
                 joint_gap=self.gap,
                 energy_change=float(np.abs(total_energy(self.sim) - self.E0).max()),
                 flops=work.per_step(self.name if self.driver is None else self.method, per))  # fmt: skip
        return r


def run_case(name, dt, worlds, duration, seed, tol, ref_tol, methods, cg_tol, max_iterations):
    case = CASES[name]
    ref = library_sim(case, worlds, dt, seed, tol=ref_tol)
    fine = library_sim(case, worlds, dt / FINE, seed, tol=ref_tol)  # the time discretisation's error
    runs = []
    for m in methods:
        if m in LIBRARY:
            runs.append(Run(m, library_sim(case, worlds, dt, seed, tol=tol, reuse_factor=(m == "lib_reuse"))))
        else:
            method, t = (m, tol) if m != "dual_tight" else ("dual", tol / 100)
            d = Driver(case, worlds, dt, t, max_iterations, cg_tol)
            start(d.sim, case, worlds, seed)
            runs.append(Run(m, d.sim, d, method))
    work = Work(case.scene(), next(r.driver for r in runs if r.driver is not None) if any(r.driver for r in runs)
                else Driver(case, worlds, dt, tol))  # fmt: skip
    kept = np.ones(worlds, bool)  # worlds whose references took every step whole (no retry's substeps)
    for _ in range(int(round(duration / dt))):
        ref.step()
        kept &= (ref.substeps() == 1) & (ref.world_status() == 0)
        for _ in range(FINE):
            fine.step()
            kept &= (fine.substeps() == 1) & (fine.world_status() == 0)
        for r in runs:
            r.step(ref, fine, kept)
    rows = [r.row(work, worlds) for r in runs]
    info = dict(case=name, dt=dt, unknowns=work.n, dual_rows=work.dual_rows, factor_flops=work.factor,
                solve_flops=work.solve, dual_factor_flops=work.dual_factor, dual_solve_flops=work.dual_solve,
                reference_gap=float(ref.joint_violation().max()), reference_worlds=int(kept.sum()))  # fmt: skip
    return info, rows


def cpu_name() -> str:
    """The CPU's model name (Linux), else the platform's."""
    try:
        with open("/proc/cpuinfo") as f:
            return next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        return platform.processor() or platform.machine()


def recount(path):
    """The flops of a study's JSON counted again from its runs' counts (after a change of ``Work``)."""
    with open(path) as f:
        out = json.load(f)
    works = {}
    for info in out["cases"]:
        name = info["case"]
        if name not in works:
            case = CASES[name]
            works[name] = Work(case.scene(), Driver(case, 1, info["dt"], 1e-5))
        work = works[name]
        info.update(factor_flops=work.factor, solve_flops=work.solve, dual_rows=work.dual_rows,
                    dual_factor_flops=work.dual_factor, dual_solve_flops=work.dual_solve)  # fmt: skip
        for r in info["rows"]:
            counts = dict(r, cg=r["cg_iterations"])
            method = "dual" if r["method"] == "dual_tight" else r["method"]
            r["flops"] = work.per_step(method, counts)
    out["assembly_flops"] = ASSEMBLY
    with open(path, "w") as f:
        json.dump(out, f, indent=1, default=lambda o: o.item())
    return out


def table(out, header=True):
    """The study's table: a row a case, dt and method."""
    if header:
        print(f"{'case':16} {'dt':>5} {'method':11} {'its':>6} {'max':>4} {'fact':>5} {'cg':>6} {'step [m]':>8} "
              f"{'err [rad]':>9} {'vs dt/10':>9} {'gap [m]':>8} {'dE [J]':>8} {'kflop':>8}")  # fmt: skip
    for info in out["cases"]:
        for r in info["rows"]:
            head = (f"{info['case']:16} {info['dt']:5.2f} {r['method']:11} {r['iterations']:6.2f} "
                    f"{r['max_iterations']:4d} {r['factorizations']:5.2f} {r['cg_iterations']:6.1f} ")  # fmt: skip
            if r["failed_at_step"] is not None:
                print(head + f"unconverged within {r['max_iterations']} iterations at step {r['failed_at_step']}")
                continue
            step = "       —" if r["step_error"] is None else f"{r['step_error']:8.1e}"
            print(head + f"{step} {r['joint_error']:9.1e} {r['fine_error']:9.1e} {r['joint_gap']:8.1e} "
                  f"{r['energy_change']:8.1e} {r['flops'] / 1e3:8.1f}", flush=True)  # fmt: skip


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default=",".join(CASE_NAMES))
    ap.add_argument("--dts", default="0.01,0.05")
    ap.add_argument("--worlds", type=int, default=4)
    ap.add_argument("--duration", type=float, default=1.0, help="simulated time a run [s]")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--tol", type=float, default=1e-5, help="the stop test's velocity tolerance [m/s]")
    ap.add_argument("--ref-tol", type=float, default=1e-10, help="the reference's tolerance [m/s]")
    ap.add_argument("--methods", default=",".join(LIBRARY + METHODS + ("dual_tight",)))
    ap.add_argument("--cg-tol", type=float, default=1e-3)
    ap.add_argument("--max-iterations", type=int, default=100, help="a driver step's budget (then the run stops)")
    ap.add_argument("--out", default=None)
    ap.add_argument("--recount", default=None, help="a study's JSON: count its flops again, print its table")
    args = ap.parse_args(argv)
    if args.recount:
        table(recount(args.recount))
        return
    methods = args.methods.split(",")
    given = argv if argv is not None else sys.argv[1:]
    out = dict(command="python scripts/constant_factor_study.py " + " ".join(given),
               machine=f"{cpu_name()}, {os.cpu_count()} cores, float64",
               date=datetime.date.today().isoformat(), assembly_flops=ASSEMBLY, cases=[])  # fmt: skip
    for name in args.cases.split(","):
        for dt in (float(x) for x in args.dts.split(",")):
            t0 = time.perf_counter()
            info, rows = run_case(name, dt, args.worlds, args.duration, args.seed, args.tol, args.ref_tol, methods,
                                  args.cg_tol, args.max_iterations)  # fmt: skip
            info.update(rows=rows, seconds=time.perf_counter() - t0)
            out["cases"].append(info)
            table(dict(cases=[info]), header=len(out["cases"]) == 1)
            if args.out:
                with open(args.out, "w") as f:
                    json.dump(out, f, indent=1, default=lambda o: o.item())


if __name__ == "__main__":
    main()
