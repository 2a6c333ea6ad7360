"""A Newton direction that lets a limit go (``release_step``): where one limit of a world acts at
the iterate q and the solution lies inside its range, the direction is Newton's for the energy
without that limit.

A limit's one-sided cubic E(x) = s·r³ (r the overrun; revolute_limit, prismatic_limit) enters H
with its curvature E″(x)∇x∇xᵀ at q.  On the way out E″ = 6s·r falls to 0 at the bound, where the
quadratic model keeps it: Newton's step stops about halfway to the bound, and the limit is left
over several iterations, each halving the overrun (design.md §4).  Where the solution lies inside
the range the limit's energy and derivatives are 0 there, and the step to it is Newton's for the
rest of the energy, g_r = g − E′u, H_r = H − E″uuᵀ (u = ∇x).  From H's factor, by Sherman and
Morrison, with w = H⁻¹u, a = uᵀw and b = uᵀΔq (Δq = −H⁻¹g, so x moves by b):

    Δq_r = −H_r⁻¹ g_r = Δq + β w,   β = (E′ + E″ b) / (1 − E″ a),

which moves x by b_r = (b + aE′)/(1 − E″a) to first order.  The bound lies 2|E′|/E″ away from x
(E′ = ±3s·r², E″ = 6s·r, with the prismatic limit's 1/width on r), so the limit is let go where
(E″ b_r + 2E′)·sign E′ ≤ 0.  Since 0 < E″a < 1 (H_r is positive definite), b_r reaches the bound
only where Newton's own step already goes at least halfway to it, (E″ b + E′)·sign E′ ≤ 0: a world
resting on its limit fails that test and pays no more than the dot product b.  Elsewhere the
release costs one pair of triangular solves through the factor.  Δq_r descends on the whole energy
(gᵀΔq_r = gᵀΔq − βb < 0 there), and the line search takes it as any Newton step.  With more than
one limit acting the direction stays Newton's (a rank-k update would be needed).

A thread per world only: the lane-split step (small batches, where a step's time follows its
kernel's code) keeps Newton's direction, since the release's limit terms and substitutions add
20–36 KB of SASS to its kernels of scenes with limits (scripts/sass_size.py: CartPole-v0 265 →
285 KB, InvertedPendulum-v5 324 → 360 KB, SliderCrank-v0 395 → 415 KB)."""
import functools
from types import SimpleNamespace
from typing import Any

import warp as wp

from ..constitutions import prismatic_limit, revolute_limit
from ..warp_ops import GRADIENT, ops
from .layout import KernelSpec
from .structs import structs


