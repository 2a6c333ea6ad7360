"""A world's Newton solve (``solve_world``): each iteration zeroes its system, assembles E, g and
(unless it reuses the factor) H, factors and solves H Δq = −g (with ``secant``, at an acting limit
the limit's curvature its secant: ``limit_secant``), then ``take_step``: the stop tests
(‖Δq‖∞ under the tolerance; the predicted decrease −gᵀΔq under the energy's rounding; a fresh
step under ``quadratic`` × q's rounding), the line search (Armijo's test
E(q + αΔq) ≤ E(q) + 10⁻⁴ α gᵀΔq with rounding-level slack, α halved on rejection, in a scene
with limits the step their cubics put the minimum at tried first: ``limit_step``), the choice
to reuse the factor (``chord_step``) and the update of q along the bodies' retraction."""
import functools
from types import SimpleNamespace
from typing import Any

import numpy as np
import warp as wp

from ...core.angles import angle_ops
from ...constitutions import affine_body
from ...sim.status import BREAKDOWN, OK, UNCONVERGED
from ...core.warp_ops import ENERGY, GRADIENT, HESSIAN, body_dofs, ops
from .assembly import assembly
from .clock import (PHASE_ZERO, PHASE_ASSEMBLE, PHASE_FACTOR, PHASE_SOLVE, PHASE_STEP, PHASE_STEP_ENERGY,
                     PHASE_STEP_TRIAL, clock)  # fmt: skip
from .factor import factor, warp_ldl_solve
from .layout import KernelSpec, indexing
from .limit_secant import limit_secant
from .structs import structs


@functools.lru_cache(maxsize=None)
def limit_model(spec: KernelSpec):
    """``limit_step``: the step along a Newton step at which the world's energy is least where a
    limit acts, from each limit's overrun and cubic along the step (the line search's first trial
    in a scene with limits, ``decide``)."""
    dtype = spec.dtype
    vec12 = ops(dtype).vec12
    Terms = structs(dtype).Terms
    angles = angle_ops(dtype)
    cos_sin, delta_theta, displacement = angles.cos_sin, angles.delta_theta, angles.displacement
    # the scene's limits (KernelSpec.limits), whose cubics the line search models (limit_step)
    NR, NP = spec.limits
    NL = NR + NP
    vecL = wp.types.vector(length=max(NL, 1), dtype=dtype)
    zero, one = dtype(0.0), dtype(1.0)

    @wp.func
    def overrun(x: dtype, lo: dtype, up: dtype, inv: dtype):
        """A limit's overrun r = max(x − u, l − x)·inv: > 0 where its cubic s·r³ acts."""
        return wp.max(x - up, lo - x) * inv

    @wp.func
    def rlim_overrun(q: wp.array2d(dtype=vec12), qr: int, t: Terms, w: int, k: int):
        """Revolute limit k's overrun [rad] at row qr of q (its angle θ0 + ΔΘ as revolute_limit)."""
        j = t.rlim_ids[k]
        c, sn = cos_sin(q[qr, t.body_a[j]], q[qr, t.body_b[j]], t.n_a[w, j], t.b_a[w, j], t.n_b[w, j], t.b_b[w, j])
        x = t.theta0[w, j] + delta_theta(c, sn, t.c_prev[w, j], t.s_prev[w, j])
        return overrun(x, t.rlim_lo[w, k], t.rlim_up[w, k], one)

    @wp.func
    def plim_overrun(q: wp.array2d(dtype=vec12), qr: int, t: Terms, w: int, k: int):
        """Prismatic limit k's overrun at row qr of q, over the range's width (prismatic_limit)."""
        j = t.plim_ids[k]
        lo = t.plim_lo[w, k]
        up = t.plim_up[w, k]
        x = displacement(q[qr, t.body_a[j]], q[qr, t.body_b[j]], t.c_a[w, j], t.c_b[w, j], t.t_a[w, j])
        return overrun(x, lo, up, wp.where(up > lo, one / (up - lo), one))

    @wp.func
    def line_slope(r0: vecL, dr: vecL, st: vecL, A: dtype, B: dtype, alpha: dtype):
        """(φ′(α), φ″(α)) of the line model φ(α) = Aα + Bα²/2 + Σ s(r₀ + αΔ)³₊ (limit_step)."""
        d1 = A + B * alpha
        d2 = B
        for k in range(wp.static(NL)):
            r = r0[k] + alpha * dr[k]
            if r > zero:
                sd = st[k] * dr[k]
                d1 += dtype(3.0) * sd * r * r
                d2 += dtype(6.0) * sd * dr[k] * r
        return d1, d2

    @wp.func
    def limit_step(q: wp.array2d(dtype=vec12), q_trial: wp.array2d(dtype=vec12), t: Terms, w: int, row: int,
                   gdq: dtype):  # fmt: skip
        """The step α* along the Newton step Δq at which the world's energy is least, where a limit
        acts at q or at the trial q + Δq (row ``row`` of q_trial); else 1.

        Newton's quadratic model misses a limit's one-sided cubic s·r³ wherever the iterate is off
        it: from r ≤ 0 the model has no curvature there, and its step runs to the free motion's
        overrun (backtracking then halves it, an iteration at a time); from r > 0 its curvature
        6s·r overestimates the cubic's on the way out, and the step stops halfway to r = 0.  Each
        costs iterations (design.md §4).  Along the step this model keeps the cubics exact: each
        limit's overrun goes linearly from r₀ (at q) to r₁ (at the trial), Δ = r₁ − r₀, and the
        rest of the energy is Newton's quadratic with the limits' own parts taken out, slope
        A = gᵀΔq − Σ 3s·r₀₊²Δ and curvature B = −gᵀΔq − Σ 6s·r₀₊Δ² (H Δq = −g).  φ(α) = Aα + Bα²/2
        + Σ s(r₀ + αΔ)³₊ is convex; its minimum is found by Newton's method on φ′ in a bracket."""
        r0 = vecL()
        dr = vecL()
        st = vecL()
        A = gdq
        B = -gdq
        acts = int(0)
        for k in range(wp.static(NL)):
            r1 = zero
            if wp.static(k < NR):
                r0[k] = rlim_overrun(q, w, t, w, k)
                r1 = rlim_overrun(q_trial, row, t, w, k)
                st[k] = t.rlim_s[w, k]
            else:
                r0[k] = plim_overrun(q, w, t, w, k - NR)
                r1 = plim_overrun(q_trial, row, t, w, k - NR)
                st[k] = t.plim_s[w, k - NR]
            dr[k] = r1 - r0[k]
            if r0[k] > zero or r1 > zero:
                acts = 1
            if r0[k] > zero:
                A -= dtype(3.0) * st[k] * r0[k] * r0[k] * dr[k]
                B -= dtype(6.0) * st[k] * r0[k] * dr[k] * dr[k]
        if acts == 0:
            return one  # (decide calls this only for a descent step, gᵀΔq < 0)
        # the rest of the energy is convex (the bodies' inertia at least): a model that says
        # otherwise is off, and a thousandth of Newton's own curvature along the step stands in
        B = wp.max(B, dtype(1.0e-3) * (-gdq))
        lo = zero
        hi = one
        d1, d2 = line_slope(r0, dr, st, A, B, hi)
        while d1 < zero and hi < dtype(4.0):
            lo = hi
            hi = hi * dtype(2.0)
            d1, d2 = line_slope(r0, dr, st, A, B, hi)
        if d1 < zero:
            return hi
        a = hi
        for _it in range(24):
            # Newton on φ′ from the bracket's right end (φ′ > 0), bisection where it leaves it
            a_new = a - d1 / d2
            if a_new <= lo or a_new >= hi:
                a_new = dtype(0.5) * (lo + hi)
            a = a_new
            d1, d2 = line_slope(r0, dr, st, A, B, a)
            if d1 > zero:
                hi = a
            else:
                lo = a
            if hi - lo < dtype(1.0e-3) * hi or wp.abs(d1) <= dtype(1.0e-6) * (-gdq):
                break
        return a

    return SimpleNamespace(limit_step=limit_step)


