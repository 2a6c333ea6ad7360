"""Adding a term's gradient and Hessian blocks to a world's scratch column (s of B) of g and H,
lower triangle only (all the factor reads), each entry formed as it is added: no 12 × 12 block is
built in a thread's local memory.

- body b (unknowns from o): m on the translation diagonal, its first moments c = m c̄ [kg·m]
  below it, and the A rows' 3 × 3 blocks (``affine_body.a_block``): 57 entries of 78;
- Kronecker blocks U ⊗ I₃ of the point joints (entry (kron_index(m, c), kron_index(m, d)) =
  U[c, d]), 48 non-zero entries of 144;
- the prismatic joint's Gauss–Newton blocks (ua ubᵀ) ⊗ Pcc + (ua tbᵀ) ⊗ Pct + (ta ubᵀ) ⊗ Ptc
  + (ta tbᵀ) ⊗ Ptt + U ⊗ I₃;
- a term E(x) of a scalar coordinate x (a limit, a drive): E′∇x and E″∇x∇xᵀ (rank one).

With lanes, a lane adds its own rows only (``own_from``), so a block's entries go in RL rows at
once without atomics.  ``compact`` (lanes): a term's blocks in loops of selected arguments, so each
put is inlined once."""
import functools
from types import SimpleNamespace
from typing import Any

import warp as wp

from ...constitutions import affine_body
from ...core.warp_ops import HESSIAN, body_dofs, ops
from .layout import KernelSpec, indexing


@functools.lru_cache(maxsize=None)
def puts(spec: KernelSpec):
    """The functions that add a term's gradient and Hessian blocks to a scratch column (s of B) of
    g and H, each thread (lane) its own rows (own_from): ``put_grad``, ``put_body``, ``body_row``,
    ``put_kron_pair``, ``put_outer_pair``, ``put_rank1``, and ``kron_split`` (``body_puts`` and
    ``pair_puts``)."""
    b, p = body_puts(spec), pair_puts(spec)
    return SimpleNamespace(kron_split=p.kron_split, put_grad=p.put_grad, body_row=b.body_row, put_body=b.put_body,
                           put_kron_pair=p.put_kron_pair, put_rank1=p.put_rank1, put_outer_pair=p.put_outer_pair)


@functools.lru_cache(maxsize=None)
def body_puts(spec: KernelSpec):
    """``put_body``: a body's Hessian added from its parts (``affine_body.hessian_parts``,
    ``a_block``), and ``body_row``, one row of it for a lane."""
    dtype = spec.dtype
    o = ops(dtype)
    vec3, vec12, mat33 = o.vec3, o.vec12, o.mat33
    bd = body_dofs(spec.axis)  # a body's D unknowns: entry r of its q is unknown slot(r) (−1: held), u moves sel(u)
    D, slot, sel, AXIS = bd.D, bd.slot, bd.sel, bd.axis
    hessian_parts, a_block = affine_body.kernels(dtype).hessian_parts, affine_body.kernels(dtype).a_block
    hrow = indexing(spec).hrow

    @wp.func
    def body_row(H: Any, s: int, B: int, o: int, u: int, qb: vec12, m: dtype, c: vec3, S: mat33, ks: dtype, Rp: mat33,
                 ata: mat33):  # fmt: skip
        """Row u of body o's Hessian (put_body's entries of that row, lower triangle), for a lane."""
        p = hrow(o + u) + o
        r = sel(u)
        if r < 3:
            H[(p + u) * B + s] = H[(p + u) * B + s] + m
        else:
            kk = (r - 3) // 3
            a = (r - 3) % 3
            pk = slot(kk)
            if pk >= 0:
                H[(p + pk) * B + s] = H[(p + pk) * B + s] + c[a]
            for ll in range(kk + 1):
                if slot(3 + 3 * ll + a) >= 0 or wp.static(D == 12):
                    blk = a_block(qb, kk, ll, Rp, ata, ks, S)
                    for bb in range(3):
                        cu = slot(3 + 3 * ll + bb)
                        if cu >= 0 and (kk != ll or bb <= a):
                            q = (p + cu) * B + s
                            H[q] = H[q] + blk[a, bb]

    @wp.func
    def put_body(H: Any, s: int, B: int, o: int, qb: vec12, m: dtype, c: vec3, S: mat33, ks: dtype, exact: int):
        """Body o's Hessian (affine_body.body_eval's h) added to the lower triangle from its parts,
        without building the 12 × 12 matrix in the thread's local memory: m on the translation
        diagonal, the first moments c below it, and the A rows' 3 × 3 blocks (a_block), 57
        entries where the dense block's lower triangle has 78.  (Lanes add bodies by rows: lane_bodies.)"""
        if o >= 0:
            Rp, ata = hessian_parts(qb, exact)
            if wp.static(D == 12):
                for r in range(3):
                    p = (hrow(o + r) + o + r) * B + s
                    H[p] = H[p] + m
                    for a in range(3):
                        p = (hrow(o + 3 + 3 * r + a) + o + r) * B + s
                        H[p] = H[p] + c[a]
                for kk in range(3):
                    for ll in range(kk + 1):
                        blk = a_block(qb, kk, ll, Rp, ata, ks, S)
                        for a in range(3):
                            p = (hrow(o + 3 + 3 * kk + a) + o + 3 + 3 * ll) * B + s
                            for bb in range(3):
                                if kk != ll or bb <= a:
                                    H[p] = H[p] + blk[a, bb]
                                p += B
            else:  # the in-plane rows and columns only (the held ones' blocks are never formed)
                for r in range(3):
                    ur = slot(r)
                    if ur >= 0:
                        p = (hrow(o + ur) + o + ur) * B + s
                        H[p] = H[p] + m
                        for a in range(3):
                            ua = slot(3 + 3 * r + a)
                            if ua >= 0:
                                p = (hrow(o + ua) + o + ur) * B + s
                                H[p] = H[p] + c[a]
                for kk in range(3):
                    if kk != AXIS:
                        for ll in range(kk + 1):
                            if ll != AXIS:
                                blk = a_block(qb, kk, ll, Rp, ata, ks, S)
                                for a in range(3):
                                    ua = slot(3 + 3 * kk + a)
                                    if ua >= 0:
                                        for bb in range(3):
                                            ub = slot(3 + 3 * ll + bb)
                                            if ub >= 0 and (kk != ll or bb <= a):
                                                p = (hrow(o + ua) + o + ub) * B + s
                                                H[p] = H[p] + blk[a, bb]

    return SimpleNamespace(body_row=body_row, put_body=put_body)