@functools.lru_cache(maxsize=None)
def release(spec: KernelSpec):
    """``release_step(q, t, w, g, H, dq, s, T, gdq, dmax) -> (gᵀΔq, ‖Δq‖∞)``: a thread's direction in
    scratch column s (of T) after Newton's solve, H holding its factor; g is overwritten."""
    dtype, N = spec.dtype, spec.N
    NR, NP = spec.limits
    vec12 = ops(dtype).vec12
    Terms = structs(dtype).Terms
    staged = spec.staged()
    substitute, h_row, row_first = staged["substitute"], staged["h_row"], staged["row_first"]
    square_envelope = spec.envelope and not spec.packed
    rlim_parts = revolute_limit.kernel(dtype).parts
    plim_parts = prismatic_limit.kernel(dtype).parts
    zero, one, two = dtype(0.0), dtype(1.0), dtype(2.0)

    @wp.func
    def acting_limit(q: wp.array2d(dtype=vec12), t: Terms, w: int):
        """(limits acting at q[w]; the last one's E′, E″, ∇x on its two bodies and their first unknowns)."""
        acting = int(0)
        de = zero
        dde = zero
        ui = vec12()
        uj = vec12()
        oi = int(-1)
        oj = int(-1)
        for k in range(wp.static(NR)):
            j = t.rlim_ids[k]
            e, d1, d2, gi, gj = rlim_parts(q[w, t.body_a[j]], q[w, t.body_b[j]], t.n_a[w, j], t.b_a[w, j], t.n_b[w, j],
                                           t.b_b[w, j], t.theta0[w, j], t.c_prev[w, j], t.s_prev[w, j],
                                           t.rlim_lo[w, k], t.rlim_up[w, k], t.rlim_s[w, k], GRADIENT)  # fmt: skip
            if d2 > zero:
                acting += 1
                de, dde, ui, uj = d1, d2, gi, gj
                oi = int(t.dof[t.body_a[j]])
                oj = int(t.dof[t.body_b[j]])
        for k in range(wp.static(NP)):
            j = t.plim_ids[k]
            e, d1, d2, gi, gj = plim_parts(q[w, t.body_a[j]], q[w, t.body_b[j]], t.c_a[w, j], t.c_b[w, j], t.t_a[w, j],
                                           t.plim_lo[w, k], t.plim_up[w, k], t.plim_s[w, k], GRADIENT)  # fmt: skip
            if d2 > zero:
                acting += 1
                de, dde, ui, uj = d1, d2, gi, gj
                oi = int(t.dof[t.body_a[j]])
                oj = int(t.dof[t.body_b[j]])
        return acting, de, dde, ui, uj, oi, oj

    @wp.func
    def u_row(i: int, ui: vec12, uj: vec12, oi: int, oj: int):
        """Row i of u = ∇x (its two bodies' rows, 0 elsewhere)."""
        v = zero
        if oi >= 0 and i >= oi and i < oi + 12:
            v = ui[i - oi]
        if oj >= 0 and i >= oj and i < oj + 12:
            v += uj[i - oj]
        return v

    @wp.func
    def u_dot(v: Any, s: int, T: int, ui: vec12, uj: vec12, oi: int, oj: int):
        """uᵀv over v's rows in scratch column s (of T)."""
        d = zero
        if oi >= 0:
            for r in range(12):
                d += ui[r] * v[(oi + r) * T + s]
        if oj >= 0:
            for r in range(12):
                d += uj[r] * v[(oj + r) * T + s]
        return d

    @wp.func
    def solve_in_place(L: Any, v: Any, s: int, T: int, t: Terms):
        """v ← −(L Lᵀ)⁻¹v through the Cholesky factor in L, row by row within each row's stored
        columns: compact loops, where the Newton step's substitutions (solver_kernels.solve_dense,
        four rows at a time) would add ~30 KB of code for a solve that few iterations take."""
        n = t.free.shape[0] * 12  # N, read at run time: loops the compiler does not unroll
        if wp.static(square_envelope):
            substitute(L, v, v, s, N, T, t.first)
        else:
            for i in range(n):  # L y = −v
                r = h_row(i, N)
                acc = -v[i * T + s]
                for k in range(row_first(i), i):
                    acc -= L[(r + k) * T + s] * v[k * T + s]
                v[i * T + s] = acc / L[(r + i) * T + s]
            for ii in range(n):  # Lᵀ x = y, a column of Lᵀ (a row of L) at a time
                i = n - 1 - ii
                r = h_row(i, N)
                xi = v[i * T + s] / L[(r + i) * T + s]
                v[i * T + s] = xi
                for k in range(row_first(i), i):
                    v[k * T + s] = v[k * T + s] - L[(r + k) * T + s] * xi

    @wp.func
    def release_step(q: wp.array2d(dtype=vec12), t: Terms, w: int, g: Any, H: Any, dq: Any, s: int, T: int,
                     gdq: dtype, dmax: dtype):  # fmt: skip
        """(gᵀΔq, ‖Δq‖∞) of the direction in dq: Newton's (unchanged), or where the one limit acting at
        q[w] would be left, Newton's without that limit (the module's docstring)."""
        acting, de, dde, ui, uj, oi, oj = acting_limit(q, t, w)
        if acting != 1:
            return gdq, dmax
        b = u_dot(dq, s, T, ui, uj, oi, oj)
        if (dde * b + de) * wp.sign(de) > zero:
            return gdq, dmax  # Newton's step goes less than halfway to the bound: the release cannot reach it
        n = t.free.shape[0] * 12  # N, read at run time (loops not unrolled: a rare path's code kept small)
        for i in range(n):
            g[i * T + s] = u_row(i, ui, uj, oi, oj)
        solve_in_place(H, g, s, T, t)  # g = −w, w = H⁻¹u
        a = -u_dot(g, s, T, ui, uj, oi, oj)
        den = one - dde * a
        if not (den > zero):
            return gdq, dmax  # (H less the limit's part is positive definite: rounding alone gets here)
        beta = (de + dde * b) / den
        if (dde * (b + beta * a) + two * de) * wp.sign(de) > zero:
            return gdq, dmax  # the step stays on the limit
        dmax_r = zero
        for i in range(n):
            d = dq[i * T + s] - beta * g[i * T + s]
            dq[i * T + s] = d
            dmax_r = wp.max(dmax_r, wp.abs(d))
        return gdq - beta * b, dmax_r

    return SimpleNamespace(release_step=release_step)
