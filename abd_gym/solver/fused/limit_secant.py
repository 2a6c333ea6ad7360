"""The Newton direction at an acting limit (``secant_step``): the limit's curvature taken as its
secant to where the step puts the coordinate, or the limit left out where the solution lies
inside its range.

A limit's one-sided cubic E(x) = s·r³ (r the overrun; revolute_limit, prismatic_limit) enters H
with its curvature E″ = 6s·r at the iterate q (times the prismatic limit's 1/w², r in units of
its width w).  Newton's model keeps that curvature along the step.  Where the overrun shrinks,
the cubic softens on the way, the model is too stiff, and each step goes about halfway: from r₀
far past the solution's r*, Newton on the cubic converges at rate 1/2 (r ← r/2 + r*²/2r); on
the way out of a limit, the same halving never reaches the bound.  Where the overrun grows, the
model is too soft and overshoots.  With u = ∇x, w = H⁻¹u, a = uᵀw (the coordinate's compliance,
0 < E″a < 1) and b = uᵀΔq (Newton's move of x), a rank-one change of the limit's curvature to
E″ − δ moves x by b/(1 − δa) (Sherman and Morrison):

    Δq′ = Δq + γ w,   γ = δb / (1 − δa).

The secant curvature from the overrun R₀ = 2|E′|/E″ (in x's unit) to R₀ − Y is E″(2R₀ − Y)/2R₀,
so δ = E″Y/2R₀, and the move it makes is consistent where (E″a/2R₀)Y² − Y + D = 0, D = −b·sign E′
being Newton's own move towards the bound:

    Y = 2D / (1 + √(1 − 2E″aD/R₀)).

For a cubic against a constant load this lands on r* in one step.  Where the root is not real or
lies past the bound (Y > R₀), the model has no solution on the limit, and the step is Newton's
for the energy without it, g_r = g − E′u, H_r = H − E″uuᵀ: γ = (E′ + E″b)/(1 − E″a), which moves
x by (b + aE′)/(1 − E″a); it is taken where that lands inside the range,
(E″(b + γa) + 2E′)·sign E′ ≤ 0.  Either direction is −H′⁻¹g for a positive definite H′ (the
secant's curvature is at least E″/2), so it descends on the whole energy (gᵀΔq′ = gᵀΔq − γb), and
the line search takes it as any Newton step.  Where Newton's move is under an eighth of the
overrun (a world resting on its limit), the secant's curvature is within 6% of Newton's and the
direction stays Newton's, at the cost of the dot product b; elsewhere it costs one more pair of
triangular solves.  With more than one limit acting the direction stays Newton's (a rank-k update
would be needed).

Where it runs (ExecutionPlan.limit_secant, KernelSpec.secant): it saves iterations in the worlds
that strike and leave limits, which at a batch of about a world a resident thread set a step's
length; it costs every iteration of every world the acting limits' check, which at batches of many
worlds a thread, where the queue evens the worlds' iterations out, is a loss (the plan rule and
its measurement: docs/performance.md, results/limit_secant_h200.json).  The lane-split step keeps
Newton's direction: the secant enlarges the code of its kernels of scenes with limits, and at
the small batches it runs a step's time follows its code (scripts/sass_size.py measures it)."""
import functools
from types import SimpleNamespace
from typing import Any

import warp as wp

from ...constitutions import prismatic_limit, revolute_limit
from ...core.warp_ops import GRADIENT, body_dofs, ops
from .layout import KernelSpec
from .structs import structs


@functools.lru_cache(maxsize=None)
def acting_limits(spec: KernelSpec):
    """``acting_limit``: how many of a world's limits act at its q, and the last one's derivatives
    and gradient ∇x (the secant's rank-one change of H)."""
    dtype = spec.dtype
    NR, NP = spec.limits
    vec12 = ops(dtype).vec12
    Terms = structs(dtype).Terms
    rlim_parts = revolute_limit.kernel(dtype).parts
    plim_parts = prismatic_limit.kernel(dtype).parts
    zero = dtype(0.0)

    @wp.func
    def acting_limit(q: wp.array2d(dtype=vec12), t: Terms, w: int):
        """(limits acting at q[w]; the last one's E′, E″, ∇x on its two bodies and their first unknowns)."""
        acting = int(0)
        de = zero
        dde = zero
        ui = vec12()
        uj = vec12()
        ja = int(0)  # its joint
        for k in range(wp.static(NR)):
            j = t.rlim_ids[k]
            e, d1, d2, gi, gj = rlim_parts(q[w, t.body_a[j]], q[w, t.body_b[j]], t.n_a[w, j], t.b_a[w, j], t.n_b[w, j],
                                           t.b_b[w, j], t.theta0[w, j], t.c_prev[w, j], t.s_prev[w, j],
                                           t.rlim_lo[w, k], t.rlim_up[w, k], t.rlim_s[w, k], GRADIENT)  # fmt: skip
            if d2 > zero:
                acting += 1
                de, dde, ui, uj, ja = d1, d2, gi, gj, j
        for k in range(wp.static(NP)):
            j = t.plim_ids[k]
            e, d1, d2, gi, gj = plim_parts(q[w, t.body_a[j]], q[w, t.body_b[j]], t.c_a[w, j], t.c_b[w, j], t.t_a[w, j],
                                           t.plim_lo[w, k], t.plim_up[w, k], t.plim_s[w, k], GRADIENT)  # fmt: skip
            if d2 > zero:
                acting += 1
                de, dde, ui, uj, ja = d1, d2, gi, gj, j
        return acting, de, dde, ui, uj, int(t.dof[t.body_a[ja]]), int(t.dof[t.body_b[ja]])

    return SimpleNamespace(acting_limit=acting_limit)