@functools.lru_cache(maxsize=None)
def pair_puts(spec: KernelSpec):
    """The blocks of a term on a pair of bodies, each thread (lane) its own rows (own_from):
    ``put_grad``, the point joints' Kronecker blocks (``put_kron_pair``) and a scalar coordinate's
    rank-one blocks (``put_rank1``, ``put_outer_pair``)."""
    dtype, RL, compact = spec.dtype, spec.RL, spec.compact
    o = ops(dtype)
    vec12, mat44 = o.vec12, o.mat44
    kron_index = o.kron_index
    bd = body_dofs(spec.axis)
    D, slot, sel = bd.D, bd.slot, bd.sel
    at = indexing(spec)
    hrow, own_from = at.hrow, at.own_from
    zero = dtype(0.0)

    @wp.func
    def kron_split(a: int):
        """(m, c) with kron_index(m, c) = a: component m, factor c of u = (1, x̄)."""
        if a < 3:
            return a, 0
        return (a - 3) // 3, (a - 3) % 3 + 1

    @wp.func
    def put_grad(g: Any, s: int, B: int, o: int, v: vec12):
        if o >= 0:
            for u in range(own_from(o), D, RL):
                p = (o + u) * B + s
                g[p] = g[p] + v[sel(u)]

    @wp.func
    def kron_rows(H: Any, s: int, B: int, oa: int, ob: int, U: mat44):
        """Block (oa, ob), oa ≥ ob, += U ⊗ I₃ (a diagonal block's lower half), this thread's rows:
        row kron_index(m, c) holds U[c, d] at columns kron_index(m, d)."""
        for ua in range(own_from(oa), D, RL):
            m, c = kron_split(sel(ua))
            for d in range(4):
                ub = slot(kron_index(m, d))
                if ub >= 0 and (oa > ob or ub <= ua):
                    p = (hrow(oa + ua) + ob + ub) * B + s
                    H[p] = H[p] + U[c, d]

    @wp.func
    def put_kron(H: Any, s: int, B: int, oa: int, ob: int, U: mat44):
        """Block (oa, ob) = U ⊗ I₃ (see warp_ops.kron3): its 48 non-zero entries only; above the
        diagonal as its transpose below it (lower triangle only, all the factor reads)."""
        if oa >= 0 and ob >= 0:
            if wp.static(compact):  # selects, not branches: one inlined kron_rows
                sw = oa < ob
                kron_rows(H, s, B, wp.max(oa, ob), wp.min(oa, ob), wp.where(sw, wp.transpose(U), U))
            elif oa < ob:
                kron_rows(H, s, B, ob, oa, wp.transpose(U))
            else:
                kron_rows(H, s, B, oa, ob, U)

    @wp.func
    def put_kron_pair(g: Any, H: Any, s: int, B: int, derivs: int, oi: int, oj: int, gi: vec12, gj: vec12,
                      uii: mat44, uij: mat44, ujj: mat44):  # fmt: skip
        put_grad(g, s, B, oi, gi)
        put_grad(g, s, B, oj, gj)
        if derivs == HESSIAN:
            if wp.static(compact):
                for blk in range(3):  # (i, i), (i, j), (j, j): a loop, so one inlined put_kron
                    put_kron(H, s, B, wp.where(blk < 2, oi, oj), wp.where(blk == 0, oi, oj),
                             wp.where(blk == 0, uii, wp.where(blk == 1, uij, ujj)))  # fmt: skip
            else:
                put_kron(H, s, B, oi, oi, uii)
                put_kron(H, s, B, oi, oj, uij)
                put_kron(H, s, B, oj, oj, ujj)

    @wp.func
    def outer_rows(H: Any, s: int, B: int, oa: int, ob: int, ga: vec12, gb: vec12, cf: dtype):
        """Block (oa, ob), oa ≥ ob, += cf·ga gbᵀ (a diagonal block's lower half), this thread's rows."""
        for u in range(own_from(oa), D, RL):
            p = (hrow(oa + u) + ob) * B + s
            v = cf * ga[sel(u)]
            for c in range(D):
                if oa != ob or c <= u:
                    H[p] = H[p] + v * gb[sel(c)]
                p += B

    @wp.func
    def put_outer(H: Any, s: int, B: int, oa: int, ob: int, ga: vec12, gb: vec12, cf: dtype):
        """Add block (oa, ob) = cf·ga gbᵀ and its transpose, lower triangle only (all the Cholesky
        reads): a diagonal block's lower half; (oa, ob) below the diagonal as it is, above it
        transposed.  Each entry is formed as it is added (no 12 × 12 matrix in local memory)."""
        if oa >= 0 and ob >= 0:
            if wp.static(compact):  # selects, not branches: one inlined outer_rows
                sw = oa < ob
                outer_rows(H, s, B, wp.max(oa, ob), wp.min(oa, ob), wp.where(sw, gb, ga), wp.where(sw, ga, gb), cf)
            elif oa < ob:
                outer_rows(H, s, B, ob, oa, gb, ga, cf)
            else:
                outer_rows(H, s, B, oa, ob, ga, gb, cf)

    @wp.func
    def put_rank1(g: Any, H: Any, s: int, B: int, derivs: int, oi: int, oj: int, gi: vec12, gj: vec12, de: dtype,
                  dde: dtype):  # fmt: skip
        """A term E(x) of a scalar joint coordinate x (a limit, a drive), ∇x = (gi, gj): its gradient
        E'∇x and, for HESSIAN where E'' ≠ 0, its Hessian E''∇x∇xᵀ (outer_blocks' blocks)."""
        if derivs != 0:
            put_grad(g, s, B, oi, de * gi)
            put_grad(g, s, B, oj, de * gj)
            if derivs == HESSIAN and dde != zero:
                put_outer_pair(H, s, B, oi, oj, gi, gj, dde)

    @wp.func
    def put_outer_pair(H: Any, s: int, B: int, oi: int, oj: int, gi: vec12, gj: vec12, dde: dtype):
        """The Hessian E''∇x∇xᵀ of a term of a scalar x, ∇x = (gi, gj): its blocks (i, i), (i, j), (j, j)."""
        if wp.static(compact):
            for blk in range(3):  # (i, i), (i, j), (j, j): a loop, so one inlined put_outer
                put_outer(H, s, B, wp.where(blk < 2, oi, oj), wp.where(blk == 0, oi, oj),
                          wp.where(blk < 2, gi, gj), wp.where(blk == 0, gi, gj), dde)  # fmt: skip
        else:
            put_outer(H, s, B, oi, oi, gi, gi, dde)
            put_outer(H, s, B, oi, oj, gi, gj, dde)
            put_outer(H, s, B, oj, oj, gj, gj, dde)

    return SimpleNamespace(kron_split=kron_split, put_grad=put_grad, put_kron_pair=put_kron_pair,
                           put_rank1=put_rank1, put_outer_pair=put_outer_pair)


