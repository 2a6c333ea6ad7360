"""Prismatic joint limit (libuipc UID 669): a one-sided cubic on the displacement.

``x = t̂_i·(c_j − c_i)`` [m] (``angles.py``).  As in libuipc the overshoot is divided by the
range width ``w = u − l``::

    E(x) = s((x − u)/w)³  (x > u),   s((l − x)/w)³  (x < l),   0 on [l, u]          [J]

falling back to ``s|x − l|³`` when ``u = l``.  Gradient ``E'(x)∇x`` exact; Hessian
``E''(x)∇x∇xᵀ`` (PSD), the ``E'(x)∇²x`` term dropped.
"""

import functools
from types import SimpleNamespace

import numpy as np
import warp as wp

from ..core.angles import angle_ops, prismatic_displacement_np
from ..core.warp_ops import ops
from .protocol import COORDINATE, Constitution

UID = 669
NAME = "prismatic_limit"
KIND = "prismatic"


def cubic_np(x, lower, upper, s):
    width = upper - lower
    scale = 1.0 / width if width > 0.0 else 1.0
    if x > upper:
        e = (x - upper) * scale
        return s * e**3, 3 * s * e**2 * scale, 6 * s * e * scale**2
    if x < lower:
        e = (lower - x) * scale
        return s * e**3, -3 * s * e**2 * scale, 6 * s * e * scale**2
    return 0.0, 0.0, 0.0


def prismatic_limit_np(q, ci, cj, ti, lower, upper, s):
    """E, gradient, exact Hessian, solver Hessian in the stacked pair q (float64)."""
    x, gx, hx = prismatic_displacement_np(q, ci, cj, ti)
    e, de, dde = cubic_np(x, lower, upper, s)
    return e, de * gx, dde * np.outer(gx, gx) + de * hx, dde * np.outer(gx, gx)


@functools.lru_cache(maxsize=None)
def kernel(dtype):
    o = ops(dtype)
    a = angle_ops(dtype)
    vec3, vec12 = o.vec3, o.vec12
    add_energy, scatter_pair, outer_blocks = o.add_energy, o.scatter_pair, o.outer_blocks
    displacement, displacement_grad = a.displacement, a.displacement_grad
    one, three, six = dtype(1.0), dtype(3.0), dtype(6.0)

    @wp.func
    def cubic(x: dtype, lo: dtype, up: dtype, st: dtype):
        """(E, E'(x), E''(x)) of the limit at displacement x [m]: s·r³ for the overshoot r past a
        bound, divided by the range's width u − l where it has one (cubic_np)."""
        inv = one
        if up > lo:
            inv = one / (up - lo)
        e = dtype(0.0)
        de = dtype(0.0)
        dde = dtype(0.0)
        if x > up:
            r = (x - up) * inv
            e = st * r * r * r
            de = three * st * r * r * inv
            dde = six * st * r * inv * inv
        elif x < lo:
            r = (lo - x) * inv
            e = st * r * r * r
            de = -three * st * r * r * inv
            dde = six * st * r * inv * inv
        return e, de, dde

    @wp.func
    def prismatic_limit_parts(
        qi: vec12, qj: vec12, ca: vec3, cb: vec3, ta: vec3, lo: dtype, up: dtype, st: dtype, derivs: int,
    ):  # fmt: skip
        """(E, E'(x), E''(x), ∇_i x, ∇_j x): the gradient is E'∇x, the solver's Hessian E''∇x∇xᵀ
        (∇x only for derivs != 0 where the limit acts)."""
        e, de, dde = cubic(displacement(qi, qj, ca, cb, ta), lo, up, st)
        gi = vec12()
        gj = vec12()
        if derivs != 0 and de != dtype(0.0):
            gi, gj = displacement_grad(qi, qj, ca, cb, ta)
        return e, de, dde, gi, gj

    @wp.func
    def prismatic_limit_eval(
        qi: vec12, qj: vec12, ca: vec3, cb: vec3, ta: vec3, lo: dtype, up: dtype, st: dtype, derivs: int,
    ):  # fmt: skip
        e, de, dde, gi, gj = prismatic_limit_parts(qi, qj, ca, cb, ta, lo, up, st, derivs)
        hii, hij, hjj = outer_blocks(gi, gj, dde, derivs)
        return e, de * gi, de * gj, hii, hij, hjj

    @wp.kernel(module="unique")
    def prismatic_limit(
        q: wp.array2d(dtype=vec12), joint: wp.array(dtype=wp.int32),
        body_a: wp.array(dtype=wp.int32), body_b: wp.array(dtype=wp.int32), dof: wp.array(dtype=wp.int32),
        c_a: wp.array2d(dtype=vec3), c_b: wp.array2d(dtype=vec3), t_a: wp.array2d(dtype=vec3),
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
        e, gi, gj, hii, hij, hjj = prismatic_limit_eval(q[w, bi], q[w, bj], c_a[w, j], c_b[w, j], t_a[w, j],
                                                        lower[w, k], upper[w, k], strength[w, k], derivs)  # fmt: skip
        add_energy(E, w, col, e)
        if derivs != 0 and e != dtype(0.0):
            scatter_pair(g, H, w, dof[bi], dof[bj], gi, gj, hii, hij, hjj)

    return SimpleNamespace(kernel=prismatic_limit, eval=prismatic_limit_eval, parts=prismatic_limit_parts, cubic=cubic)


def terms(model, physical=False):
    return (NAME,) if model.limit_joints[KIND] else ()


def launch(model, state, ctx, q, E, g, H, active, derivs, cols, physical=False):
    m = model
    wp.launch(kernel(m.dtype).kernel, dim=(m.num_worlds, len(m.limit_joints[KIND])),
              inputs=[q, m.limit_joint_ids[KIND], m.body_a, m.body_b, m.dof, m.c_a, m.c_b, m.t_a,
                      *m.limit_params[KIND], active, derivs, cols[NAME], E, g, H], device=m.device)  # fmt: skip


@functools.lru_cache(maxsize=None)
def fold(dtype, Terms):
    """The limit folded into its prismatic joint's term (protocol.Constitution.fold)."""
    cubic = kernel(dtype).cubic

    @wp.func
    def prismatic(t: Terms, w: int, j: int, a: int, x: dtype, e: dtype, de: dtype, dde: dtype):
        """Joint term a's limit, if it has one, at the displacement x (prismatic_limit.cubic)."""
        kl = t.fold_prismatic_limit_prismatic[a]
        if kl >= 0:
            el, dl, ddl = cubic(x, t.plim_lo[w, kl], t.plim_up[w, kl], t.plim_s[w, kl])
            e += el
            de += dl
            dde += ddl
        return e, de, dde

    return SimpleNamespace(prismatic=prismatic)


CONSTITUTION = Constitution(NAME, UID, COORDINATE, prismatic_limit_np, terms, launch, work=6.0,
                            instances=lambda model: model.limit_joints[KIND], slots={KIND: 1}, fold=fold)  # fmt: skip
