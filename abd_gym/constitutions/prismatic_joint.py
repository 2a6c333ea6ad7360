"""Prismatic joint (libuipc UID 20), exactly the seed ``affine_body_prismatic_joint.md``.

Frame ``(c, t̂, n̂, b̂)`` captured in both bodies at creation; with ``c_k = J(c) q_k`` etc.::

    C0 = (c_j − c_i) × t̂_i      C1 = (c_i − c_j) × t̂_j
    C2 = n̂_i − n̂_j              C3 = b̂_i − b̂_j
    E  = Σ_k K/2 ‖C_k‖²  [J·s²],   K = strength_ratio·(m_i + m_j)

Gradient exact; the Hessian is the Gauss–Newton part ``K Σ ∇C_mᵀ∇C_m`` (PSD; C0 and C1 are
bilinear, and the dropped ``K Σ C_m ∇²C_m`` vanishes as the constraint is met).
"""

import functools
from types import SimpleNamespace

import numpy as np
import warp as wp

from ..core import affine
from ..core.warp_ops import HESSIAN, ops
from . import _joint_step
from .protocol import JOINT, Constitution

UID = 20
NAME = "prismatic_joint"
KIND = "prismatic"


def prismatic_joint_np(q, ci, cj, ti, tj, ni, nj, bi, bj, K):
    """Energy, gradient, exact Hessian and Gauss–Newton Hessian in the stacked pair q (float64)."""
    D = affine.on_pair(affine.J(cj), 1) - affine.on_pair(affine.J(ci), 0)
    E, g, H, Hgn = 0.0, np.zeros(24), np.zeros((24, 24)), np.zeros((24, 24))
    parts = [
        affine.cross_derivs(D, affine.on_pair(affine.Jo(ti), 0), q),
        affine.cross_derivs(-D, affine.on_pair(affine.Jo(tj), 1), q),
    ]
    for ui, uj in ((ni, nj), (bi, bj)):
        L = affine.on_pair(affine.Jo(ui), 0) - affine.on_pair(affine.Jo(uj), 1)
        parts.append((L @ q, L, np.zeros((3, 24, 24))))
    for C, jac, hes in parts:
        E += 0.5 * K * C @ C
        g += K * jac.T @ C
        Hgn += K * jac.T @ jac
        H += K * (jac.T @ jac + np.einsum("m,mab->ab", C, hes))
    return E, g, H, Hgn