@functools.lru_cache(maxsize=None)
def prismatic_puts(spec: KernelSpec):
    """``prismatic_hessian``: a prismatic joint's Gauss–Newton Hessian blocks, added entry by entry
    (``put_ksum``)."""
    dtype, RL, compact = spec.dtype, spec.RL, spec.compact
    o = ops(dtype)
    vec3, vec4, vec12, mat33, mat44 = o.vec3, o.vec4, o.vec12, o.mat33, o.mat44
    kron_index = o.kron_index
    at = indexing(spec)
    hrow, own_from = at.hrow, at.own_from
    kron_split = puts(spec).kron_split
    bd = body_dofs(spec.axis)
    D, slot, sel = bd.D, bd.slot, bd.sel
    zero, one = dtype(0.0), dtype(1.0)

    @wp.func
    def cross_gram(x: vec3, y: vec3):
        """Σ_m (row m of [x]×)ᵀ(row m of [y]×) = [x]×ᵀ[y]× = (x·y) I − y xᵀ."""
        return wp.dot(x, y) * wp.identity(3, dtype) - wp.outer(y, x)

    @wp.func
    def ksum_rows(H: Any, s: int, B: int, oa: int, ob: int, ua: vec4, ta: vec4, ub: vec4, tb: vec4, Pcc: mat33,
                  Pct: mat33, Ptc: mat33, Ptt: mat33, U: mat44):  # fmt: skip
        """put_ksum's block (oa, ob), oa ≥ ob, this thread's rows."""
        for ra in range(own_from(oa), D, RL):
            al, a = kron_split(sel(ra))
            for b in range(4):
                cc = ua[a] * ub[b]
                ct = ua[a] * tb[b]
                tc = ta[a] * ub[b]
                tt = ta[a] * tb[b]
                for be in range(3):
                    cb = slot(kron_index(be, b))
                    if cb >= 0 and (oa > ob or cb <= ra):
                        v = cc * Pcc[al, be] + ct * Pct[al, be] + tc * Ptc[al, be] + tt * Ptt[al, be]
                        if al == be:
                            v += U[a, b]
                        p = (hrow(oa + ra) + ob + cb) * B + s
                        H[p] = H[p] + v

    @wp.func
    def put_ksum(H: Any, s: int, B: int, oa: int, ob: int, ua: vec4, ta: vec4, ub: vec4, tb: vec4, Pcc: mat33,
                 Pct: mat33, Ptc: mat33, Ptt: mat33, U: mat44):  # fmt: skip
        """Add block (oa, ob) = (ua ubᵀ) ⊗ Pcc + (ua tbᵀ) ⊗ Pct + (ta ubᵀ) ⊗ Ptc + (ta tbᵀ) ⊗ Ptt
        + U ⊗ I₃
        (entry (kron_index(α, a), kron_index(β, b)) = Σ u[a] v[b] P[α, β] + δ_αβ U[a, b]), lower
        triangle only as put_outer: the Gauss–Newton block of rows J(x)ᵀ-type Kronecker products
        (prismatic_hessian), summed per entry in registers, without a 12 × 12 matrix.  Above the
        diagonal as the transpose, (ub uaᵀ) ⊗ Pccᵀ + (ub taᵀ) ⊗ Ptcᵀ + (tb uaᵀ) ⊗ Pctᵀ + …, below it."""
        if oa >= 0 and ob >= 0:
            if wp.static(compact):  # selects, not branches: one inlined ksum_rows
                sw = oa < ob
                ksum_rows(H, s, B, wp.max(oa, ob), wp.min(oa, ob), wp.where(sw, ub, ua), wp.where(sw, tb, ta),
                          wp.where(sw, ua, ub), wp.where(sw, ta, tb), wp.where(sw, wp.transpose(Pcc), Pcc),
                          wp.where(sw, wp.transpose(Ptc), Pct), wp.where(sw, wp.transpose(Pct), Ptc),
                          wp.where(sw, wp.transpose(Ptt), Ptt), wp.where(sw, wp.transpose(U), U))  # fmt: skip
            elif oa < ob:
                ksum_rows(H, s, B, ob, oa, ub, tb, ua, ta, wp.transpose(Pcc), wp.transpose(Ptc), wp.transpose(Pct),
                          wp.transpose(Ptt), wp.transpose(U))  # fmt: skip
            else:
                ksum_rows(H, s, B, oa, ob, ua, ta, ub, tb, Pcc, Pct, Ptc, Ptt, U)

    @wp.func
    def prismatic_hessian(H: Any, s: int, B: int, oi: int, oj: int, qi: vec12, qj: vec12, ci: vec3, cj: vec3, ti: vec3,
                          tj: vec3, ni: vec3, nj: vec3, bi: vec3, bj: vec3, kk: dtype):  # fmt: skip
        """The prismatic joint's Gauss–Newton Hessian (prismatic_joint.prismatic_eval's blocks) added
        straight into H.  Its rows are Kronecker products: C0's row m is J(c_i)ᵀ([T_i]×)_m +
        J̊(t_i)ᵀ([d]×)_m on body i and J(c_j)ᵀ([−T_i]×)_m on body j (C1's likewise), so Σ_m of their
        outer products is (ũ ũ'ᵀ) ⊗ [x]×ᵀ[y]× summed over the pairs of terms, ũ = (1, c̄) or (0, t̄);
        C2, C3 add (ũn ũnᵀ + ũb ũbᵀ) ⊗ I₃ as in prismatic_eval."""
        d = o.point(qj, cj) - o.point(qi, ci)
        Ti = o.direction(qi, ti)
        Tj = o.direction(qj, tj)
        uci = vec4(one, ci[0], ci[1], ci[2])
        uti = vec4(zero, ti[0], ti[1], ti[2])
        ucj = vec4(one, cj[0], cj[1], cj[2])
        utj = vec4(zero, tj[0], tj[1], tj[2])
        uni = vec4(zero, ni[0], ni[1], ni[2])
        unj = vec4(zero, nj[0], nj[1], nj[2])
        ubi = vec4(zero, bi[0], bi[1], bi[2])
        ubj = vec4(zero, bj[0], bj[1], bj[2])
        PT = kk * (cross_gram(Ti, Ti) + cross_gram(Tj, Tj))
        Pdd = kk * cross_gram(d, d)
        if wp.static(compact):
            # blocks (i, i), (j, j), (i, j) in a loop of selected arguments: one inlined put_ksum
            # where three calls inlined three (put_ksum skips a block of a fixed body, oi or oj < 0)
            for blk in range(3):
                ra = blk != 1  # the block's rows are body i's (else j's); its columns body i's for blk 0
                cb = blk == 0
                Pct = kk * cross_gram(wp.where(blk == 0, Ti, Tj), d)
                Ptc = kk * cross_gram(d, wp.where(blk == 1, Tj, Ti))
                U = wp.outer(wp.where(ra, uni, unj), wp.where(cb, uni, unj)) + wp.outer(wp.where(ra, ubi, ubj),
                                                                                       wp.where(cb, ubi, ubj))  # fmt: skip
                put_ksum(H, s, B, wp.where(ra, oi, oj), wp.where(cb, oi, oj), wp.where(ra, uci, ucj),
                         wp.where(ra, uti, utj), wp.where(cb, uci, ucj), wp.where(cb, uti, utj),
                         wp.where(blk == 2, -PT, PT), wp.where(blk == 1, -Pct, Pct), wp.where(blk == 0, Ptc, -Ptc),
                         wp.where(blk == 2, mat33(), Pdd), wp.where(blk == 2, -kk * U, kk * U))  # fmt: skip
        else:
            if oi >= 0:
                put_ksum(H, s, B, oi, oi, uci, uti, uci, uti, PT, kk * cross_gram(Ti, d), kk * cross_gram(d, Ti), Pdd,
                         kk * (wp.outer(uni, uni) + wp.outer(ubi, ubi)))  # fmt: skip
            if oj >= 0:
                put_ksum(H, s, B, oj, oj, ucj, utj, ucj, utj, PT, -kk * cross_gram(Tj, d), -kk * cross_gram(d, Tj), Pdd,
                         kk * (wp.outer(unj, unj) + wp.outer(ubj, ubj)))  # fmt: skip
            if oi >= 0 and oj >= 0:
                put_ksum(H, s, B, oi, oj, uci, uti, ucj, utj, -PT, kk * cross_gram(Tj, d), -kk * cross_gram(d, Ti),
                         mat33(), -kk * (wp.outer(uni, unj) + wp.outer(ubi, ubj)))  # fmt: skip

    return SimpleNamespace(prismatic_hessian=prismatic_hessian)
