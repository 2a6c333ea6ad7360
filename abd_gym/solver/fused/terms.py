"""The terms of the incremental potential, one function per constitution instance (kind k of
assemble's loops), each its energy [J] and, per ``derivs``, its gradient and Hessian added to
scratch column s (of B) of g and H through ``puts``:

- ``body_term``: body b's inertia ½(q − q̃)ᵀM(q − q̃) and orthogonality h²·κ·vol·‖AAᵀ − I‖²_F;
- ``point_term``: a revolute (2 points) or fixed (4 points) joint, K/2 Σ‖x_a − x_b‖²;
- ``prismatic_term``: a prismatic joint and the coordinate terms folded into it (its limit, a
  drive) on its displacement x;
- ``angle_term``: the coordinate terms folded on a revolute joint (its limit, drives) on its angle;
- ``rlim_term``, ``plim_term``, ``drive_term``: limits and drives with terms of their own.

The drives' energies are inside ĥ² (ĥ: the world's step, Terms.h_step).  The formulas are the
constitutions' (``abd_gym.constitutions``); this module only loads their arguments and puts their
blocks."""
import functools
from types import SimpleNamespace
from typing import Any

import warp as wp

from ...core.angles import angle_ops
from ...constitutions import _joint_step, _point_joint, affine_body, drive, prismatic_joint, prismatic_limit, revolute_limit
from ...sim.scene import PRISMATIC, REVOLUTE
from ...core.warp_ops import HESSIAN, ops
from .layout import KernelSpec
from .puts import prismatic_puts, puts
from .structs import structs


# coordinate constitutions one joint term folds at most: a joint term calls its folds as this
# many static calls, in order (not a static loop: Warp resolves a wp.static() that reads a loop
# variable only at code generation, after the kernel cache's hash, so two scenes folding different
# constitutions would share one cached kernel)
MAX_FOLDS = 4


def fold_slots(folds: list) -> list:
    """``folds`` padded with None to MAX_FOLDS."""
    if len(folds) > MAX_FOLDS:
        raise ValueError(f"{len(folds)} coordinate terms folded on one joint kind: raise fused.terms.MAX_FOLDS")
    return list(folds) + [None] * (MAX_FOLDS - len(folds))