@functools.lru_cache(maxsize=None)
def limit_secant(spec: KernelSpec):
    """``secant_step(q, t, w, g, H, dq, s, T, gdq, dmax) -> (gᵀΔq, ‖Δq‖∞)``: a thread's direction in
    scratch column s (of T) after Newton's solve, H holding its factor; g is overwritten."""
    dtype, N = spec.dtype, spec.N
    vec12 = ops(dtype).vec12
    bd = body_dofs(spec.axis)
    D, sel = bd.D, bd.sel
    Terms = structs(dtype).Terms
    staged = spec.staged()
    h_row, row_first = staged["h_row"], staged["row_first"]
    square_envelope = spec.envelope and not spec.packed  # H square, each row from Terms.first
    acting_limit = acting_limits(spec).acting_limit
    zero, one, two, eighth = dtype(0.0), dtype(1.0), dtype(2.0), dtype(0.125)

    @wp.func
    def u_row(i: int, ui: vec12, uj: vec12, oi: int, oj: int):
        """Row i of u = ∇x (its two bodies' rows, 0 elsewhere)."""
        v = zero
        if oi >= 0 and i >= oi and i < oi + D:
            v = ui[sel(i - oi)]
        if oj >= 0 and i >= oj and i < oj + D:
            v += uj[sel(i - oj)]
        return v

    @wp.func
    def u_dot(v: Any, s: int, T: int, ui: vec12, uj: vec12, oi: int, oj: int):
        """uᵀv over v's rows in scratch column s (of T)."""
        d = zero
        if oi >= 0:
            for u in range(D):
                d += ui[sel(u)] * v[(oi + u) * T + s]
        if oj >= 0:
            for u in range(D):
                d += uj[sel(u)] * v[(oj + u) * T + s]
        return d

    @wp.func
    def first_column(t: Terms, i: int):
        """The first column row i of the factor stores (the solves skip only exact zeros left of it)."""
        if wp.static(square_envelope):
            return t.first[i]
        return row_first(i)

    @wp.func
    def solve_in_place(L: Any, v: Any, s: int, T: int, t: Terms, n: int):
        """v ← −(L Lᵀ)⁻¹v through the Cholesky factor in L (n = N rows, read at run time), row by row
        within each row's stored columns: compact loops, where the Newton step's substitutions
        (solver.kernels' solve_dense, four rows at a time) would add their unrolled code to the
        kernel for a solve that few iterations take."""
        for i in range(n):  # L y = −v
            r = h_row(i, N)
            acc = -v[i * T + s]
            for k in range(first_column(t, i), i):
                acc -= L[(r + k) * T + s] * v[k * T + s]
            v[i * T + s] = acc / L[(r + i) * T + s]
        for ii in range(n):  # Lᵀ x = y, a column of Lᵀ (a row of L) at a time
            i = n - 1 - ii
            r = h_row(i, N)
            xi = v[i * T + s] / L[(r + i) * T + s]
            v[i * T + s] = xi
            for k in range(first_column(t, i), i):
                v[k * T + s] = v[k * T + s] - L[(r + k) * T + s] * xi

    @wp.func
    def secant_step(q: wp.array2d(dtype=vec12), t: Terms, w: int, g: Any, H: Any, dq: Any, s: int, T: int,
                     gdq: dtype, dmax: dtype):  # fmt: skip
        """(gᵀΔq, ‖Δq‖∞) of the direction in dq: Newton's (unchanged), or where the one limit acting at
        q[w] moves by more than an eighth of its overrun, Newton's with that limit's curvature its
        secant to where the step puts it, or without the limit where that lies inside the range
        (the module's docstring)."""
        acting, de, dde, ui, uj, oi, oj = acting_limit(q, t, w)
        if acting != 1:
            return gdq, dmax
        b = u_dot(dq, s, T, ui, uj, oi, oj)
        sg = wp.sign(de)
        r0 = two * de / dde * sg  # the overrun [x's unit], E′ = ±3s·r², E″ = 6s·r (× the width's 1/w, 1/w²)
        d1 = -sg * b  # how far Newton's step moves x towards the bound
        if wp.abs(d1) <= eighth * r0:
            return gdq, dmax  # the secant's curvature is within 6% of Newton's
        n = t.free.shape[0] * D  # the bodies' rows (N less its padding), read at run time (loops not unrolled: a rare path's code kept small)
        for i in range(n):
            g[i * T + s] = u_row(i, ui, uj, oi, oj)
        solve_in_place(H, g, s, T, t, n)  # g = −w, w = H⁻¹u
        a = -u_dot(g, s, T, ui, uj, oi, oj)
        if not (dde * a < one):
            return gdq, dmax  # (H less the limit's part is positive definite: rounding alone gets here)
        gamma = zero  # Δq += γ w
        y = two * r0  # the secant's move towards the bound (past it: none on the limit)
        disc = one - two * dde * a * d1 / r0
        if disc >= zero:
            y = two * d1 / (one + wp.sqrt(disc))
        if y <= r0:
            delta = dde * y / (two * r0)  # E″ less the secant's curvature (at least E″/2 stays)
            gamma = delta * b / (one - delta * a)
        else:
            gamma = (de + dde * b) / (one - dde * a)  # without the limit
            if (dde * (b + gamma * a) + two * de) * sg > zero:
                return gdq, dmax  # its first-order move stays on the limit: Newton's direction
        dmax_r = zero
        for i in range(n):
            d = dq[i * T + s] - gamma * g[i * T + s]
            dq[i * T + s] = d
            dmax_r = wp.max(dmax_r, wp.abs(d))
        return gdq - gamma * b, dmax_r

    return SimpleNamespace(secant_step=secant_step)
