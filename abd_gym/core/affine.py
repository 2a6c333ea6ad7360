"""Affine-body kinematics in float64 NumPy: the references every Warp kernel is tested against.

``q = (p, a1, a2, a3)``: a body-frame point ``xb`` sits at ``x = p + A xb = J(xb) q`` and a
body-frame direction ``v`` at ``A v = J̊(v) q`` (docs/design.md §1, the seeds' notation).
"""
from __future__ import annotations

import numpy as np


def axis_rotations(axis, angle) -> np.ndarray:
    """(n, 3, 3) rotations by ``angle`` (n,) [rad] about the unit ``axis`` (3,) (Rodrigues)."""
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    return np.eye(3) + s * k + (1.0 - c) * (k @ k)


def J(x) -> np.ndarray:
    """3x12 map q -> p + A x."""
    x = np.asarray(x, dtype=np.float64)
    out = np.zeros((3, 12))
    out[:, :3] = np.eye(3)
    for k in range(3):
        out[k, 3 + 3 * k : 6 + 3 * k] = x
    return out


def Jo(v) -> np.ndarray:
    """3x12 map q -> A v (no translation: the seeds' J̊)."""
    out = J(v)
    out[:, :3] = 0.0
    return out


def mass_matrix(mass, com, second_moment) -> np.ndarray:
    """M = ∫ρ J(x)ᵀJ(x) dV = [[m I, (m c) blocks], [.., diag(S, S, S)]] (12x12)."""
    m = np.zeros((12, 12))
    m[:3, :3] = mass * np.eye(3)
    mc = mass * np.asarray(com, dtype=np.float64)
    for k in range(3):
        m[k, 3 + 3 * k : 6 + 3 * k] = mc
        m[3 + 3 * k : 6 + 3 * k, k] = mc
        m[3 + 3 * k : 6 + 3 * k, 3 + 3 * k : 6 + 3 * k] = second_moment
    return m


def on_pair(L, side) -> np.ndarray:
    """Embed a 3x12 map of one body into the stacked pair q = (q_i, q_j) (3x24)."""
    out = np.zeros((L.shape[0], 24))
    out[:, 12 * side : 12 * side + 12] = L
    return out


def dot_derivs(U, V, q):
    """u·v with u = U q, v = V q: value, gradient, Hessian."""
    u, v = U @ q, V @ q
    return u @ v, U.T @ v + V.T @ u, U.T @ V + V.T @ U


def cross_derivs(U, V, q):
    """u×v with u = U q, v = V q: value (3), Jacobian (3xn), Hessians (3xnxn)."""
    u, v = U @ q, V @ q
    eps = np.zeros((3, 3, 3))
    eps[0, 1, 2] = eps[1, 2, 0] = eps[2, 0, 1] = 1.0
    eps[0, 2, 1] = eps[2, 1, 0] = eps[1, 0, 2] = -1.0
    val = np.cross(u, v)
    jac = np.einsum("mab,an,b->mn", eps, U, v) + np.einsum("mab,a,bn->mn", eps, u, V)
    hes = np.einsum("mab,an,bk->mnk", eps, U, V)
    return val, jac, hes + hes.transpose(0, 2, 1)
