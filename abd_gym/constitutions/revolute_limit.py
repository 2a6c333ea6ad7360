"""Revolute joint limit (libuipc UID 670), exactly the seed ``affine_body_revolute_joint_limit.md``.

``x = θ0 + δ`` [rad] with ``θ0 = ΔΘ(q^{t−1}, q_ref)`` (fixed during the step) and
``δ = ΔΘ(q, q^{t−1})`` (the atan2 increment of ``angles.py``); then::

    E(x) = s(x − u)³  (x > u),   s(l − x)³  (x < l),   0 on [l, u] (bounds included)  [J]

Not normalised by the range (unlike 669).  Gradient ``E'(x)∇x`` exact; Hessian ``E''(x)∇x∇xᵀ``
(PSD since E'' ≥ 0); the indefinite ``E'(x)∇²x`` term is dropped (tests show Newton still
converges in a few iterations against the limit).
"""

import functools
from types import SimpleNamespace

import numpy as np
import warp as wp

from ..core.angles import angle_ops, revolute_angle_np
from ..core.warp_ops import ops
from .protocol import COORDINATE, Constitution

UID = 670
NAME = "revolute_limit"
KIND = "revolute"


def cubic_np(x, lower, upper, s):
    """E, E', E'' of the seed's one-sided cubic."""
    if x > upper:
        e = x - upper
        return s * e**3, 3 * s * e**2, 6 * s * e
    if x < lower:
        e = lower - x
        return s * e**3, -3 * s * e**2, 6 * s * e
    return 0.0, 0.0, 0.0


def revolute_limit_np(q, q_prev, q_ref, frames, lower, upper, s):
    """E, gradient, exact Hessian, solver Hessian (E''∇x∇xᵀ) in the stacked pair q (float64)."""
    x, gx, hx = revolute_angle_np(q, q_prev, q_ref, frames)
    e, de, dde = cubic_np(x, lower, upper, s)
    return e, de * gx, dde * np.outer(gx, gx) + de * hx, dde * np.outer(gx, gx)