@functools.lru_cache(maxsize=None)
def acceptance(spec: KernelSpec):
    """``armijo`` and ``decide``: a trial's test and the line search's next step from it (α halved,
    or in a scene with limits ``next_trial`` from ``limit_model``'s α*)."""
    dtype = spec.dtype
    vec12 = ops(dtype).vec12
    Terms = structs(dtype).Terms
    limit_step = limit_model(spec).limit_step
    has_limits = sum(spec.limits) > 0
    one, half = dtype(1.0), dtype(0.5)
    EPS = dtype(float(np.finfo(np.float32 if dtype == wp.float32 else np.float64).eps))

    @wp.func
    def armijo(e0: dtype, e1: dtype, alpha: dtype, gdq: dtype):
        """(accepted, stalled) for the trial energy e1 at step α: Armijo's test with rounding-level
        slack; stalled when the decrease is below what the precision resolves."""
        noise = dtype(16.0) * EPS * (wp.abs(e0) + wp.abs(e1))
        if e1 <= e0 + dtype(1.0e-4) * alpha * gdq + noise and wp.isfinite(e1):
            return 1, wp.where(e0 - e1 <= noise, 1, 0)
        return 0, 0

    @wp.func
    def next_trial(phase: int, accepted: int, a_star: dtype, e1: dtype, e_first: dtype, alpha: dtype,
                   max_line_search: int, chord: int):  # fmt: skip
        """The line search after a trial at α: (over, take, phase, α, e_first).

        phase 0: the Newton step's first trial, α = 1, and ``a_star`` the step at which the world's
        limits put the minimum along it (limit_step; 1 where no limit acts on the step).  Accepted
        by Armijo, the step is kept unless a_star lies outside [0.75, 1.25]: then a_star is tried
        (phase 1), and kept where ``accepted`` (decide: its energy is below the first trial's,
        e_first, by more than rounding), else the search goes back to α = 1 (phase 2, kept without
        a test).  Rejected, the next α is a_star where it is below 1, else 1/2, then α is halved
        (phase 3) until accepted or α ≤ 2^-(max_line_search − 1) (the search ran out: over 1,
        take 0).  A reused
        factor's step (chord > 0) is tried at α = 1 only."""
        min_alpha = wp.pow(half, dtype(max_line_search - 1))
        if phase == 1:
            if accepted != 0:
                return 1, 1, phase, alpha, e_first
            return 0, 0, 2, one, e_first
        if phase == 0 and chord <= 0:
            if accepted != 0:
                if a_star > dtype(1.25) or a_star < dtype(0.75):
                    return 0, 0, 1, a_star, e1
                return 1, 1, phase, alpha, e_first
            if alpha > min_alpha:
                return 0, 0, 3, wp.max(wp.where(a_star < one, a_star, dtype(0.5)), min_alpha), e_first
            return 1, 0, 3, alpha, e_first
        if accepted != 0:
            return 1, 1, phase, alpha, e_first
        if chord > 0 or alpha <= min_alpha:
            return 1, 0, phase, alpha, e_first
        return 0, 0, 3, alpha * dtype(0.5), e_first

    @wp.func
    def decide(q: wp.array2d(dtype=vec12), q_trial: wp.array2d(dtype=vec12), t: Terms, w: int, row: int, ok: int,
               e0: dtype, e1: dtype, gdq: dtype, alpha: dtype, phase: int, e_first: dtype, max_line_search: int,
               chord: int):  # fmt: skip
        """After a trial's Armijo test ``ok``: (over, accepted, phase, α, e_first).  Without limits,
        α is halved until accepted; with them, next_trial from the limits' step α* (limit_step, at
        the first trial).  α* is sought only where the first trial's energy e1 is off Newton's
        quadratic model e0 + gᵀΔq/2 by more than |gᵀΔq|/32 (elsewhere the energy along the step
        is as good as quadratic, and so is the step), and where the predicted decrease −gᵀΔq is
        100× the energies' rounding (below it, e1 is mostly rounding, and so would the model be).
        A tried α* is kept only where its energy is below the first trial's by more than rounding,
        for the same reason."""
        if wp.static(has_limits):
            a_star = one
            noise = dtype(16.0) * EPS * (wp.abs(e0) + wp.abs(e1))
            if phase == 0 and chord <= 0:
                off = wp.abs(e1 - e0 - half * gdq) > dtype(0.03125) * wp.abs(gdq)
                if off and -gdq > dtype(100.0) * noise:
                    a_star = limit_step(q, q_trial, t, w, row, gdq)
            if phase == 1:
                ok = wp.where(ok != 0 and e1 < e_first - dtype(16.0) * EPS * (wp.abs(e1) + wp.abs(e_first)), 1, 0)
            return next_trial(phase, ok, a_star, e1, e_first, alpha, max_line_search, chord)
        return ok, ok, phase, wp.where(ok != 0, alpha, alpha * half), e_first

    return SimpleNamespace(armijo=armijo, decide=decide)