@functools.lru_cache(maxsize=None)
def terms(spec: KernelSpec):
    """The bodies' and joints' terms: ``body_term``, ``point_term``, ``prismatic_term`` (with the
    coordinate terms folded on it)."""
    dtype = spec.dtype
    folds = [c.fold(dtype, structs(dtype).Terms).prismatic for c in spec.folded(PRISMATIC)]
    f0, f1, f2, f3 = fold_slots(folds)
    vec12 = ops(dtype).vec12
    Terms = structs(dtype).Terms
    body_grad = affine_body.kernels(dtype).body_grad
    point_eval_kron = _point_joint.kernel(dtype).eval_kron
    prismatic_grad = prismatic_joint.kernel(dtype).grad
    pri_displacement, pri_displacement_grad = angle_ops(dtype).displacement, angle_ops(dtype).displacement_grad
    p = puts(spec)
    put_grad, put_body, put_kron_pair, put_outer_pair = p.put_grad, p.put_body, p.put_kron_pair, p.put_outer_pair
    prismatic_hessian = prismatic_puts(spec).prismatic_hessian
    zero = dtype(0.0)
    joint_k = _joint_step.funcs(dtype)

    @wp.func
    def body_term(q: wp.array2d(dtype=vec12), qr: int, w: int, s: int, B: int, derivs: int, t: Terms, g: Any, H: Any,
                  k: int, h2: dtype):  # fmt: skip
        b = t.free[k]
        qb = q[qr, b]
        ks = t.kv[w, b] * h2
        # the Hessian goes straight into H (put_body)
        e_in, e_or, f = body_grad(qb, t.q_tilde[w, b], t.mass[w, b], t.mc[w, b], t.S[w, b], ks, derivs)
        if derivs != 0:
            put_grad(g, s, B, t.dof[b], f)
            if derivs == HESSIAN:
                exact = int(0)
                if wp.static(spec.exact):
                    exact = t.exact[w]
                put_body(H, s, B, t.dof[b], qb, t.mass[w, b], t.mc[w, b], t.S[w, b], ks, exact)
        return e_in + e_or

    @wp.func
    def point_term(q: wp.array2d(dtype=vec12), qr: int, w: int, s: int, B: int, derivs: int, t: Terms, g: Any,
                   H: Any, j: int, points: int):  # fmt: skip
        """A revolute (2 points) or fixed (4 points) joint j."""
        ej, gi, gj, uii, uij, ujj = point_eval_kron(q[qr, t.body_a[j]], q[qr, t.body_b[j]], t.pts_a, t.pts_b, w, j,
                                                    points, joint_k(t.K, t.h_step, t.h_joint, w, j), derivs)  # fmt: skip
        if derivs != 0:
            put_kron_pair(g, H, s, B, derivs, t.dof[t.body_a[j]], t.dof[t.body_b[j]], gi, gj, uii, uij, ujj)
        return ej

    @wp.func
    def prismatic_term(q: wp.array2d(dtype=vec12), qr: int, w: int, s: int, B: int, derivs: int, t: Terms, g: Any,
                       H: Any, kp: int):  # fmt: skip
        """Prismatic joint kp (of pri_ids) and the coordinate terms folded on it (spec.folds: its
        limit, a drive; each constitution's fold, in registry order): their energies E(x) of the
        displacement x add E'∇x to the joint's gradient before its one put, and E''∇x∇xᵀ to its
        Hessian (the arithmetic of plim_term and drive_term on the same x and ∇x)."""
        j = t.pri_ids[kp]
        qi = q[qr, t.body_a[j]]
        qj = q[qr, t.body_b[j]]
        oi = t.dof[t.body_a[j]]
        oj = t.dof[t.body_b[j]]
        ca = t.c_a[w, j]
        cb = t.c_b[w, j]
        ta = t.t_a[w, j]
        kk = joint_k(t.K, t.h_step, t.h_joint, w, j)
        # the Hessian goes straight into H (prismatic_hessian), so the evaluator builds none
        ej, gi, gj = prismatic_grad(qi, qj, ca, cb, ta, t.t_b[w, j], t.n_a[w, j], t.n_b[w, j], t.b_a[w, j],
                                    t.b_b[w, j], kk, derivs)  # fmt: skip
        de = zero
        dde = zero
        gxi = vec12()
        gxj = vec12()
        if wp.static(len(folds) > 0):
            x = pri_displacement(qi, qj, ca, cb, ta)
            if wp.static(f0 is not None):
                ej, de, dde = wp.static(f0)(t, w, j, kp, x, ej, de, dde)
            if wp.static(f1 is not None):
                ej, de, dde = wp.static(f1)(t, w, j, kp, x, ej, de, dde)
            if wp.static(f2 is not None):
                ej, de, dde = wp.static(f2)(t, w, j, kp, x, ej, de, dde)
            if wp.static(f3 is not None):
                ej, de, dde = wp.static(f3)(t, w, j, kp, x, ej, de, dde)
            if derivs != 0 and (de != zero or dde != zero):
                gxi, gxj = pri_displacement_grad(qi, qj, ca, cb, ta)
                gi = gi + de * gxi
                gj = gj + de * gxj
        if derivs != 0:
            put_grad(g, s, B, oi, gi)
            put_grad(g, s, B, oj, gj)
            if derivs == HESSIAN:
                prismatic_hessian(H, s, B, oi, oj, qi, qj, ca, cb, ta, t.t_b[w, j], t.n_a[w, j], t.n_b[w, j],
                                  t.b_a[w, j], t.b_b[w, j], kk)  # fmt: skip
                if wp.static(len(folds) > 0):
                    if dde != zero:
                        put_outer_pair(H, s, B, oi, oj, gxi, gxj, dde)
        return ej

    return SimpleNamespace(body_term=body_term, point_term=point_term, prismatic_term=prismatic_term)