@functools.lru_cache(maxsize=None)
def kernel(dtype):
    o = ops(dtype)
    a = angle_ops(dtype)
    vec3, vec12 = o.vec3, o.vec12
    add_energy, scatter_pair, outer_blocks = o.add_energy, o.scatter_pair, o.outer_blocks
    cos_sin, delta_theta, theta_grad = a.cos_sin, a.delta_theta, a.theta_grad
    three, six = dtype(3.0), dtype(6.0)

    @wp.func
    def cubic(x: dtype, lo: dtype, up: dtype, st: dtype):
        e = dtype(0.0)
        de = dtype(0.0)
        dde = dtype(0.0)
        if x > up:
            r = x - up
            e = st * r * r * r
            de = three * st * r * r
            dde = six * st * r
        elif x < lo:
            r = lo - x
            e = st * r * r * r
            de = -three * st * r * r
            dde = six * st * r
        return e, de, dde

    @wp.func
    def revolute_limit_parts(
        qi: vec12, qj: vec12, na: vec3, ba: vec3, nb: vec3, bb: vec3, theta0: dtype, cp: dtype, sp: dtype,
        lo: dtype, up: dtype, st: dtype, derivs: int,
    ):  # fmt: skip
        """(E, E'(x), E''(x), ∇_i x, ∇_j x): the gradient is E'∇x, the solver's Hessian E''∇x∇xᵀ
        (∇x only for derivs != 0 where the limit acts)."""
        c, s = cos_sin(qi, qj, na, ba, nb, bb)
        x = theta0 + delta_theta(c, s, cp, sp)
        e, de, dde = cubic(x, lo, up, st)
        gi = vec12()
        gj = vec12()
        if derivs != 0 and de != dtype(0.0):
            gi, gj = theta_grad(qi, qj, na, ba, nb, bb, c, s)
        return e, de, dde, gi, gj

    @wp.func
    def revolute_limit_eval(
        qi: vec12, qj: vec12, na: vec3, ba: vec3, nb: vec3, bb: vec3, theta0: dtype, cp: dtype, sp: dtype,
        lo: dtype, up: dtype, st: dtype, derivs: int,
    ):  # fmt: skip
        e, de, dde, gi, gj = revolute_limit_parts(qi, qj, na, ba, nb, bb, theta0, cp, sp, lo, up, st, derivs)
        hii, hij, hjj = outer_blocks(gi, gj, dde, derivs)
        return e, de * gi, de * gj, hii, hij, hjj

    @wp.kernel(module="unique")
    def revolute_limit(
        q: wp.array2d(dtype=vec12), joint: wp.array(dtype=wp.int32),
        body_a: wp.array(dtype=wp.int32), body_b: wp.array(dtype=wp.int32), dof: wp.array(dtype=wp.int32),
        n_a: wp.array2d(dtype=vec3), b_a: wp.array2d(dtype=vec3), n_b: wp.array2d(dtype=vec3), b_b: wp.array2d(dtype=vec3),
        theta0: wp.array2d(dtype=dtype), c_prev: wp.array2d(dtype=dtype), s_prev: wp.array2d(dtype=dtype),
        lower: wp.array2d(dtype=dtype), upper: wp.array2d(dtype=dtype), strength: wp.array2d(dtype=dtype),
        active: wp.array(dtype=wp.int32), derivs: int, col: int,
        E: wp.array2d(dtype=dtype), g: wp.array2d(dtype=dtype), H: wp.array3d(dtype=dtype),
    ):  # fmt: skip
        w, k = wp.tid()
        if active[w] == 0:
            return
        j = joint[k]
        bi = body_a[j]
        bj = body_b[j]
        e, gi, gj, hii, hij, hjj = revolute_limit_eval(
            q[w, bi], q[w, bj], n_a[w, j], b_a[w, j], n_b[w, j], b_b[w, j], theta0[w, j], c_prev[w, j], s_prev[w, j],
            lower[w, k], upper[w, k], strength[w, k], derivs)  # fmt: skip
        add_energy(E, w, col, e)
        if derivs != 0 and e != dtype(0.0):
            scatter_pair(g, H, w, dof[bi], dof[bj], gi, gj, hii, hij, hjj)

    return SimpleNamespace(kernel=revolute_limit, eval=revolute_limit_eval, parts=revolute_limit_parts, cubic=cubic)


def terms(model, physical=False):
    return (NAME,) if model.limit_joints[KIND] else ()


def launch(model, state, ctx, q, E, g, H, active, derivs, cols, physical=False):
    m = model
    wp.launch(kernel(m.dtype).kernel, dim=(m.num_worlds, len(m.limit_joints[KIND])),
              inputs=[q, m.limit_joint_ids[KIND], m.body_a, m.body_b, m.dof, m.n_a, m.b_a, m.n_b, m.b_b,
                      state.theta0, state.c_prev, state.s_prev, *m.limit_params[KIND], active, derivs, cols[NAME],
                      E, g, H], device=m.device)  # fmt: skip


@functools.lru_cache(maxsize=None)
def fold(dtype, Terms):
    """The limit folded into its revolute joint's angle term (protocol.Constitution.fold)."""
    cubic = kernel(dtype).cubic

    @wp.func
    def revolute(t: Terms, w: int, j: int, a: int, x: dtype, hw: dtype, e: dtype, de: dtype, dde: dtype):
        """Joint term a's limit, if it has one, at x = θ0 + δ (revolute_limit.cubic)."""
        kl = t.fold_revolute_limit_revolute[a]
        if kl >= 0:
            el, d1, d2 = cubic(t.theta0[w, j] + x, t.rlim_lo[w, kl], t.rlim_up[w, kl], t.rlim_s[w, kl])
            e += el
            de += d1
            dde += d2
        return e, de, dde

    return SimpleNamespace(revolute=revolute)


CONSTITUTION = Constitution(NAME, UID, COORDINATE, revolute_limit_np, terms, launch, work=6.0,
                            instances=lambda model: model.limit_joints[KIND], slots={KIND: 1}, fold=fold)  # fmt: skip