@functools.lru_cache(maxsize=None)
def line_search(spec: KernelSpec):
    """``search``: the line search along a Newton step (``trial`` points on the bodies'
    retraction, ``acceptance``'s test on the world's energy)."""
    dtype, LANES, lanes, compact = spec.dtype, spec.LANES, spec.lanes, spec.compact
    vec12 = ops(dtype).vec12
    bd = body_dofs(spec.axis)
    D, sel = bd.D, bd.sel
    Terms = structs(dtype).Terms
    retract_body = affine_body.kernels(dtype).retract
    block_sync = indexing(spec).block_sync
    assemble = assembly(spec).assemble
    clock_now, tick = clock(spec).clock_now, clock(spec).tick
    armijo, decide = acceptance(spec).armijo, acceptance(spec).decide
    has_limits = sum(spec.limits) > 0
    zero, one = dtype(0.0), dtype(1.0)

    @wp.func
    def trial(q: wp.array2d(dtype=vec12), q_trial: wp.array2d(dtype=vec12), t: Any, step: Any, w: int, row: int,
              s: int, T: int, alpha: dtype, lane: int):  # fmt: skip
        """q_trial[row] = q[w] + α Δq along the retraction's path (affine_body.retract), Δq in
        scratch column s of the flat ``step`` (T columns); lane ``lane`` of LANES moves bodies lane,
        lane + LANES, … (then the block synchronises)."""
        for b in range(lane, q.shape[1], LANES):
            qb = q[w, b]
            ob = t.dof[b]
            if ob >= 0:
                d = vec12()  # the body's step, 0 on the entries a planar scene holds
                for u in range(D):
                    d[sel(u)] = step[(ob + u) * T + s]
                qb = retract_body(qb, d, alpha, t.mass[w, b], t.mc[w, b], 0)
            q_trial[row, b] = qb
        if wp.static(lanes):
            block_sync()

    @wp.func
    def search(q: wp.array2d(dtype=vec12), q_trial: wp.array2d(dtype=vec12), t: Terms, step: Any, g: Any, H: Any,
               w: int, row: int, s: int, B: int, e0: dtype, gdq: dtype, skip: int, done: int, chord: int,
               max_line_search: int, lane: int):  # fmt: skip
        """(accepted, stalled, α) for the step: taken whole when ``skip`` (whole_step); a reused
        factor's step tried at α = 1 only; else Armijo's test on the world's own energy, α halved on
        rejection, or where the scene has limits the next α from ``decide``.  The search runs out
        after ``max_line_search`` rejections (α ≤ 2^-(max_line_search − 1)).  The trial points go
        to row ``row`` of q_trial; s, B as in assemble, lane as in trial.

        The trial loop is written twice, for the two forms of the fused step (KernelSpec.compact).
        The lane-split kernel (compact) runs one loop of tries with a single trial and a single
        energy in it: its step is a latency-bound chain, and each inlined copy of assemble's energy
        adds that whole code to the kernel again.  The thread-per-world kernels (shared and global
        scratch) try α = 1 before the loop and test a reused factor's step on a branch of its own:
        a throughput-bound thread pays less for the branches than for the selects.  The staged
        (reference) step has its own search, the same Armijo test as kernels over all worlds a
        round (solver/kernels.py, ``_search_kernels``), without the limits' model."""
        c = clock_now()
        alpha = one
        accepted = int(0)
        stalled = int(0)
        over = int(0)
        phase = int(0)  # (next_trial's phases, with limits)
        e_first = zero
        tries = max_line_search
        if wp.static(has_limits):
            tries = max_line_search + 2  # α* and, where it fails, α = 1 again
        if wp.static(compact):
            # one trial and one energy in the code (a loop of tries, not a first try and a loop):
            # each inlined copy of assemble's energy adds that whole code to the kernel again
            tries = wp.where(skip != 0 or chord > 0, 1, tries)
            for _ls in range(tries):
                trial(q, q_trial, t, step, w, row, s, B, alpha, lane)
                c = tick(t, w, lane, PHASE_STEP_TRIAL, c)
                if skip != 0:
                    accepted = 1
                    stalled = done
                    break
                if wp.static(has_limits):
                    if phase == 2:
                        accepted = 1  # back at the first trial's point, which passed
                        _ok, stalled = armijo(e0, e_first, one, gdq)
                        break
                e1 = assemble(q_trial, row, w, s, B, ENERGY, t, g, H)
                ok, stalled = armijo(e0, e1, alpha, gdq)
                c = tick(t, w, lane, PHASE_STEP_ENERGY, c)
                over, accepted, phase, alpha, e_first = decide(q, q_trial, t, w, row, ok, e0, e1, gdq, alpha, phase,
                                                               e_first, max_line_search, chord)  # fmt: skip
                if over != 0:
                    break
                if wp.static(lanes):
                    # the next trial moves q_trial: every lane's energy must have read it first
                    # (assemble ends on the joints' terms, with no barrier; without this one a
                    # fast lane's next trial races a slow lane's energy, and the world's lanes
                    # take different steps: a SliderCrank-v0 world in tests/test_graph.py)
                    block_sync()
        else:
            trial(q, q_trial, t, step, w, row, s, B, alpha, lane)
            c = tick(t, w, lane, PHASE_STEP_TRIAL, c)
            if skip != 0:
                accepted = 1
                stalled = done
            elif chord > 0:
                accepted, stalled = armijo(e0, assemble(q_trial, row, w, s, B, ENERGY, t, g, H), one, gdq)
                c = tick(t, w, lane, PHASE_STEP_ENERGY, c)
            else:
                for ls in range(tries):
                    if ls > 0:
                        trial(q, q_trial, t, step, w, row, s, B, alpha, lane)
                        c = tick(t, w, lane, PHASE_STEP_TRIAL, c)
                        if wp.static(has_limits):
                            if phase == 2:
                                accepted = 1
                                _ok, stalled = armijo(e0, e_first, one, gdq)
                                break
                    e1 = assemble(q_trial, row, w, s, B, ENERGY, t, g, H)
                    ok, stalled = armijo(e0, e1, alpha, gdq)
                    c = tick(t, w, lane, PHASE_STEP_ENERGY, c)
                    over, accepted, phase, alpha, e_first = decide(q, q_trial, t, w, row, ok, e0, e1, gdq, alpha, phase,
                                                                   e_first, max_line_search, 0)  # fmt: skip
                    if over != 0:
                        break
        return accepted, stalled, alpha

    return SimpleNamespace(search=search)


