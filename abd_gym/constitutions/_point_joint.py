"""Shared kernel for joints made of coincident points (revolute: 2 on the axis; fixed: 4).

``E = K/2 Σ_p ‖x_i(P_p) − x_j(P_p)‖²`` with ``x_k(P) = J(P_k) q_k``: linear constraints, so
``∇E = K Σ (J(P_i)ᵀC, −J(P_j)ᵀC)`` and the Hessian ``K Σ JᵀJ`` is exact and PSD.
"""

import functools
from types import SimpleNamespace

import numpy as np
import warp as wp

from ..core import affine
from ..core.warp_ops import HESSIAN, ops
from . import _joint_step


def point_joint_np(q, points_i, points_j, K):
    """Energy, gradient, Hessian of the stacked pair q = (q_i, q_j) (float64)."""
    E, g, H = 0.0, np.zeros(24), np.zeros((24, 24))
    for pi, pj in zip(points_i, points_j):
        L = affine.on_pair(affine.J(pi), 0) - affine.on_pair(affine.J(pj), 1)
        C = L @ q
        E += 0.5 * K * C @ C
        g += K * L.T @ C
        H += K * L.T @ L
    return E, g, H


@functools.lru_cache(maxsize=None)
def kernel(dtype):
    o = ops(dtype)
    vec3, vec4, vec12, mat12, mat44 = o.vec3, o.vec4, o.vec12, o.mat12, o.mat44
    point, JT, kron3, add_energy, scatter_pair = o.point, o.JT, o.kron3, o.add_energy, o.scatter_pair
    one, half = dtype(1.0), dtype(0.5)
    joint_k = _joint_step.funcs(dtype)

    @wp.func
    def point_eval_kron(
        qi: vec12, qj: vec12, pts_a: wp.array3d(dtype=vec3), pts_b: wp.array3d(dtype=vec3), w: int, j: int,
        npts: int, kk: dtype, derivs: int,
    ):  # fmt: skip
        """Energy, gradients and the Hessian's 4 × 4 factors: H_ab = U_ab ⊗ I₃ with
        U_ij = K Σ_p ±u_i u_jᵀ, u = (1, x̄) (J = [I₃, x̄ᵀ ⊗ I₃], so J_iᵀJ_j = (u_i u_jᵀ) ⊗ I₃)."""
        e = dtype(0.0)
        gi = vec12()
        gj = vec12()
        uii = mat44()
        uij = mat44()
        ujj = mat44()
        for p in range(npts):
            xi = pts_a[w, j, p]
            xj = pts_b[w, j, p]
            C = point(qi, xi) - point(qj, xj)
            e += half * kk * wp.dot(C, C)
            if derivs != 0:
                gi += kk * JT(xi, C, one)
                gj -= kk * JT(xj, C, one)
            if derivs == HESSIAN:
                ui = vec4(one, xi[0], xi[1], xi[2])
                uj = vec4(one, xj[0], xj[1], xj[2])
                uii += wp.outer(ui, ui)
                uij += wp.outer(ui, uj)
                ujj += wp.outer(uj, uj)
        return e, gi, gj, kk * uii, -kk * uij, kk * ujj

    @wp.func
    def point_eval(
        qi: vec12, qj: vec12, pts_a: wp.array3d(dtype=vec3), pts_b: wp.array3d(dtype=vec3), w: int, j: int,
        npts: int, kk: dtype, derivs: int,
    ):  # fmt: skip
        """Energy, gradients and 12 × 12 Hessian blocks (the factors of point_eval_kron, expanded)."""
        e, gi, gj, uii, uij, ujj = point_eval_kron(qi, qj, pts_a, pts_b, w, j, npts, kk, derivs)
        hii = mat12()
        hij = mat12()
        hjj = mat12()
        if derivs == HESSIAN:
            hii = kron3(uii)
            hij = kron3(uij)
            hjj = kron3(ujj)
        return e, gi, gj, hii, hij, hjj

    @wp.kernel(module="unique")
    def point_joint(
        q: wp.array2d(dtype=vec12), ids: wp.array(dtype=wp.int32),
        body_a: wp.array(dtype=wp.int32), body_b: wp.array(dtype=wp.int32), dof: wp.array(dtype=wp.int32),
        pts_a: wp.array3d(dtype=vec3), pts_b: wp.array3d(dtype=vec3), npts: int, K: wp.array2d(dtype=dtype),
        h_step: wp.array(dtype=dtype), h_joint: dtype, active: wp.array(dtype=wp.int32), derivs: int, col: int,
        E: wp.array2d(dtype=dtype), g: wp.array2d(dtype=dtype), H: wp.array3d(dtype=dtype),
    ):  # fmt: skip
        w, k = wp.tid()
        if active[w] == 0:
            return
        j = ids[k]
        bi = body_a[j]
        bj = body_b[j]
        e, gi, gj, hii, hij, hjj = point_eval(q[w, bi], q[w, bj], pts_a, pts_b, w, j, npts,
                                              joint_k(K, h_step, h_joint, w, j), derivs)  # fmt: skip
        add_energy(E, w, col, e)
        if derivs != 0:
            scatter_pair(g, H, w, dof[bi], dof[bj], gi, gj, hii, hij, hjj)

    return SimpleNamespace(kernel=point_joint, eval=point_eval, eval_kron=point_eval_kron)


def launch_points(model, ctx, kind, npts, q, E, g, H, active, derivs, col, physical):
    """The point joints of ``kind``; in a step (not ``physical``), each world's K for its step's
    length (_joint_step)."""
    wp.launch(kernel(model.dtype).kernel, dim=(model.num_worlds, model.joint_count[kind]),
              inputs=[q, model.joint_ids[kind], model.body_a, model.body_b, model.dof, model.pts_a, model.pts_b,
                      npts, model.K, ctx.h_step, 0.0 if physical else ctx.h_joint, active, derivs, col, E, g, H],
              device=model.device)  # fmt: skip
