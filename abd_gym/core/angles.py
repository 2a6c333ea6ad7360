"""Joint coordinates: the seed's atan2 revolute angle and the prismatic displacement.

Revolute (seed ``affine_body_revolute_joint_limit.md``)::

    cos θ = (b̂_i·b̂_j + n̂_i·n̂_j)/2,   sin θ = (n̂_i·b̂_j − b̂_i·n̂_j)/2
    ΔΘ(q_a, q_b) = atan2(sin θ_a cos θ_b − cos θ_a sin θ_b, cos θ_a cos θ_b + sin θ_a sin θ_b)

with ``n̂_k = A_k n̂_k^local`` (frames built by ``scene.axis_frame``, so a right-hand turn of body
j about t̂ is a positive angle).  Its gradient does not depend on the second state:
``∇ΔΘ(q, ·) = ∇θ = (cos θ ∇sin θ − sin θ ∇cos θ)/(cos²θ + sin²θ)``.

Prismatic: ``d = t̂_i·(c_j − c_i)`` [m], the second body's displacement along the first's axis.
"""

import functools
from types import SimpleNamespace

import numpy as np
import warp as wp

from . import affine
from .warp_ops import ops


# ----------------------------------------------------------------------------- float64 NumPy
def cos_sin_np(q, ni, bi, nj, bj):
    """cos θ, sin θ of the stacked pair q = (q_i, q_j) (24,), with gradients and Hessians."""
    Ni, Bi = affine.on_pair(affine.Jo(ni), 0), affine.on_pair(affine.Jo(bi), 0)
    Nj, Bj = affine.on_pair(affine.Jo(nj), 1), affine.on_pair(affine.Jo(bj), 1)
    bb, nn, nb, bn = (affine.dot_derivs(U, V, q) for U, V in ((Bi, Bj), (Ni, Nj), (Ni, Bj), (Bi, Nj)))
    c = tuple(0.5 * (x + y) for x, y in zip(bb, nn))
    s = tuple(0.5 * (x - y) for x, y in zip(nb, bn))
    return c, s


def delta_theta_np(cs_a, cs_b):
    (ca, sa), (cb, sb) = cs_a, cs_b
    return np.arctan2(sa * cb - ca * sb, ca * cb + sa * sb)


def revolute_angle_np(q, q_prev, q_ref, frames):
    """x = θ0 + δ with θ0 = ΔΘ(q_prev, q_ref), δ = ΔΘ(q, q_prev); gradient and exact Hessian in q."""
    (c, dc, hc), (s, ds, hs) = cos_sin_np(q, *frames)
    cs_prev = tuple(v[0] for v in cos_sin_np(q_prev, *frames))
    cs_ref = tuple(v[0] for v in cos_sin_np(q_ref, *frames))
    x = delta_theta_np(cs_prev, cs_ref) + delta_theta_np((c, s), cs_prev)
    r = c * c + s * s
    u = c * ds - s * dc
    grad = u / r
    du = np.outer(ds, dc) + c * hs - np.outer(dc, ds) - s * hc  # ∂(c∇s − s∇c)/∂q, rows index ∂
    hess = du / r - np.outer(u, 2.0 * (c * dc + s * ds)) / r**2
    return x, grad, hess


def prismatic_displacement_np(q, ci, cj, ti):
    """d = t̂_i·(c_j − c_i): value, gradient, Hessian in the stacked pair q."""
    T = affine.on_pair(affine.Jo(ti), 0)
    D = affine.on_pair(affine.J(cj), 1) - affine.on_pair(affine.J(ci), 0)
    return affine.dot_derivs(T, D, q)


# ----------------------------------------------------------------------------- Warp
@functools.lru_cache(maxsize=None)
def angle_ops(dtype):
    o = ops(dtype)
    vec3, vec12, JT, direction, point = o.vec3, o.vec12, o.JT, o.direction, o.point
    half = dtype(0.5)
    zero = dtype(0.0)

    @wp.func
    def cos_sin(qi: vec12, qj: vec12, ni: vec3, bi: vec3, nj: vec3, bj: vec3):
        Ni = direction(qi, ni)
        Bi = direction(qi, bi)
        Nj = direction(qj, nj)
        Bj = direction(qj, bj)
        return half * (wp.dot(Bi, Bj) + wp.dot(Ni, Nj)), half * (wp.dot(Ni, Bj) - wp.dot(Bi, Nj))

    @wp.func
    def delta_theta(ca: dtype, sa: dtype, cb: dtype, sb: dtype):
        return wp.atan2(sa * cb - ca * sb, ca * cb + sa * sb)

    @wp.func
    def theta_grad(qi: vec12, qj: vec12, ni: vec3, bi: vec3, nj: vec3, bj: vec3, c: dtype, s: dtype):
        """∇θ on (q_i, q_j) as two 12-vectors."""
        Ni = direction(qi, ni)
        Bi = direction(qi, bi)
        Nj = direction(qj, nj)
        Bj = direction(qj, bj)
        dci = half * (JT(bi, Bj, zero) + JT(ni, Nj, zero))
        dcj = half * (JT(bj, Bi, zero) + JT(nj, Ni, zero))
        dsi = half * (JT(ni, Bj, zero) - JT(bi, Nj, zero))
        dsj = half * (JT(bj, Ni, zero) - JT(nj, Bi, zero))
        r = c * c + s * s
        return (c * dsi - s * dci) / r, (c * dsj - s * dcj) / r

    @wp.func
    def displacement(qi: vec12, qj: vec12, ci: vec3, cj: vec3, ti: vec3):
        return wp.dot(direction(qi, ti), point(qj, cj) - point(qi, ci))

    @wp.func
    def displacement_grad(qi: vec12, qj: vec12, ci: vec3, cj: vec3, ti: vec3):
        t = direction(qi, ti)
        d = point(qj, cj) - point(qi, ci)
        return JT(ti, d, zero) - JT(ci, t, dtype(1.0)), JT(cj, t, dtype(1.0))

    return SimpleNamespace(
        cos_sin=cos_sin,
        delta_theta=delta_theta,
        theta_grad=theta_grad,
        displacement=displacement,
        displacement_grad=displacement_grad,
    )