@functools.lru_cache(maxsize=None)
def stepping(spec: KernelSpec):
    """``take_step``: everything after a Newton direction (stop tests, line search, factor
    reuse, update of q)."""
    dtype, LANES, lanes = spec.dtype, spec.LANES, spec.lanes
    vec12 = ops(dtype).vec12
    Terms = structs(dtype).Terms
    staged = spec.staged()
    noise_floor, energy_noise = staged["noise_floor"], staged["energy_noise"]
    block_sync = indexing(spec).block_sync
    search = line_search(spec).search
    zero, one, half = dtype(0.0), dtype(1.0), dtype(0.5)
    EPS = dtype(float(np.finfo(np.float32 if dtype == wp.float32 else np.float64).eps))
    QUAD = dtype(4.0 * float(spec.quadratic))  # × q's rounding (SolverSettings.quadratic_stop)

    @wp.func
    def whole_step(e0: dtype, gdq: dtype, dmax: dtype, floor: dtype, noise: dtype, chord: int):
        """(skip, done): take the Newton step whole, without a line search, when it is under the
        tolerance or when its predicted decrease −gᵀΔq is below what the energy's float rounding
        can resolve (the search could only halve it on noise; ``noise``: solver.kernels.energy_noise);
        done: the solve ends with it.  A step from a reused factor (chord) converges linearly: only
        one under the tolerance ends it."""
        unresolved = -gdq <= dtype(1600.0) * EPS * wp.abs(e0) or -gdq <= noise
        # within 10x the noise floor the step is taken whole: in float32 the energy's rounding there
        # exceeds the step's decrease (a joint's energy K/2‖Δx‖² at ‖Δx‖ ~ 1e-6 m is computed from
        # positions rounded to ~6e-8 m), and a search halves good steps on noise: a float32 solve
        # would crawl at a small α where float64 takes the whole step and converges
        skip = dmax < dtype(10.0) * floor or unresolved
        done = dmax < floor or (unresolved and dmax < dtype(1000.0) * floor and chord <= 0)
        return wp.where(skip, 1, 0), wp.where(done, 1, 0)

    @wp.func
    def chord_step(chord: int, reuse: int, accepted: int, alpha: dtype, dmax: dtype, d_prev: dtype):
        """(retry, chord) after an iteration; chord 1: the next iteration reuses the factor, 0: it
        factors, −1: it factors and the step reuses no factor again.  A step from a reused factor is
        tried at α = 1 only: rejected, it is not taken and the next iteration refactors at the same q
        (retry 1), and the rest of the step refactors every iteration (where a reused factor fails,
        the Hessian changes fast, and alternating the two would spend iterations on reused steps
        that fail).  The factor is reused after a full step taken whole, and kept while the reused
        steps shrink at least 8× an iteration (they converge linearly, at the rate the Hessian has
        changed; a slow rate would leave the solve's error near the tolerance, where Newton's leaves
        it far below); a reused step that shrinks less also ends reuse for the step (where float32's
        noise makes steps ~1e-3 that are taken whole, refactor and reuse would otherwise alternate
        until the iteration cap ends the solve unconverged: a rule that keeps float32 solves of
        large steps converging)."""
        if chord > 0:
            if accepted == 0:
                return 1, -1
            return 0, wp.where(dmax <= dtype(0.125) * d_prev, 1, -1)
        if chord < 0:
            return 0, -1
        return 0, wp.where(accepted != 0 and alpha == one, reuse, 0)

    @wp.func
    def end_iteration(q: wp.array2d(dtype=vec12), q_trial: wp.array2d(dtype=vec12), w: int, row: int, accepted: int,
                      stalled: int, dmax: dtype, floor: dtype, converged: wp.array(dtype=wp.int32),
                      lane: int):  # fmt: skip
        """Take the accepted trial point (row of q_trial) as world w's q; 1 when its solve is over
        (converged), 2 when its search ran out away from convergence, else 0.  A search that ran out
        takes no step: converged if the step was already within 1000× the floor, where float32's
        energy cannot resolve the decrease a correct step makes.  (Steps within 10x the noise floor
        are taken whole, see whole_step.)  Lane-split: each lane copies its bodies, lane 0 writes the
        flag."""
        if accepted == 0:
            if dmax < dtype(1000.0) * floor:
                if lane == 0:
                    converged[w] = 1
                return 1
            return 2
        for b in range(lane, q.shape[1], LANES):
            q[w, b] = q_trial[row, b]
        if dmax < floor or stalled != 0:
            if lane == 0:
                converged[w] = 1
            return 1
        return 0

    @wp.func
    def take_step(q: wp.array2d(dtype=vec12), q_trial: wp.array2d(dtype=vec12), t: Terms, step: Any, g: Any, H: Any,
                  w: int, row: int, s: int, B: int, e0: dtype, gdq: dtype, dmax: dtype, g_abs: dtype, threshold: dtype, chord: int,
                  reuse: int, d_prev: dtype, max_line_search: int, converged: wp.array(dtype=wp.int32),
                  lane: int):  # fmt: skip
        """Everything after a Newton direction (both layouts): the stop test, the line search, the
        choice to reuse the factor next, and the update of q.  Returns (end_iteration's 1 when the
        solve converged, 2 when its search ran out, else 0; chord for the next iteration)."""
        floor, rounding = noise_floor(q, w, threshold)
        # a Newton step under quadratic_stop × q's rounding ends the solve if accepted at α = 1
        quad = chord <= 0 and dmax < QUAD * rounding
        skip, done = whole_step(e0, gdq, dmax, floor, energy_noise(rounding, g_abs), chord)
        accepted, stalled, alpha = search(q, q_trial, t, step, g, H, w, row, s, B, e0, gdq, skip, done, chord,
                                          max_line_search, lane)  # fmt: skip
        if quad and accepted != 0 and alpha == one:
            stalled = 1  # taken whole or by Armijo: Newton's next step would be rounding (quadratic_stop)
        retry, chord_next = chord_step(chord, reuse, accepted, alpha, dmax, d_prev)
        stop = int(0)
        if retry == 0:
            stop = end_iteration(q, q_trial, w, row, accepted, stalled, dmax, floor, converged, lane)
        if wp.static(lanes):
            block_sync()  # q is read whole by the next iteration
        # a fresh factor's step accepted whole by the line search (not one at the noise floor) that
        # shrank less than 2× from the last: Newton converges only linearly, its Hessian short of the
        # exact one (affine_body: R⁺ for R where a body is compressed)
        linear = chord <= 0 and skip == 0 and accepted != 0 and alpha == one and d_prev > zero and dmax > half * d_prev
        return stop, chord_next, wp.where(linear, 1, 0)

    return SimpleNamespace(take_step=take_step)