@functools.lru_cache(maxsize=None)
def coordinate_terms(spec: KernelSpec):
    """The terms of a joint coordinate x (an angle, a displacement): ``angle_term`` (a revolute
    joint's limit and drives on its angle), ``rlim_term``, ``plim_term``, ``drive_term``."""
    dtype = spec.dtype
    vec12 = ops(dtype).vec12
    Terms = structs(dtype).Terms
    rlim_parts = revolute_limit.kernel(dtype).parts
    folds = [c.fold(dtype, structs(dtype).Terms).revolute for c in spec.folded(REVOLUTE)]
    f0, f1, f2, f3 = fold_slots(folds)
    an = angle_ops(dtype)
    cos_sin, delta_theta, theta_grad = an.cos_sin, an.delta_theta, an.theta_grad
    plim_parts = prismatic_limit.kernel(dtype).parts
    drive_parts = drive.kernel(dtype).parts
    put_rank1 = puts(spec).put_rank1
    zero = dtype(0.0)

    @wp.func
    def angle_term(q: wp.array2d(dtype=vec12), qr: int, w: int, s: int, B: int, derivs: int, t: Terms, g: Any,
                   H: Any, a: int, hw: dtype):  # fmt: skip
        """Angle term a: the coordinate terms folded on revolute joint j (spec.folds, each
        constitution's fold in registry order: its limit, on x = θ0 + δ, its drives, on x = x_prev +
        δ; δ = ΔΘ(q, q^{t−1}), the one increment all read), their E′ and E″ summed into one put of
        E′∇θ and E″∇θ∇θᵀ (the arithmetic of rlim_term and drive_term on the same angle); ∇θ only
        where they are not zero."""
        j = t.ang_joint[a]
        qi = q[qr, t.body_a[j]]
        qj = q[qr, t.body_b[j]]
        na = t.n_a[w, j]
        ba = t.b_a[w, j]
        nb = t.n_b[w, j]
        bb = t.b_b[w, j]
        c, sn = cos_sin(qi, qj, na, ba, nb, bb)
        dl = delta_theta(c, sn, t.c_prev[w, j], t.s_prev[w, j])
        e = zero
        de = zero
        dde = zero
        if wp.static(f0 is not None):
            e, de, dde = wp.static(f0)(t, w, j, a, dl, hw, e, de, dde)
        if wp.static(f1 is not None):
            e, de, dde = wp.static(f1)(t, w, j, a, dl, hw, e, de, dde)
        if wp.static(f2 is not None):
            e, de, dde = wp.static(f2)(t, w, j, a, dl, hw, e, de, dde)
        if wp.static(f3 is not None):
            e, de, dde = wp.static(f3)(t, w, j, a, dl, hw, e, de, dde)
        if derivs != 0 and (de != zero or dde != zero):
            gi, gj = theta_grad(qi, qj, na, ba, nb, bb, c, sn)
            put_rank1(g, H, s, B, derivs, t.dof[t.body_a[j]], t.dof[t.body_b[j]], gi, gj, de, dde)
        return e

    @wp.func
    def put_limit(g: Any, H: Any, s: int, B: int, derivs: int, t: Terms, j: int, ej: dtype, de: dtype, dde: dtype,
                  gi: vec12, gj: vec12):  # fmt: skip
        """A limit of joint j adds its terms only where it acts (its energy is not zero)."""
        if ej != zero:
            put_rank1(g, H, s, B, derivs, t.dof[t.body_a[j]], t.dof[t.body_b[j]], gi, gj, de, dde)

    @wp.func
    def rlim_term(q: wp.array2d(dtype=vec12), qr: int, w: int, s: int, B: int, derivs: int, t: Terms, g: Any,
                  H: Any, k: int):  # fmt: skip
        j = t.rlim_ids[k]
        ej, de, dde, gi, gj = rlim_parts(q[qr, t.body_a[j]], q[qr, t.body_b[j]], t.n_a[w, j], t.b_a[w, j], t.n_b[w, j],
                                         t.b_b[w, j], t.theta0[w, j], t.c_prev[w, j], t.s_prev[w, j], t.rlim_lo[w, k],
                                         t.rlim_up[w, k], t.rlim_s[w, k], derivs)  # fmt: skip
        put_limit(g, H, s, B, derivs, t, j, ej, de, dde, gi, gj)
        return ej

    @wp.func
    def plim_term(q: wp.array2d(dtype=vec12), qr: int, w: int, s: int, B: int, derivs: int, t: Terms, g: Any,
                  H: Any, k: int):  # fmt: skip
        j = t.plim_ids[k]
        ej, de, dde, gi, gj = plim_parts(q[qr, t.body_a[j]], q[qr, t.body_b[j]], t.c_a[w, j], t.c_b[w, j], t.t_a[w, j],
                                         t.plim_lo[w, k], t.plim_up[w, k], t.plim_s[w, k], derivs)  # fmt: skip
        put_limit(g, H, s, B, derivs, t, j, ej, de, dde, gi, gj)
        return ej

    @wp.func
    def drive_term(q: wp.array2d(dtype=vec12), qr: int, w: int, s: int, B: int, derivs: int, t: Terms, g: Any,
                   H: Any, k: int, hw: dtype, h2: dtype):  # fmt: skip
        j = t.drive_joint[k]
        ej, de, dde, gi, gj = drive_parts(q[qr, t.body_a[j]], q[qr, t.body_b[j]], w, k, t.drive_joint, t.joint_kind,
                                          t.c_a, t.c_b, t.t_a, t.n_a, t.b_a, t.n_b, t.b_b, t.c_prev, t.s_prev,
                                          t.drive_mode, t.kp, t.kd, t.fmax, t.control, t.unwrapped, t.x_anchor, hw,
                                          h2, 0, derivs)  # fmt: skip
        # an effort drive (or a clipped PD drive) is linear in x: dde = 0, its gradient only
        put_rank1(g, H, s, B, derivs, t.dof[t.body_a[j]], t.dof[t.body_b[j]], gi, gj, de, dde)
        return ej

    return SimpleNamespace(angle_term=angle_term, rlim_term=rlim_term, plim_term=plim_term, drive_term=drive_term)