@functools.lru_cache(maxsize=None)
def kernel(dtype):
    o = ops(dtype)
    joint_k = _joint_step.funcs(dtype)
    vec3, vec4, vec12, mat12 = o.vec3, o.vec4, o.vec12, o.mat12
    point, direction, JT, skew_row, kron3 = o.point, o.direction, o.JT, o.skew_row, o.kron3
    add_energy, scatter_pair = o.add_energy, o.scatter_pair
    one, zero, half = dtype(1.0), dtype(0.0), dtype(0.5)

    @wp.func
    def prismatic_grad(
        qi: vec12, qj: vec12, ci: vec3, cj: vec3, ti: vec3, tj: vec3, ni: vec3, nj: vec3, bi: vec3, bj: vec3,
        kk: dtype, derivs: int,
    ):  # fmt: skip
        """(E, g_i, g_j), the gradient for derivs != 0 (the fused step adds the Hessian straight into
        its system, without 12 × 12 blocks)."""
        d = point(qj, cj) - point(qi, ci)
        Ti = direction(qi, ti)
        Tj = direction(qj, tj)
        C0 = wp.cross(d, Ti)
        C1 = wp.cross(-d, Tj)
        C2 = direction(qi, ni) - direction(qj, nj)
        C3 = direction(qi, bi) - direction(qj, bj)
        e = half * kk * (wp.dot(C0, C0) + wp.dot(C1, C1) + wp.dot(C2, C2) + wp.dot(C3, C3))
        gi = vec12()
        gj = vec12()
        if derivs == 0:
            return e, gi, gj
        # gradient K Σ_m C_m ∇C_m in closed form: row m of ∇(d × T) is J(c)ᵀ([T]×)_m-type terms,
        # and Σ_m v_m ([t]×)_m = [t]×ᵀ v = v × t, so C0's rows sum to J(c_i)ᵀ(C0 × T_i) + J̊(t_i)ᵀ(C0 × d)
        # on body i and −J(c_j)ᵀ(C0 × T_i) on body j (C1 likewise with T_j and −d)
        a0 = wp.cross(C0, Ti)
        a1 = wp.cross(C1, Tj)
        gi = kk * (JT(ci, a0 - a1, one) + JT(ti, wp.cross(C0, d), zero) + JT(ni, C2, zero) + JT(bi, C3, zero))
        gj = kk * (JT(cj, a1 - a0, one) - JT(tj, wp.cross(C1, d), zero) - JT(nj, C2, zero) - JT(bj, C3, zero))
        return e, gi, gj

    @wp.func
    def prismatic_eval(
        qi: vec12, qj: vec12, ci: vec3, cj: vec3, ti: vec3, tj: vec3, ni: vec3, nj: vec3, bi: vec3, bj: vec3,
        kk: dtype, derivs: int, free_i: int, free_j: int,
    ):  # fmt: skip
        """(E, g_i, g_j, H_ii, H_ij, H_jj).  ``free_i`` / ``free_j`` 0: that body has no unknowns
        (the rail a slider rides on), so its blocks, which nobody reads, are left zero (for a
        cart on a fixed rail: two thirds of the slide rows' outer products)."""
        e, gi, gj = prismatic_grad(qi, qj, ci, cj, ti, tj, ni, nj, bi, bj, kk, derivs)
        hii = mat12()
        hij = mat12()
        hjj = mat12()
        if derivs != HESSIAN:
            return e, gi, gj, hii, hij, hjj
        d = point(qj, cj) - point(qi, ci)
        Ti = direction(qi, ti)
        Tj = direction(qj, tj)
        # C0, C1 (the slide direction): Gauss–Newton rows that mix p and A through cross products,
        # added one by one; C2, C3 (the frames' normal and binormal) are linear in A alone, so their
        # Hessian is K Σ (ũ_i ũ_jᵀ) ⊗ I₃ with ũ = (0, n̄) or (0, b̄), expanded once
        for c in range(2):
            for m in range(3):
                ri = JT(ci, skew_row(Ti, m), one) + JT(ti, skew_row(d, m), zero)
                rj = -JT(cj, skew_row(Ti, m), one)
                if c == 1:
                    ri = -JT(ci, skew_row(Tj, m), one)
                    rj = JT(cj, skew_row(Tj, m), one) + JT(tj, skew_row(-d, m), zero)
                kri = kk * ri
                if free_i != 0:
                    hii += wp.outer(kri, ri)
                    if free_j != 0:
                        hij += wp.outer(kri, rj)
                if free_j != 0:
                    hjj += wp.outer(kk * rj, rj)
        uni = vec4(zero, ni[0], ni[1], ni[2])
        unj = vec4(zero, nj[0], nj[1], nj[2])
        ubi = vec4(zero, bi[0], bi[1], bi[2])
        ubj = vec4(zero, bj[0], bj[1], bj[2])
        if free_i != 0:
            hii += kron3(kk * (wp.outer(uni, uni) + wp.outer(ubi, ubi)))
        if free_i != 0 and free_j != 0:
            hij += kron3(-kk * (wp.outer(uni, unj) + wp.outer(ubi, ubj)))
        if free_j != 0:
            hjj += kron3(kk * (wp.outer(unj, unj) + wp.outer(ubj, ubj)))
        return e, gi, gj, hii, hij, hjj

    @wp.kernel(module="unique")
    def prismatic_joint(
        q: wp.array2d(dtype=vec12), ids: wp.array(dtype=wp.int32),
        body_a: wp.array(dtype=wp.int32), body_b: wp.array(dtype=wp.int32), dof: wp.array(dtype=wp.int32),
        c_a: wp.array2d(dtype=vec3), c_b: wp.array2d(dtype=vec3), t_a: wp.array2d(dtype=vec3), t_b: wp.array2d(dtype=vec3),
        n_a: wp.array2d(dtype=vec3), n_b: wp.array2d(dtype=vec3), b_a: wp.array2d(dtype=vec3), b_b: wp.array2d(dtype=vec3),
        K: wp.array2d(dtype=dtype), h_step: wp.array(dtype=dtype), h_joint: dtype, active: wp.array(dtype=wp.int32),
        derivs: int, col: int, E: wp.array2d(dtype=dtype), g: wp.array2d(dtype=dtype), H: wp.array3d(dtype=dtype),
    ):  # fmt: skip
        w, k = wp.tid()
        if active[w] == 0:
            return
        j = ids[k]
        bi = body_a[j]
        bj = body_b[j]
        e, gi, gj, hii, hij, hjj = prismatic_eval(q[w, bi], q[w, bj], c_a[w, j], c_b[w, j], t_a[w, j], t_b[w, j],
                                                  n_a[w, j], n_b[w, j], b_a[w, j], b_b[w, j],
                                                  joint_k(K, h_step, h_joint, w, j), derivs,
                                                  wp.where(dof[bi] >= 0, 1, 0), wp.where(dof[bj] >= 0, 1, 0))  # fmt: skip
        add_energy(E, w, col, e)
        if derivs != 0:
            scatter_pair(g, H, w, dof[bi], dof[bj], gi, gj, hii, hij, hjj)

    return SimpleNamespace(kernel=prismatic_joint, eval=prismatic_eval, grad=prismatic_grad)


def terms(model, physical=False):
    return (NAME,) if model.joint_count[KIND] else ()


def launch(model, state, ctx, q, E, g, H, active, derivs, cols, physical=False):
    m = model
    wp.launch(kernel(m.dtype).kernel, dim=(m.num_worlds, m.joint_count[KIND]),
              inputs=[q, m.joint_ids[KIND], m.body_a, m.body_b, m.dof, m.c_a, m.c_b, m.t_a, m.t_b, m.n_a, m.n_b,
                      m.b_a, m.b_b, m.K, ctx.h_step, 0.0 if physical else ctx.h_joint, active, derivs, cols[NAME], E, g,
                      H], device=m.device)  # fmt: skip


CONSTITUTION = Constitution(NAME, UID, JOINT, prismatic_joint_np, terms, launch, work=13.0, joint=KIND)