@functools.lru_cache(maxsize=None)
def iteration(spec: KernelSpec):
    """``iterate``: one Newton iteration of a world's solve (zero, assemble, factor and solve, take
    the step), in the layout ``spec`` builds for.  One function: a function of its own for any of
    its stages changes the generated machine code (results/solver_notes.md)."""
    dtype, N, NF, TRI, LANES, G, RL = spec.dtype, spec.N, spec.NF, spec.TRI, spec.LANES, spec.G, spec.RL
    lanes, compact, envelope, warp_regs = spec.lanes, spec.compact, spec.envelope, spec.warp_regs
    packed = spec.packed and not envelope
    vec12 = ops(dtype).vec12
    Terms = structs(dtype).Terms
    staged = spec.staged()
    cholesky_solve, factored_solve = staged["cholesky_solve"], staged["factored_solve"]
    reductions = staged["reductions"]
    regs_ldl_solve = warp_ldl_solve(dtype, N, RL) if warp_regs else None
    ldl_lanes, solve_lanes = factor(spec).ldl_lanes, factor(spec).solve_lanes
    at = indexing(spec)
    hrow, block_sync = at.hrow, at.block_sync
    assemble = assembly(spec).assemble
    take_step = stepping(spec).take_step
    # the direction at an acting limit from its secant (limit_secant), where the plan takes it
    secant = spec.secant and spec.limits != (0, 0)  # (KernelSpec refuses it with lanes)
    secant_step = limit_secant(spec).secant_step
    clock_now, tick = clock(spec).clock_now, clock(spec).tick
    zero, one = dtype(0.0), dtype(1.0)

    @wp.func
    def iterate(q: wp.array2d(dtype=vec12), q_trial: wp.array2d(dtype=vec12), t: Terms, g: wp.array(dtype=dtype),
                H: wp.array(dtype=dtype), dq: wp.array(dtype=dtype), w: int, s: int, T: int, row: int, threshold: dtype,
                max_iterations: int, max_line_search: int, reuse: int, status: wp.array(dtype=wp.int32),
                iterations: wp.array(dtype=wp.int32), factorizations: wp.array(dtype=wp.int32),
                converged: wp.array(dtype=wp.int32), lane: int, chord: int, d_prev: dtype, nfact: int, its: int,
                cap: int, spare: int, exact: int):  # fmt: skip
        """One Newton iteration of world w's solve (solve_world): zero, assemble, factor and solve, take
        the step.  The solve's state goes in and comes back: ``chord`` (1: H holds the factor of an
        earlier iteration, reused for this one; chord_step), ``d_prev`` (the last step's ‖Δq‖∞),
        ``nfact`` (factorisations so far), ``its`` (Newton iterations, solves, so far), ``cap`` (the
        budget), ``spare`` (1: a budget from a fresh factor is left), ``exact`` (1: the Hessian is
        assembled exact, indefinite orthogonality blocks included; from the first iteration after one
        that converged only linearly, until a factor of it breaks down, when the iteration is done
        again with the PSD Hessian, or its step's line search runs out, when the next iteration takes
        the PSD Hessian's step from the same q).  Returns (1 when the solve is over, converged or rejected, else
        0; the new state)."""
        c = clock_now()
        if wp.static(spec.exact):
            if chord <= 0:
                t.exact[w] = exact  # (every lane writes the same value; assemble reads it after a barrier)
        if wp.static(G > 1 or packed):
            # H packed (the triangle or the block band): its TRI words are one run of the column;
            # lane groups (T = 1): every group's copy of g and H, each TRI words on
            for cp in range(G):
                for i in range(lane, N, LANES):
                    g[(cp * TRI + i) * T + s] = zero
                if chord <= 0:
                    for p in range(lane, TRI, LANES):
                        H[(cp * TRI + p) * T + s] = zero
        else:
            for i in range(lane, N, LANES):
                g[i * T + s] = zero
                if chord <= 0:
                    j0 = int(0)
                    if wp.static(envelope):
                        j0 = t.first[i]
                    p = (hrow(i) + j0) * T + s
                    for j in range(j0, i + 1):
                        H[p] = zero
                        p += T
        if wp.static(lanes):
            block_sync()
        c = tick(t, w, lane, PHASE_ZERO, c)
        e0 = zero
        ok = int(0)
        gdq = zero
        dmax = zero
        g_abs = zero
        if wp.static(compact):
            # one call with the derivatives chosen at run time: a second inlined assemble
            # (gradient only) would add its whole code to the kernel again
            e0 = assemble(q, w, w, s, T, wp.where(chord > 0, GRADIENT, HESSIAN), t, g, H)
        elif chord > 0:
            e0 = assemble(q, w, w, s, T, GRADIENT, t, g, H)
        else:
            e0 = assemble(q, w, w, s, T, HESSIAN, t, g, H)
        c = tick(t, w, lane, PHASE_ASSEMBLE, c)
        if chord <= 0:
            nfact += 1
        if wp.static(warp_regs and G == 1):
            block_sync()  # the factor reads every lane's rows
            ok = regs_ldl_solve(H, g, dq, lane, wp.where(chord <= 0, 1, 0))
            c = tick(t, w, lane, PHASE_FACTOR, c)  # (the factor and the substitutions)
            if ok != 0:
                ok, gdq, dmax, g_abs = reductions(g, dq, s, N, 1)
            c = tick(t, w, lane, PHASE_SOLVE, c)
        elif wp.static(warp_regs):
            # lane groups: the first group's warp factors and solves (assemble_groups ended with a
            # barrier), and passes ok to the others through slot N + NF + G of g
            if lane < 32:
                ok = regs_ldl_solve(H, g, dq, lane, wp.where(chord <= 0, 1, 0))
                if lane == 0:
                    g[s + N + NF + G] = wp.where(ok != 0, one, zero)
            block_sync()
            ok = wp.where(g[s + N + NF + G] != zero, 1, 0)
            c = tick(t, w, lane, PHASE_FACTOR, c)
            if ok != 0:
                ok, gdq, dmax, g_abs = reductions(g, dq, s, N, 1)
            c = tick(t, w, lane, PHASE_SOLVE, c)
        elif wp.static(lanes):
            block_sync()  # the factor and the solves read every lane's rows
            ok = 1
            if chord <= 0:
                ok = ldl_lanes(H, s, lane)
            c = tick(t, w, lane, PHASE_FACTOR, c)
            if ok != 0:
                ok, gdq, dmax, g_abs = solve_lanes(H, g, dq, s, lane)
            c = tick(t, w, lane, PHASE_SOLVE, c)
        elif chord > 0:
            ok, gdq, dmax, g_abs = factored_solve(H, g, dq, s, N, T, t.first)
            c = tick(t, w, lane, PHASE_SOLVE, c)
        else:
            ok, gdq, dmax, g_abs = cholesky_solve(H, g, dq, s, N, T, t.first)
            c = tick(t, w, lane, PHASE_FACTOR, c)
        if wp.static(secant):
            if ok != 0 and chord <= 0:
                gdq, dmax = secant_step(q, t, w, g, H, dq, s, T, gdq, dmax)
                c = tick(t, w, lane, PHASE_SOLVE, c)
        if lane == 0:
            factorizations[w] = nfact
        if wp.static(spec.exact):
            if ok == 0 and exact != 0 and chord <= 0:
                return 0, chord, d_prev, nfact, its, cap, spare, 0  # the exact Hessian is not positive definite here
        stop = int(3)  # 3: the factor or the solve broke down
        if ok != 0:
            its += 1
            if lane == 0:
                iterations[w] = its
            linear = int(0)
            stop, chord, linear = take_step(q, q_trial, t, dq, g, H, w, row, s, T, e0, gdq, dmax, g_abs, threshold,
                                            chord, reuse, d_prev, max_line_search, converged, lane)  # fmt: skip
            c = tick(t, w, lane, PHASE_STEP, c)
            if wp.static(spec.exact):
                if stop == 2 and exact != 0 and its < cap:
                    # the exact Hessian's step found no decrease (its search ran out; q is unchanged):
                    # the next iteration takes R⁺'s
                    return 0, chord, d_prev, nfact, its, cap, spare, 0
                exact = wp.where(linear != 0, 1, exact)
        if stop == 1:
            return 1, chord, dmax, nfact, its, cap, spare, exact
        if stop >= 2 or its == cap:
            if spare == 0:
                if lane == 0:
                    status[w] = wp.where(stop == 3, BREAKDOWN, UNCONVERGED)
                return 1, chord, dmax, nfact, its, cap, spare, exact
            # the retry: reuse's budget spent, or its iterates broke down or stalled
            spare = 0
            chord = -1
            cap = its + max_iterations
            if lane == 0:
                t.retried[w] = 1
            for b in range(lane, q.shape[1], LANES):
                if t.dof[b] >= 0:
                    q[w, b] = t.q_tilde[w, b]
            if wp.static(lanes):
                block_sync()
        return 0, chord, dmax, nfact, its, cap, spare, exact

    return SimpleNamespace(iterate=iterate)


@functools.lru_cache(maxsize=None)
def newton(spec: KernelSpec):
    """``solve_world``: a world's whole Newton solve (see its docstring): ``open_solve``, then
    ``iteration``'s ``iterate`` until the solve is over."""
    dtype = spec.dtype
    vec12 = ops(dtype).vec12
    Terms = structs(dtype).Terms
    iterate = iteration(spec).iterate
    zero = dtype(0.0)

    @wp.func
    def open_solve(t: Terms, w: int, max_iterations: int, reuse: int, status: wp.array(dtype=wp.int32),
                   iterations: wp.array(dtype=wp.int32), factorizations: wp.array(dtype=wp.int32),
                   converged: wp.array(dtype=wp.int32), lane: int):  # fmt: skip
        """World w's counters cleared (by lane 0); (1 where its solve runs: its status is OK and the
        budget max_iterations is not empty, else 0; the solve's first state, as iterate takes it: a
        retry from q̃ left with ``reuse`` or in a scene built with ``exact``)."""
        if lane == 0:
            iterations[w] = 0
            factorizations[w] = 0
            converged[w] = 0
            t.retried[w] = 0
        solving = wp.where(status[w] == OK and max_iterations > 0, 1, 0)
        spare = reuse
        if wp.static(spec.exact):
            spare = 1
        return solving, int(0), zero, int(0), int(0), max_iterations, spare, int(0)

    @wp.func
    def solve_world(q: wp.array2d(dtype=vec12), q_trial: wp.array2d(dtype=vec12), t: Terms, g: wp.array(dtype=dtype),
                    H: wp.array(dtype=dtype), dq: wp.array(dtype=dtype), w: int, s: int, T: int, row: int, threshold: dtype,
                    max_iterations: int, max_line_search: int, reuse: int, status: wp.array(dtype=wp.int32),
                    iterations: wp.array(dtype=wp.int32), factorizations: wp.array(dtype=wp.int32),
                    converged: wp.array(dtype=wp.int32), lane: int):  # fmt: skip
        """World w's whole Newton solve, in scratch column s (of T) of the flat g, H, dq and row
        ``row`` of q_trial; lane ``lane`` of LANES (one thread per world: 0 of 1): open_solve, then
        iterate until the solve is over.

        With ``reuse``, an iteration after a full step (α = 1) keeps the Cholesky factor it left in H
        and solves only the new gradient against it (a simplified-Newton step; see ``chord_step``).
        The solve's budget is max_iterations; it also ends where the line search runs out away from
        convergence or the factor breaks down.  A solve with ``reuse`` then starts again from the
        prediction q̃ (t.q_tilde: the extrapolated guess it began from is not kept, which would cost a
        store per body every step) with max_iterations more, factoring at every one (chord −1), so
        factor reuse never commits a step that a fresh factor could not solve; so does every solve in
        a scene built with ``exact`` (a stiff joint), whose iterates from the guess can end where
        neither Hessian's step finds a decrease.  A solve that ends its
        last budget unconverged is rejected (status UNCONVERGED, or BREAKDOWN; close_world keeps qⁿ).
        The counts include the retry's iterations.  Lane-split, every lane takes every branch (each
        decides from the same sums in the same order) and lane 0 alone writes the world's counters."""
        solving, chord, d_prev, nfact, its, cap, spare, exact = open_solve(
            t, w, max_iterations, reuse, status, iterations, factorizations, converged, lane)  # fmt: skip
        over = 1 - solving
        while over == 0:
            over, chord, d_prev, nfact, its, cap, spare, exact = iterate(
                q, q_trial, t, g, H, dq, w, s, T, row, threshold, max_iterations, max_line_search, reuse, status,
                iterations, factorizations, converged, lane, chord, d_prev, nfact, its, cap, spare, exact)  # fmt: skip
        return 0

    return SimpleNamespace(solve_world=solve_world, open_solve=open_solve, iterate=iterate)
