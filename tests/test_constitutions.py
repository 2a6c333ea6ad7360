"""Energies of every constitution: float64 NumPy references against central differences, the
solver's PSD Hessian variants, the Warp kernels against the references (float64 and float32),
``Simulator.energies()`` against each term's own formula, and the shapes' mass moments.

Conventions (docs/design.md §1, seeds): q = (p, a1, a2, a3) per body, a pair of bodies stacks (q_i, q_j).
In the solve, inertia, joints and limits enter as they are, orthogonality and drives times h² (ĥ² = (2h/3)²
under BDF2).  The Warp checks share one scene (module-scoped simulators: each kernel compiles once per dtype).
"""
import math

import numpy as np
import pytest
import warp as wp

import abd_gym as ag
from abd_gym import WorldStatus
from abd_gym.core import affine, angles
from abd_gym.constitutions import affine_body, drive, prismatic_joint, prismatic_limit, revolute_limit
from abd_gym.constitutions._point_joint import point_joint_np
from abd_gym.sim.scene import axis_frame
from abd_gym.core.warp_ops import GRADIENT, HESSIAN

H_FD = 1e-6  # central-difference step
RTOL_G = 1e-6  # relative (norm-wise) tolerance on gradients from energies
RTOL_H = 1e-5  # ... on Hessians from gradients


# ============================================================================ helpers
def rot(axis, angle):
    """Right-hand rotation about ``axis`` (Rodrigues), written independently of the package."""
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def random_rotation(rng):
    Q, R = np.linalg.qr(rng.normal(size=(3, 3)))
    Q = Q * np.sign(np.diag(R))
    if np.linalg.det(Q) < 0:
        Q[:, 0] *= -1
    return Q


def near_rotation_q(rng, eps=1e-2, R=None, p=None):
    """12-vector: a rotation plus a small random affine perturbation, at a random position."""
    R = random_rotation(rng) if R is None else R
    p = rng.normal(scale=0.5, size=3) if p is None else p
    return np.concatenate([p, (R + eps * rng.normal(size=(3, 3))).ravel()])


def fd_grad(f, q, h=H_FD):
    out = np.empty(q.size)
    for k in range(q.size):
        e = np.zeros(q.size)
        e[k] = h
        out[k] = (f(q + e) - f(q - e)) / (2 * h)
    return out


def fd_jac(f, q, h=H_FD):
    cols = []
    for k in range(q.size):
        e = np.zeros(q.size)
        e[k] = h
        cols.append((f(q + e) - f(q - e)) / (2 * h))
    return np.stack(cols, axis=1)


def rel_err(a, b):
    return np.linalg.norm(np.asarray(a, float) - np.asarray(b, float)) / np.linalg.norm(b)


def check_derivatives(fn, q, g_idx=1, h_idx=2):
    """fn(q) -> (E, g, H, ...): g against central differences of E, H against those of g."""
    out = fn(q)
    g, H = out[g_idx], out[h_idx]
    assert np.linalg.norm(g) > 0 and np.linalg.norm(H) > 0  # something to compare
    assert rel_err(fd_grad(lambda z: fn(z)[0], q), g) < RTOL_G
    assert rel_err(fd_jac(lambda z: fn(z)[g_idx], q), H) < RTOL_H
    np.testing.assert_allclose(H, H.T, atol=1e-12 * np.abs(H).max())


def min_eig_ok(H, tol=1e-9):
    w = np.linalg.eigvalsh(0.5 * (H + H.T))
    return w.min() >= -tol * max(1.0, np.abs(w).max())


def random_joint(rng, eps=1e-2):
    """A joint frame (c, t̂, n̂, b̂) captured with two bodies at random creation poses: the local
    frames of both bodies, q_ref, and a random state near q_ref's shape: a common rotation, a turn
    about the axis, random positions, and a random affine perturbation of size eps."""
    c = rng.normal(scale=0.3, size=3)
    t, n, b = axis_frame(rng.normal(size=3))
    Ri, Rj = random_rotation(rng), random_rotation(rng)
    pi, pj = rng.normal(scale=0.3, size=3), rng.normal(scale=0.3, size=3)
    loc = dict(ci=Ri.T @ (c - pi), cj=Rj.T @ (c - pj), ti=Ri.T @ t, tj=Rj.T @ t, ni=Ri.T @ n, nj=Rj.T @ n,
               bi=Ri.T @ b, bj=Rj.T @ b)  # fmt: skip
    q_ref = np.concatenate([pi, Ri.ravel(), pj, Rj.ravel()])
    G = random_rotation(rng)
    q = np.concatenate([near_rotation_q(rng, eps, R=G @ Ri),
                        near_rotation_q(rng, eps, R=G @ rot(t, rng.uniform(-2.5, 2.5)) @ Rj)])  # fmt: skip
    return loc, q_ref, q


def rigid_motion(q12, R, c, d=np.zeros(3)):
    """Body q after the world map x -> R (x − c) + c + d."""
    p, A = q12[:3], q12[3:].reshape(3, 3)
    return np.concatenate([R @ (p - c) + c + d, (R @ A).ravel()])


# ============================================================================ 1. NumPy references
def test_orthogonality_derivatives_and_psd_hessian():
    rng = np.random.default_rng(10)
    for _ in range(4):
        q = near_rotation_q(rng, eps=3e-2)
        check_derivatives(lambda z: affine_body.orthogonality_np(z, 1.7), q)
        V, g, H, Hp = affine_body.orthogonality_np(q, 1.7)
        assert min_eig_ok(Hp)
        A = q[3:].reshape(3, 3)
        assert V == pytest.approx(1.7 * np.sum((A @ A.T - np.eye(3)) ** 2), rel=1e-14)


def test_orthogonality_psd_hessian_is_exact_when_R_is_psd():
    """A = (I + S) Q with S ⪰ 0 gives R = A Aᵀ − I ⪰ 0: Hp is then the exact Hessian.  A compressed
    A (R ≺ 0) makes the exact Hessian indefinite and Hp differs from it but stays PSD."""
    rng = np.random.default_rng(11)
    for _ in range(3):
        B = rng.normal(size=(3, 3))
        S = 1e-2 * B @ B.T
        q = np.concatenate([rng.normal(size=3), ((np.eye(3) + S) @ random_rotation(rng)).ravel()])
        _, _, H, Hp = affine_body.orthogonality_np(q, 2.0)
        assert rel_err(Hp, H) < 1e-12
    q = np.concatenate([np.zeros(3), (0.5 * random_rotation(rng)).ravel()])
    _, _, H, Hp = affine_body.orthogonality_np(q, 2.0)
    assert np.linalg.eigvalsh(H).min() < -0.1
    assert min_eig_ok(Hp)
    check_derivatives(lambda z: affine_body.orthogonality_np(z, 2.0), q)


def test_orthogonality_hessian_keeps_the_positive_part_of_R():
    """R = AAᵀ − I of mixed sign (A stretched along one axis, compressed along another): the solver's
    Hessian keeps R⁺ (R's positive eigen-part, along its eigenvectors): PSD, and it differs from the
    exact Hessian by 4κv (R − R⁺) ⊗ I only, so a direction in R's positive eigenspace keeps its
    exact curvature (dropping all of R loses it: Newton then crawls at dt 0.05)."""
    rng = np.random.default_rng(12)
    Q, P = random_rotation(rng), random_rotation(rng)
    A = P @ np.diag([1.01, 0.99, 1.0]) @ Q  # R = P diag(0.0201, −0.0199, 0) Pᵀ
    q = np.concatenate([rng.normal(size=3), A.ravel()])
    kv = 2.0
    _, _, H, Hp = affine_body.orthogonality_np(q, kv)
    R = A @ A.T - np.eye(3)
    Rp = (0.0201 * np.outer(P[:, 0], P[:, 0]))
    assert np.linalg.eigvalsh(H).min() < 0 and min_eig_ok(Hp)
    D = np.zeros((12, 12))
    for k in range(3):
        for m in range(3):
            D[3 + 3 * k:6 + 3 * k, 3 + 3 * m:6 + 3 * m] = 4 * kv * (R - Rp)[k, m] * np.eye(3)
    np.testing.assert_allclose(H - Hp, D, atol=1e-12)
    # the row direction along R's positive eigenvector: dA = P[:, 0] e_jᵀ, exact curvature kept
    dq = np.zeros(12)
    dq[3:] = np.outer(P[:, 0], [0.0, 0.0, 1.0]).ravel()
    assert dq @ Hp @ dq == pytest.approx(dq @ H @ dq, rel=1e-12)


@pytest.mark.parametrize("dtype, rtol", [("float64", 1e-9), ("float32", 2e-3)])
def test_warp_psd_part_matches_eigh(dtype, rtol):
    """affine_body.psd_part (closed-form eigenvalues, eigenvectors from cross products) against
    NumPy's eigh on symmetric 3 × 3 matrices with 0 to 3 negative eigenvalues, at the scale of
    A Aᵀ − I (1e-5) and of order one, a near-repeated pair included."""
    rng = np.random.default_rng(13)
    mats = []
    for scale in (1e-5, 1.0):
        for signs in ((1, 1, 1), (1, 1, -1), (1, -1, -1), (-1, -1, -1), (1, 0, -1), (1, 1e-3, -1)):
            V = random_rotation(rng)
            lam = scale * np.array(signs) * rng.uniform(0.5, 2.0, 3)
            mats.append((V * lam) @ V.T)
    V = random_rotation(rng)
    mats.append((V * np.array([2e-5, 2e-5 * (1 + 1e-6), -1e-5])) @ V.T)  # a near-repeated pair
    wdt = getattr(wp, dtype)
    psd_part = affine_body.kernels(wdt).psd_part
    mat33 = wp.types.matrix(shape=(3, 3), dtype=wdt)

    @wp.kernel(module="unique")
    def k(R: wp.array(dtype=mat33), out: wp.array(dtype=mat33)):
        i = wp.tid()
        out[i] = psd_part(R[i])

    R = wp.array(np.array(mats), dtype=mat33)
    out = wp.zeros_like(R)
    wp.launch(k, dim=len(mats), inputs=[R, out])
    for M, got in zip(mats, out.numpy()):
        want = affine_body.psd_part_np(M)
        np.testing.assert_allclose(got, want, rtol=0, atol=rtol * np.abs(M).max())
        assert np.linalg.eigvalsh(want).min() >= -1e-12 * np.abs(M).max()


@pytest.mark.parametrize("exact", [0, 1])
def test_warp_orthogonality_hessian_blocks_match_numpy(exact):
    """The fused step's orthogonality blocks (affine_body.hessian_parts, a_block) of a compressed A
    (R of mixed sign): the PSD Hessian Hp, or with ``exact`` the exact Hessian H (indefinite), each
    as orthogonality_np gives it (float64)."""
    rng = np.random.default_rng(14)
    A = random_rotation(rng) @ np.diag([1.01, 0.99, 1.0]) @ random_rotation(rng)
    q = np.concatenate([rng.normal(size=3), A.ravel()])
    kv = 2.0
    _, _, H, Hp = affine_body.orthogonality_np(q, kv)
    k = affine_body.kernels(wp.float64)
    vec12 = wp.types.vector(12, wp.float64)
    mat33 = wp.types.matrix(shape=(3, 3), dtype=wp.float64)

    @wp.kernel(module="unique")
    def blocks(qb: wp.array(dtype=vec12), exact: int, out: wp.array2d(dtype=mat33)):
        kk, ll = wp.tid()
        Rp, ata = k.hessian_parts(qb[0], exact)
        out[kk, ll] = k.a_block(qb[0], kk, ll, Rp, ata, wp.float64(kv), mat33())

    out = wp.zeros((3, 3), dtype=mat33, device="cpu")
    wp.launch(blocks, dim=(3, 3), inputs=[wp.array([q], dtype=vec12, device="cpu"), exact, out], device="cpu")
    got = out.numpy().transpose(0, 2, 1, 3).reshape(9, 9)
    want = (H if exact else Hp)[3:, 3:]
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * np.abs(want).max())
    assert (np.linalg.eigvalsh(got).min() < 0) == bool(exact)


def _retract_warp(q, d, alpha, m, mc):
    k = affine_body.kernels(wp.float64).retract
    vec12 = wp.types.vector(12, wp.float64)

    @wp.kernel(module="unique")
    def run(q: wp.array(dtype=vec12), d: wp.array(dtype=vec12), alpha: wp.float64, m: wp.float64, mc: wp.vec3d,
            out: wp.array(dtype=vec12)):  # fmt: skip
        i = wp.tid()
        out[i] = k(q[i], d[i], alpha, m, mc, 0)

    out = wp.zeros(len(q), dtype=vec12, device="cpu")
    wp.launch(run, dim=len(q), inputs=[wp.array(q, dtype=vec12, device="cpu"), wp.array(d, dtype=vec12, device="cpu"),
                                       float(alpha), float(m), wp.vec3d(*mc), out], device="cpu")  # fmt: skip
    return out.numpy()


def test_retraction_path():
    """Newton's trial points (affine_body.retract): the path leaves q along d (first order, so
    Armijo's test holds), keeps a rotation a rotation, and moves the centre of mass by αd alone."""
    rng = np.random.default_rng(7)
    m, mc = 0.7, np.array([0.02, -0.05, 0.1])
    R0 = affine_body_rotation(rng)
    q = np.concatenate([rng.normal(size=3), R0.ravel()])
    W = np.array([[0.0, -0.3, 0.2], [0.3, 0.0, -0.1], [-0.2, 0.1, 0.0]])
    d = np.concatenate([rng.normal(size=3) * 0.1, (0.2 * W @ R0).ravel()])  # a rotation's tangent, |K| = 0.075
    got = _retract_warp(np.stack([q, q]), np.stack([d, d]), 0.5, m, mc)
    np.testing.assert_allclose(got[0], affine_body.retract_np(q, d, 0.5, m, mc), rtol=0, atol=1e-14)
    A = got[0][3:].reshape(3, 3)
    np.testing.assert_allclose(A @ A.T, np.eye(3), atol=1e-14)  # a straight step: off by ~|αK|² = 1.4e-3
    com = lambda x: x[:3] + x[3:].reshape(3, 3) @ (mc / m)  # noqa: E731
    np.testing.assert_allclose(com(got[0]), com(q) + 0.5 * (d[:3] + (0.2 * W @ R0) @ (mc / m)), atol=1e-14)
    # the initial guess (rigid): an extrapolated rotation plus its symmetric curvature part ½W²A
    # turns by Cayley alone and stays a rotation
    d2 = np.concatenate([np.zeros(3), ((0.1 * W + 0.5 * 0.01 * W @ W) @ R0).ravel()])
    A2 = affine_body.retract_np(q, d2, 1.0, m, mc, rigid=True)[3:].reshape(3, 3)
    np.testing.assert_allclose(A2 @ A2.T, np.eye(3), atol=1e-14)
    d3 = np.concatenate([np.zeros(3), (W @ R0).ravel()])
    assert np.abs(affine_body.retract_np(q, d3, 1.0, m, mc) - (q + d3)).max() == 0.0  # |K| = 0.37 rad: a line
    d = rng.normal(size=12) * 0.01
    for a in (1e-2, 1e-3):  # (retract(α) − q)/α → d with an O(α) error
        err = np.abs((affine_body.retract_np(q, d, a, m, mc) - q) / a - d).max()
        assert err < 2.0 * a * np.abs(d).max() ** 2 * (1 + np.abs(mc / m).max())


def affine_body_rotation(rng):
    Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return Q * np.sign(np.linalg.det(Q))


def test_inertia_derivatives():
    rng = np.random.default_rng(12)
    q, qt = near_rotation_q(rng), near_rotation_q(rng)
    com = rng.normal(scale=0.1, size=3)
    B = rng.normal(size=(3, 3))
    S = 0.01 * B @ B.T + 2.0 * np.outer(com, com)
    check_derivatives(lambda z: affine_body.inertia_np(z, qt, 2.0, com, S), q)
    E, g, M = affine_body.inertia_np(q, qt, 2.0, com, S)
    assert min_eig_ok(M)


@pytest.mark.parametrize("npts", [2, 4])  # revolute: 2 axis points, fixed: 4
def test_point_joint_derivatives(npts):
    rng = np.random.default_rng(13 + npts)
    for _ in range(3):
        loc, q_ref, q = random_joint(rng)
        pts_i, pts_j = rng.normal(size=(npts, 3)), rng.normal(size=(npts, 3))
        check_derivatives(lambda z: point_joint_np(z, pts_i, pts_j, 3.0), q)
        E, g, H = point_joint_np(q, pts_i, pts_j, 3.0)
        assert min_eig_ok(H)
        # E is K/2 Σ ‖x_i(P) − x_j(P)‖²
        xi = [q[:3] + q[3:12].reshape(3, 3) @ p for p in pts_i]
        xj = [q[12:15] + q[15:].reshape(3, 3) @ p for p in pts_j]
        assert E == pytest.approx(1.5 * sum(np.sum((a - b) ** 2) for a, b in zip(xi, xj)), rel=1e-13)


def _prismatic(q, loc, K=3.0):
    return prismatic_joint.prismatic_joint_np(q, loc["ci"], loc["cj"], loc["ti"], loc["tj"], loc["ni"], loc["nj"],
                                              loc["bi"], loc["bj"], K)  # fmt: skip


def test_prismatic_joint_derivatives_and_gauss_newton():
    rng = np.random.default_rng(15)
    for _ in range(3):
        loc, q_ref, q = random_joint(rng, eps=5e-2)
        check_derivatives(lambda z: _prismatic(z, loc), q)
        E, g, H, Hgn = _prismatic(q, loc)
        assert min_eig_ok(Hgn)
        assert rel_err(Hgn, H) > 1e-6  # violated: the dropped term is there
        # the seed's constraints, written out
        A_i, A_j = q[3:12].reshape(3, 3), q[15:].reshape(3, 3)
        c_i, c_j = q[:3] + A_i @ loc["ci"], q[12:15] + A_j @ loc["cj"]
        C = [np.cross(c_j - c_i, A_i @ loc["ti"]), np.cross(c_i - c_j, A_j @ loc["tj"]),
             A_i @ loc["ni"] - A_j @ loc["nj"], A_i @ loc["bi"] - A_j @ loc["bj"]]  # fmt: skip
        assert E == pytest.approx(1.5 * sum(v @ v for v in C), rel=1e-13)


def test_prismatic_gauss_newton_is_exact_when_the_constraint_holds():
    """Any common affine map of the two bodies plus a slide along t̂ keeps C0..C3 = 0: there the
    Gauss–Newton Hessian is the exact one."""
    rng = np.random.default_rng(16)
    for _ in range(3):
        loc, q_ref, _ = random_joint(rng)
        G = random_rotation(rng) + 0.05 * rng.normal(size=(3, 3))
        shift = rng.normal(size=3)
        qi = np.concatenate([G @ q_ref[:3] + shift, (G @ q_ref[3:12].reshape(3, 3)).ravel()])
        t_world = q_ref[3:12].reshape(3, 3) @ loc["ti"]
        qj = np.concatenate([G @ (q_ref[12:15] + 0.37 * t_world) + shift, (G @ q_ref[15:].reshape(3, 3)).ravel()])
        E, g, H, Hgn = _prismatic(np.concatenate([qi, qj]), loc)
        assert E < 1e-25 and np.abs(g).max() < 1e-12
        assert rel_err(Hgn, H) < 1e-12


def _rev_limit(q, q_prev, q_ref, loc, lower, upper, s):
    fr = (loc["ni"], loc["bi"], loc["nj"], loc["bj"])
    return revolute_limit.revolute_limit_np(q, q_prev, q_ref, fr, lower, upper, s)


def _angle(q, q_prev, q_ref, loc):
    return angles.revolute_angle_np(q, q_prev, q_ref, (loc["ni"], loc["bi"], loc["nj"], loc["bj"]))


def test_revolute_cubic_matches_the_seed():
    s, l, u = 7.0, -0.4, 0.9
    for x, want in ((1.2, s * 0.3**3), (-0.5, s * 0.1**3), (0.0, 0.0), (l, 0.0), (u, 0.0)):
        assert revolute_limit.cubic_np(x, l, u, s)[0] == pytest.approx(want, rel=1e-14)
    for x in (1.2, 0.9 + 1e-3, -0.5, -0.4 - 1e-3):
        e, de, dde = revolute_limit.cubic_np(x, l, u, s)
        assert de == pytest.approx(fd_grad(lambda z: revolute_limit.cubic_np(z[0], l, u, s)[0], np.array([x]))[0],
                                   rel=1e-6, abs=1e-12)  # fmt: skip
        assert dde == pytest.approx(fd_grad(lambda z: revolute_limit.cubic_np(z[0], l, u, s)[1], np.array([x]))[0],
                                    rel=1e-6)  # fmt: skip
    # not normalised by the range (unlike 669): E(u + 0.1) is s·0.1³ whatever the width
    assert revolute_limit.cubic_np(0.1 + 0.05, 0.0, 0.05, 2.0)[0] == pytest.approx(2.0 * 0.1**3, rel=1e-12)


@pytest.mark.parametrize("side", ["upper", "lower"])
def test_revolute_limit_derivatives_near_the_bounds(side):
    """x just past the bound (1e-3 .. 0.2 rad): gradient and exact Hessian against differences;
    the solver's E''∇x∇xᵀ is PSD, rank one, and E'' times the differenced ∇x."""
    rng = np.random.default_rng(17 if side == "upper" else 18)
    s = 50.0
    for over in (1e-3, 0.03, 0.2):
        loc, q_ref, q = random_joint(rng)
        q_prev = q + 0.03 * rng.normal(size=24)
        x = _angle(q, q_prev, q_ref, loc)[0]
        lower, upper = (x - 1.0, x - over) if side == "upper" else (x + over, x + 1.0)
        fn = lambda z: _rev_limit(z, q_prev, q_ref, loc, lower, upper, s)  # noqa: E731
        E, g, H, Hs = fn(q)
        assert E == pytest.approx(s * over**3, rel=1e-9)
        check_derivatives(fn, q)
        assert min_eig_ok(Hs)
        assert np.linalg.matrix_rank(Hs, tol=1e-10 * np.abs(Hs).max()) == 1
        gx = fd_grad(lambda z: _angle(z, q_prev, q_ref, loc)[0], q)
        assert rel_err(Hs, 6 * s * over * np.outer(gx, gx)) < 1e-6


def test_revolute_limit_is_exactly_zero_in_range_and_at_the_bounds():
    rng = np.random.default_rng(19)
    loc, q_ref, q = random_joint(rng)
    q_prev = q + 0.03 * rng.normal(size=24)
    x = _angle(q, q_prev, q_ref, loc)[0]
    for lower, upper in ((x, x + 0.5), (x - 0.5, x), (x, x), (x - 0.1, x + 0.1)):
        E, g, H, Hs = _rev_limit(q, q_prev, q_ref, loc, lower, upper, 1e3)
        assert E == 0.0 and not g.any() and not H.any() and not Hs.any()
    # one ulp past the bound it is no longer zero (the check above could fail)
    E, g, _, _ = _rev_limit(q, q_prev, q_ref, loc, x - 1.0, np.nextafter(x, -np.inf), 1e3)
    assert E > 0.0 and g.any()


@pytest.mark.parametrize("side", [+1, -1])
def test_revolute_limit_past_pi_uses_the_increment(side):
    """q_prev at ±(π − 0.01), q at ±(π + 0.02) (across the cut): x = ±(π + 0.02), so a limit at
    ±(π − 0.005) sees an overshoot of 0.025, not a jump to the other bound."""
    axis = (1.0, 2.0, 2.0)
    _, n, b = axis_frame(axis)
    loc = dict(ni=n, bi=b, nj=n, bj=b)
    eye = np.concatenate([np.zeros(3), np.eye(3).ravel()])
    q_ref = np.concatenate([eye, eye])
    q_prev = np.concatenate([eye, np.zeros(3), rot(axis, side * (math.pi - 0.01)).ravel()])
    q = np.concatenate([eye, np.zeros(3), rot(axis, side * (math.pi + 0.02)).ravel()])
    s = 1e3
    fn = lambda z: _rev_limit(z, q_prev, q_ref, loc, -math.pi + 0.005, math.pi - 0.005, s)  # noqa: E731
    E, g, H, Hs = fn(q)
    assert _angle(q, q_prev, q_ref, loc)[0] == pytest.approx(side * (math.pi + 0.02), abs=1e-12)
    assert E == pytest.approx(s * 0.025**3, rel=1e-9)
    check_derivatives(fn, q)
    # the force pushes back towards the range: along a spin about +t̂ the slope is +3s·0.025² (side +1)
    dq = np.zeros(24)
    dq[15:] = (np.array(rot(axis, 1e-6)) @ rot(axis, side * (math.pi + 0.02)) -
               np.array(rot(axis, -1e-6)) @ rot(axis, side * (math.pi + 0.02))).ravel() / 2e-6  # fmt: skip
    assert g @ dq == pytest.approx(side * 3 * s * 0.025**2, rel=1e-6)


def test_prismatic_cubic_range_normalisation_and_fallback():
    """669: s((x−u)/(u−l))³ above, s((l−x)/(u−l))³ below; s|x−l|³ when u = l; derivatives exact."""
    s = 4.0
    cases = [(-0.1, 0.3, 0.5), (-0.1, 0.3, -0.35), (-0.1, 0.3, 0.2), (-0.1, 0.3, 0.3), (-0.1, 0.3, -0.1),
             (0.2, 0.2, 0.5), (0.2, 0.2, -0.1), (0.2, 0.2, 0.2)]  # fmt: skip
    for l, u, x in cases:
        if u > l:
            want = s * ((x - u) / (u - l)) ** 3 if x > u else s * ((l - x) / (u - l)) ** 3 if x < l else 0.0
        else:
            want = s * abs(x - l) ** 3
        e, de, dde = prismatic_limit.cubic_np(x, l, u, s)
        assert e == pytest.approx(want, rel=1e-13, abs=0.0)
        if l <= x <= u:
            assert (e, de, dde) == (0.0, 0.0, 0.0)
        else:
            f = lambda z: prismatic_limit.cubic_np(z[0], l, u, s)  # noqa: E731
            assert de == pytest.approx(fd_grad(lambda z: f(z)[0], np.array([x]))[0], rel=1e-7)
            assert dde == pytest.approx(fd_grad(lambda z: f(z)[1], np.array([x]))[0], rel=1e-7)


@pytest.mark.parametrize("bounds", [(-0.2, 0.1), (0.05, 0.05)])
def test_prismatic_limit_derivatives(bounds):
    rng = np.random.default_rng(20)
    l, u = bounds
    for target in (u + 0.07, l - 0.03):
        loc, q_ref, q = random_joint(rng)
        x = angles.prismatic_displacement_np(q, loc["ci"], loc["cj"], loc["ti"])[0]
        t_i = q[3:12].reshape(3, 3) @ loc["ti"]  # moving p_j along t̂_i changes x by t̂_i·Δp_j
        q[12:15] += (target - x) * t_i / (t_i @ t_i)
        fn = lambda z: prismatic_limit.prismatic_limit_np(z, loc["ci"], loc["cj"], loc["ti"], l, u, 30.0)  # noqa: E731
        E, g, H, Hs = fn(q)
        width = u - l if u > l else 1.0
        assert E == pytest.approx(30.0 * (abs(target - (u if target > u else l)) / width) ** 3, rel=1e-9)
        check_derivatives(fn, q)
        assert min_eig_ok(Hs)
    # at the bounds: exactly zero
    for bound in (l, u):
        loc, q_ref, q = random_joint(rng)
        x = angles.prismatic_displacement_np(q, loc["ci"], loc["cj"], loc["ti"])[0]
        lo, up = (x, x + (u - l)) if bound == l else (x - (u - l), x)
        E, g, H, Hs = prismatic_limit.prismatic_limit_np(q, loc["ci"], loc["cj"], loc["ti"], lo, up, 30.0)
        assert E == 0.0 and not g.any() and not Hs.any()


def _clip(v, m):
    return min(max(v, -m), m)


@pytest.mark.parametrize("mode", [drive.EFFORT, drive.POSITION, drive.VELOCITY])
def test_drive_scalar_energy(mode):
    """E'(x) is the clipped generalised force: −clip(u) for motors, clip(k(x−x*) + (d/h)(x − x_prev − h v*))
    for PD (a Huber energy); E'' its derivative away from the kink; derivatives against differences."""
    h, xp, fmax = 0.01, 0.3, 2.0
    k, d = {drive.EFFORT: (0.0, 0.0), drive.POSITION: (40.0, 0.5), drive.VELOCITY: (0.0, 0.1)}[mode]
    for u in (-5.0, -0.7, 0.4, 1.5, 5.0):
        for x in (xp - 0.3, xp - 0.01, xp, xp + 0.003, xp + 0.02, xp + 0.5):
            e, de, dde = drive.drive_np(x, xp, u, mode, k, d, fmax, h)
            if mode == drive.EFFORT:
                assert (e, de, dde) == pytest.approx((-_clip(u, fmax) * (x - xp), -_clip(u, fmax), 0.0), rel=1e-14)
                continue
            xs, vs = (u, 0.0) if mode == drive.POSITION else (0.0, u)
            force = k * (x - xs) + d / h * (x - xp - h * vs)
            assert de == pytest.approx(_clip(force, fmax), rel=1e-12, abs=1e-12)
            assert dde == (k + d / h if abs(force) < fmax else 0.0)
            if abs(abs(force) - fmax) > 1e-3:  # central differences away from the kink
                f = lambda z: drive.drive_np(z[0], xp, u, mode, k, d, fmax, h)  # noqa: E731
                assert de == pytest.approx(fd_grad(lambda z: f(z)[0], np.array([x]))[0], rel=1e-7, abs=1e-9)
                assert dde == pytest.approx(fd_grad(lambda z: f(z)[1], np.array([x]))[0], rel=1e-7, abs=1e-9)
    # the Huber energy is continuous at the kink (the PD force is clipped, not the energy)
    if mode != drive.EFFORT:
        a = k + d / h
        xs, vs = (1.0, 0.0) if mode == drive.POSITION else (0.0, 1.0)  # control u = 1
        x0 = (k * xs + d / h * (xp + h * vs)) / a
        below = drive.drive_np(x0 + fmax / a * (1 - 1e-12), xp, 1.0, mode, k, d, fmax, h)[0]
        above = drive.drive_np(x0 + fmax / a * (1 + 1e-12), xp, 1.0, mode, k, d, fmax, h)[0]
        assert above == pytest.approx(below, rel=1e-9)


# ============================================================================ 3/4. Warp vs NumPy
BASE_POSE = dict(position=(0.1, 0.0, 0.2), rotation=rot((1, 0, 0), 0.3))
REV_ANCHOR, REV_AXIS = np.array([0.05, 0.05, 0.0]), np.array([1.0, 2.0, 2.0]) / 3.0
PRI_ANCHOR, PRI_AXIS = np.array([0.2, 0.1, -0.4]), np.array([1.0, 0.0, -1.0]) / math.sqrt(2.0)
HINGE2_ANCHOR, HINGE2_AXIS = np.array([0.6, 0.25, -0.55]), np.array([-0.3, 0.9, 0.3]) / math.sqrt(0.99)
REV_LIMIT, PRI_LIMIT, HINGE2_LIMIT = (-0.5, 0.6, 1e3), (-0.1, 0.2, 1e2), (-0.3, 0.4, 2e2)
LIMITS = {0: REV_LIMIT, 1: PRI_LIMIT, 3: HINGE2_LIMIT}  # joint index -> (lower, upper, strength)


def build_scene():
    """Fixed base —revolute 0 (limit, position + effort drives)— link1 —prismatic 1 (limit, velocity +
    effort drives; link2 is body_a)— link2 —fixed 2— link3 (explicit inertia, com off the origin)
    —revolute 3 (limit, position drive; both bodies free, link4 is body_a)— link4."""
    sc = ag.Scene(gravity=(0.3, -0.2, -9.81))
    base = sc.add_body(ag.Box((0.1, 0.1, 0.1)), fixed=True, **BASE_POSE)
    l1 = sc.add_body(ag.Box((0.05, 0.1, 0.2)), mass=1.3, rotation=rot((0, 1, 1), 0.7), position=(0.0, 0.1, -0.3))
    l2 = sc.add_body(ag.Cylinder(0.05, 0.2), mass=0.7, rotation=rot((1, 1, 0), -0.4), position=(0.3, 0.1, -0.5),
                     stiffness=3e7)  # fmt: skip
    l3 = sc.add_body(ag.Inertia(0.5, com=(0.01, 0.02, -0.01), inertia=((2e-3, 1e-4, 0), (1e-4, 3e-3, 0), (0, 0, 4e-3))),
                     position=(0.5, 0.2, -0.5), rotation=rot((1, 2, 3), 1.0))  # fmt: skip
    l4 = sc.add_body(ag.Capsule(0.04, 0.1), mass=0.4, rotation=rot((2, -1, 1), 2.0), position=(0.7, 0.3, -0.6))
    r = sc.add_revolute_joint(base, l1, anchor=REV_ANCHOR, axis=REV_AXIS, strength_ratio=80.0)
    sc.add_revolute_limit(r, *REV_LIMIT)
    p = sc.add_prismatic_joint(l2, l1, anchor=PRI_ANCHOR, axis=PRI_AXIS, strength_ratio=120.0)
    sc.add_prismatic_limit(p, *PRI_LIMIT)
    sc.add_fixed_joint(l2, l3, strength_ratio=50.0)
    r2 = sc.add_revolute_joint(l4, l3, anchor=HINGE2_ANCHOR, axis=HINGE2_AXIS, strength_ratio=60.0)
    sc.add_revolute_limit(r2, *HINGE2_LIMIT)
    sc.add_drive(r, "position", stiffness=50.0, damping=2.0, max_effort=5.0)
    sc.add_drive(r, "effort", max_effort=3.0)
    sc.add_drive(p, "velocity", damping=20.0, max_effort=4.0)
    sc.add_drive(p, "effort", max_effort=3.0)
    sc.add_drive(r2, "position", stiffness=8.0, damping=0.5, max_effort=1.0)
    return sc


class SceneRef:
    """The NumPy reference of a whole scene, built from the Scene alone (not from the Model)."""

    def __init__(self, scene, dt, h_eff=None):
        self.scene, self.h = scene, dt
        self.h_eff = dt if h_eff is None else h_eff  # BDF2: physical potentials sit inside ĥ², ĥ = 2h/3
        self.bodies = scene.bodies
        self.dof, n = [], 0
        for b in self.bodies:
            self.dof.append(-1 if b.fixed else n)
            n += 0 if b.fixed else 12
        self.n = n
        self.q0 = np.stack([b.q() for b in self.bodies])
        self.joints = []
        for j in scene.joints:
            A, B = self.bodies[j.body_a], self.bodies[j.body_b]
            la, lb = (lambda x, X=X: X.rotation.T @ (x - X.position) for X in (A, B))
            da, db = (lambda v, X=X: X.rotation.T @ v for X in (A, B))
            t, nn, bb = axis_frame(j.frame[0])
            np.testing.assert_allclose(j.frame, np.stack([t, nn, bb]))
            L = j.half_length
            world = [j.anchor] + [j.anchor + L * e for e in np.eye(3)] if j.kind == "fixed" else \
                [j.anchor + L * t, j.anchor - L * t]  # fmt: skip
            self.joints.append(dict(
                kind=j.kind, a=j.body_a, b=j.body_b, K=j.strength_ratio * (A.mass + B.mass),
                pts_i=[la(x) for x in world], pts_j=[lb(x) for x in world],
                ci=la(j.anchor), cj=lb(j.anchor), ti=da(t), tj=db(t), ni=da(nn), nj=db(nn), bi=da(bb), bj=db(bb),
            ))  # fmt: skip

    def pair(self, q, j):
        return np.concatenate([q[j["a"]], q[j["b"]]])

    def frames(self, j):
        return j["ni"], j["bi"], j["nj"], j["bj"]

    def _scatter(self, out, name, e, j, g24, H24):
        E, g, H = out.setdefault(name, [0.0, np.zeros(self.n), np.zeros((self.n, self.n))])
        out[name][0] = E + e
        for si, bi in enumerate((j["a"], j["b"])):
            oi = self.dof[bi]
            if oi < 0:
                continue
            g[oi : oi + 12] += g24[12 * si : 12 * si + 12]
            for sj, bj in enumerate((j["a"], j["b"])):
                oj = self.dof[bj]
                if oj >= 0:
                    H[oi : oi + 12, oj : oj + 12] += H24[12 * si : 12 * si + 12, 12 * sj : 12 * sj + 12]

    def coordinate(self, q, q_prev, unwrapped, k):
        """Drive coordinate of joint k (multi-turn angle / displacement), its gradient and Hessian of x."""
        j = self.joints[k]
        if j["kind"] == "revolute":
            cs = [tuple(v[0] for v in angles.cos_sin_np(self.pair(s, j), *self.frames(j))) for s in (q, q_prev)]
            _, gx, _ = angles.revolute_angle_np(self.pair(q, j), self.pair(q_prev, j), self.pair(self.q0, j),
                                                self.frames(j))  # fmt: skip
            return unwrapped[k] + angles.delta_theta_np(cs[0], cs[1]), gx
        x, gx, _ = angles.prismatic_displacement_np(self.pair(q, j), j["ci"], j["cj"], j["ti"])
        return x, gx

    def solve_terms(self, q, q_prev, q_tilde, unwrapped, control, limits, x_anchor=None):
        """name -> [E, g, H] of the incremental potential's terms for one world, with the solver's
        Hessians: PSD orthogonality, Gauss–Newton prismatic, E''∇x∇xᵀ for limits and drives.
        ``x_anchor``: where PD damping measures the step from (xⁿ; BDF2's x̂ = (4xⁿ − xⁿ⁻¹)/3)."""
        h2, out = self.h_eff**2, {}
        x_anchor = unwrapped if x_anchor is None else x_anchor
        for k, b in enumerate(self.bodies):
            if b.fixed:
                continue
            o = self.dof[k]
            e, g, M = affine_body.inertia_np(q[k], q_tilde[k], b.mass, b.moments.com, b.moments.second_moment)
            V, gv, _, Hp = affine_body.orthogonality_np(q[k], b.stiffness * b.shape.volume())
            for name, ee, gg, HH in (("inertia", e, g, M), ("orthogonality", h2 * V, h2 * gv, h2 * Hp)):
                E_, g_, H_ = out.setdefault(name, [0.0, np.zeros(self.n), np.zeros((self.n, self.n))])
                out[name][0] = E_ + ee
                g_[o : o + 12] += gg
                H_[o : o + 12, o : o + 12] += HH
        for k, j in enumerate(self.joints):
            qp = self.pair(q, j)
            if j["kind"] == "prismatic":
                E, g, _, Hgn = prismatic_joint.prismatic_joint_np(qp, j["ci"], j["cj"], j["ti"], j["tj"], j["ni"],
                                                                  j["nj"], j["bi"], j["bj"], j["K"])  # fmt: skip
                self._scatter(out, "prismatic_joint", E, j, g, Hgn)
                if k in limits:
                    E, g, _, Hs = prismatic_limit.prismatic_limit_np(qp, j["ci"], j["cj"], j["ti"], *limits[k])
                    self._scatter(out, "prismatic_limit", E, j, g, Hs)
            else:
                E, g, H = point_joint_np(qp, j["pts_i"], j["pts_j"], j["K"])
                self._scatter(out, f"{j['kind']}_joint", E, j, g, H)
                if k in limits:
                    E, g, _, Hs = revolute_limit.revolute_limit_np(qp, self.pair(q_prev, j), self.pair(self.q0, j),
                                                                   self.frames(j), *limits[k])  # fmt: skip
                    self._scatter(out, "revolute_limit", E, j, g, Hs)
        for d, dr in enumerate(self.scene.drives):
            j = self.joints[dr.joint]
            x, gx = self.coordinate(q, q_prev, unwrapped, dr.joint)
            anchor = unwrapped[dr.joint] if dr.mode == "effort" else x_anchor[dr.joint]
            e, de, dde = drive.drive_np(x, anchor, control[d], drive.MODES[dr.mode], dr.stiffness, dr.damping,
                                        dr.max_effort, self.h_eff)  # fmt: skip
            self._scatter(out, "drive", h2 * e, j, h2 * de * gx, h2 * dde * np.outer(gx, gx))
        return out

    def physical(self, q, qd, q_prev, unwrapped, control, limits):
        """Each term's own energy [J] (what Simulator.energies() reports), for one world."""
        out = dict(kinetic=0.0, gravity=0.0, orthogonality=0.0, drive=0.0)
        g = self.scene.gravity
        for k, b in enumerate(self.bodies):
            if b.fixed:
                continue
            M = affine.mass_matrix(b.mass, b.moments.com, b.moments.second_moment)
            out["kinetic"] += 0.5 * qd[k] @ M @ qd[k]
            out["gravity"] -= g @ (b.mass * q[k, :3] + q[k, 3:].reshape(3, 3) @ (b.mass * b.moments.com))
            out["orthogonality"] += affine_body.orthogonality_np(q[k], b.stiffness * b.shape.volume())[0]
        terms = self.solve_terms(q, q_prev, q, unwrapped, control, limits)
        for name in ("revolute_limit", "prismatic_limit"):  # physical: stiffness s/h² (the next step's)
            out[name] = terms[name][0] / self.h**2
        for name in ("revolute_joint", "prismatic_joint", "fixed_joint"):  # physical: stiffness K/ĥ₀²
            out[name] = terms[name][0] / self.h_eff**2
        for d, dr in enumerate(self.scene.drives):
            if dr.mode == "position":
                x, _ = self.coordinate(q, q_prev, unwrapped, dr.joint)
                out["drive"] += 0.5 * dr.stiffness * (x - control[d]) ** 2
        return out


PART_TERMS = {"affine_body": ("inertia", "orthogonality")}


@pytest.fixture(scope="module")
def scene():
    return build_scene()


@pytest.fixture(scope="module")
def ref(scene):
    return SceneRef(scene, 0.01)


@pytest.fixture(scope="module")
def sims(scene):
    # one_launch=False: the fused kernel is Newton alone, so test_fused_step_assembles_the_same_system
    # can run one iteration on a loaded state (one_launch would open the step first: a new prediction)
    # implicit Euler: the reference's h (a BDF2 step's ĥ = 2h/3 is checked by its own test)
    plan = ag.ExecutionPlan(one_launch=False)
    return {dt: ag.Simulator(scene, num_worlds=2, dt=0.01, dtype=dt, integrator="implicit_euler", plan=plan)
            for dt in ("float64", "float32")}


def move_subtree(q, bodies, R, c, d=np.zeros(3)):
    q = q.copy()
    for b in bodies:
        q[b] = rigid_motion(q[b], R, c, d)
    return q


def pose(ref, rev_angle, slide, hinge2_angle):
    """Forward kinematics from the zero pose (children first, then each parent moves its subtree)."""
    q = move_subtree(ref.q0, [4], rot(HINGE2_AXIS, hinge2_angle), HINGE2_ANCHOR)
    # the slider's body_a is link2: x = t̂_a·(c_b − c_a) grows when link2 moves along −t̂
    q = move_subtree(q, [2, 3, 4], np.eye(3), np.zeros(3), -slide * PRI_AXIS)
    return move_subtree(q, [1, 2, 3, 4], rot(REV_AXIS, rev_angle), REV_ANCHOR)


def make_case(ref, rng, rev_angles, slides, hinge2_angles=(0.0, 0.0), noise=(0.02, 0.01), limits=None,
              prev_angles=None):  # fmt: skip
    """Per world: the pose at the given joint coordinates plus position noise and affine noise on the
    free bodies; q_prev a little off q (or, with prev_angles, exactly at that first-hinge angle).
    Drive controls put world 0 on the linear (unclipped) branch of every PD drive and world 1 on the
    clipped one; effort controls inside and beyond max_effort."""
    W = len(rev_angles)
    nb = len(ref.bodies)
    q, q_prev = np.empty((W, nb, 12)), np.empty((W, nb, 12))
    for w in range(W):
        qw = pose(ref, rev_angles[w], slides[w], hinge2_angles[w])
        np.testing.assert_array_equal(qw[0], ref.q0[0])
        qw[1:, :3] += noise[0] * rng.normal(size=(nb - 1, 3))
        qw[1:, 3:] += noise[1] * rng.normal(size=(nb - 1, 9))
        q[w] = qw
        q_prev[w] = qw
        q_prev[w, 1:] += 0.01 * rng.normal(size=(nb - 1, 12))
        if prev_angles is not None:
            q_prev[w] = pose(ref, prev_angles[w], 0.0, 0.0)
    q_tilde = q + 0.02 * rng.normal(size=q.shape)
    q_tilde[:, 0] = q[:, 0]
    qd = rng.normal(size=q.shape)
    qd[:, 0] = 0.0
    limits = limits or [LIMITS] * W
    nj = len(ref.joints)
    unwrapped = np.zeros((W, nj))
    control = np.empty((W, len(ref.scene.drives)))
    h = ref.h_eff
    for w in range(W):
        for k, j in enumerate(ref.joints):
            if j["kind"] == "revolute":
                cs, cs_ref = (tuple(v[0] for v in angles.cos_sin_np(ref.pair(s, j), *ref.frames(j))) for s in
                              (q_prev[w], ref.q0))  # fmt: skip
                # joint 0's multi-turn angle has gone once round: the drives must use it, not θ0
                unwrapped[w, k] = angles.delta_theta_np(cs, cs_ref) + (2 * math.pi if k == 0 else 0.0)
            elif j["kind"] == "prismatic":
                unwrapped[w, k] = angles.prismatic_displacement_np(ref.pair(q_prev[w], j), j["ci"], j["cj"], j["ti"])[0]
        x = [ref.coordinate(q[w], q_prev[w], unwrapped[w], k)[0] if ref.joints[k]["kind"] != "fixed" else 0.0
             for k in range(nj)]  # fmt: skip
        lin = w == 0
        # position drive: force k(x − u) + (d/h)(x − x_prev) = f  ->  u;  velocity: (d/h)(x − x_prev − h v) = f  ->  v
        u0 = x[0] - ((2.0 if lin else 40.0) - 2.0 / h * (x[0] - unwrapped[w, 0])) / 50.0
        v2 = (x[1] - unwrapped[w, 1] - (-1.5 if lin else -30.0) * h / 20.0) / h
        u4 = x[3] - ((0.3 if lin else -6.0) - 0.5 / h * (x[3] - unwrapped[w, 3])) / 8.0
        control[w] = [u0, 2.0 if lin else -7.0, v2, -1.0 if lin else 9.0, u4]
    return dict(q=q, q_prev=q_prev, q_tilde=q_tilde, qd=qd, unwrapped=unwrapped, control=control, limits=limits)


def load(sim, case):
    """Write a case into the simulator: θ0 and cos/sin θ of q_prev via solver.begin (as _set_q does)."""
    st, npd = sim.state, sim.model.np_dtype
    st.status.zero_()
    # the multi-turn coordinate (and BDF2's previous one) first: begin() derives the drives' anchor from them
    st.unwrapped.assign(case["unwrapped"].astype(npd))
    if hasattr(st, "x_hist"):
        st.x_hist.assign(case.get("x_hist", case["unwrapped"]).astype(npd))
    st.q.assign(case["q_prev"].astype(npd))
    sim.solver.begin(st, sim.solver.all_active)
    st.q.assign(case["q"].astype(npd))
    st.q_prev.assign(case["q_prev"].astype(npd))
    st.qd.assign(case["qd"].astype(npd))
    st.control.assign(case["control"].astype(npd))
    sim.solver.q_tilde.assign(case["q_tilde"].astype(npd))
    for k in case["limits"][0]:
        lo, up, s = (np.array([lim[k][i] for lim in case["limits"]]) for i in range(3))
        sim.set_limit(k, lower=lo, upper=up, strength=s, check_state=False)  # the case sets the state


def assemble(sim, parts=None, derivs=HESSIAN):
    """Zero E/g/H and assemble every term (parts=None) or the listed constitution modules."""
    s = sim.solver
    s.E.zero_()
    s.g.zero_()
    s.H.zero_()
    if parts is None:
        s.assemble(sim.state, sim.state.q, s.E, s.all_active, derivs)
    else:
        for c in parts:
            c.launch(sim.model, sim.state, s, sim.state.q, s.E, s.g, s.H, s.all_active, derivs, s.cols)
    return s.E.numpy().astype(np.float64), s.gradient().astype(np.float64), s.hessian().astype(np.float64)


def reference(ref, case):
    W = case["q"].shape[0]
    anchor = case["unwrapped"]
    if "x_hist" in case:  # BDF2
        anchor = (4 * case["unwrapped"] - case["x_hist"]) / 3
    return [ref.solve_terms(case["q"][w], case["q_prev"][w], case["q_tilde"][w], case["unwrapped"][w],
                            case["control"][w], case["limits"][w], anchor[w]) for w in range(W)]  # fmt: skip


def close(a, b, rtol, atol=0.0):
    a, b = np.asarray(a, float), np.asarray(b, float)
    return np.linalg.norm(a - b) <= rtol * np.linalg.norm(b) + atol


def compare(sim, ref, case, rtol, check_active=True):
    """Per constitution: energy column, gradient and Hessian against the reference; then the full
    assembly.  Returns the reference (for callers that look at particular terms)."""
    want = reference(ref, case)
    W = len(want)
    load(sim, case)
    cols = sim.solver.cols
    n = ref.n
    for part in sim.solver.parts:
        names = PART_TERMS.get(part.name, (part.name,))
        # float32 PD drives: the force a(x − x0), a = k + d/h (250 and 2000 here), loses a·|x|·ε₃₂ to the
        # rounding of x (the multi-turn angle is near 2π + ...): ~1e-4 of a 2 N·m force, so 10x the tolerance.
        tol = 10 * rtol if part.name == "drive" and sim.model.dtype == wp.float32 else rtol
        E, g, H = assemble(sim, [part])
        for w in range(W):
            for name in names:
                e_ref = want[w][name][0]
                assert E[w, cols[name]] == pytest.approx(e_ref, rel=tol, abs=1e-300), (name, w)
            g_ref = sum(want[w][name][1] for name in names)
            H_ref = sum(want[w][name][2] for name in names)
            scale = max(np.linalg.norm(want[w][nm][1]) for nm in names) + 1e-300
            assert close(g[w], g_ref, tol, atol=tol * 1e-6 * scale), (part.name, w, g[w], g_ref)
            assert close(H[w], H_ref, tol), (part.name, w)
            if check_active and part.name not in ("revolute_limit", "prismatic_limit"):
                assert np.linalg.norm(g_ref) > 0
    E, g, H = assemble(sim)
    for w in range(W):
        assert close(E[w], [want[w][name][0] for name in cols], rtol)
        assert close(g[w], sum(v[1] for v in want[w].values()), rtol)
        assert close(H[w], sum(v[2] for v in want[w].values()), rtol)
        assert g[w].shape == (n,)
    return want


CASES = {
    # world 0 past every upper bound, world 1 below every lower one (hinge 2 turns link4 = body_a: x = −angle)
    "limits_active": dict(rev_angles=(0.75, -0.7), slides=(0.3, -0.25), hinge2_angles=(-0.55, 0.45)),
    "in_range": dict(rev_angles=(0.1, -0.3), slides=(0.05, -0.05), hinge2_angles=(0.1, -0.2)),
}


@pytest.mark.parametrize("dtype, rtol", [("float64", 1e-10), ("float32", 1e-4)])
@pytest.mark.parametrize("case_name", list(CASES))
def test_warp_matches_numpy(sims, ref, dtype, rtol, case_name):
    rng = np.random.default_rng(30 + sorted(CASES).index(case_name))
    case = make_case(ref, rng, **CASES[case_name])
    want = compare(sims[dtype], ref, case, rtol)
    active = case_name == "limits_active"
    for w in range(2):
        for name in ("revolute_limit", "prismatic_limit"):
            assert (want[w][name][0] > 0) == active, (name, w)
        # every PD drive is on its linear branch in world 0 and clipped in world 1
        for d, dr in enumerate(ref.scene.drives):
            if dr.mode != "effort":
                x, _ = ref.coordinate(case["q"][w], case["q_prev"][w], case["unwrapped"][w], dr.joint)
                dde = drive.drive_np(x, case["unwrapped"][w, dr.joint], case["control"][w, d], drive.MODES[dr.mode],
                                     dr.stiffness, dr.damping, dr.max_effort, ref.h)[2]  # fmt: skip
                assert (dde > 0) == (w == 0), (d, w)
    if active:  # the case covers what it claims: world 0 above every upper bound, world 1 below every lower one
        for k, (lo, up, _) in LIMITS.items():
            j = ref.joints[k]
            for w, sign in ((0, 1), (1, -1)):
                if j["kind"] == "revolute":
                    x = angles.revolute_angle_np(ref.pair(case["q"][w], j), ref.pair(case["q_prev"][w], j),
                                                 ref.pair(ref.q0, j), ref.frames(j))[0]  # fmt: skip
                else:
                    x = ref.coordinate(case["q"][w], case["q_prev"][w], case["unwrapped"][w], k)[0]
                assert sign * (x - (up if w == 0 else lo)) > 0.02, (k, w, x)


@pytest.mark.parametrize("case_name", list(CASES))
def test_fused_assembly_matches_staged(sims, ref, case_name):
    """The fused step's assembly (its own Hessian puts: a body's block from its parts, point joints'
    4 × 4 Kronecker factors, a fixed body's blocks skipped) gives the staged kernels' energy,
    gradient and lower-triangular Hessian, every constitution with limits and drives active or not."""
    check_fused_system(sims["float64"], ref, case_name)


def check_fused_system(sim, ref, case_name):
    """The fused step's energy, gradient and lower-triangular Hessian (sim.solver.fused_system) at a
    case against the staged kernels' (float64)."""
    case = make_case(ref, np.random.default_rng(36 + sorted(CASES).index(case_name)), **CASES[case_name])
    load(sim, case)
    E, g, H = assemble(sim)
    for derivs in (HESSIAN, GRADIENT):
        Ef, gf, Hf = sim.solver.fused_system(sim.state, derivs)
        np.testing.assert_allclose(Ef, E.sum(axis=1), rtol=1e-12)
        np.testing.assert_allclose(gf, g, rtol=1e-11, atol=1e-11 * np.abs(g).max())
        if derivs == HESSIAN:
            np.testing.assert_allclose(Hf, np.tril(H), rtol=1e-11, atol=1e-11 * np.abs(H).max())
        else:
            assert not Hf.any()


@pytest.mark.parametrize("lanes, groups, band", [(8, 1, False), (15, 3, False), (15, 3, True)])
def test_lane_split_assembly_matches_staged(scene, ref, lanes, groups, band):
    """scratch="lanes": each lane adds only its own rows of every term's blocks (rows i ≡ lane mod
    lanes), as cooperative CPU fibers, and together they give the staged kernels' energy, gradient
    and lower-triangular Hessian (H packed in the scratch).  15 lanes in 3 groups: each group of 5
    (which split a 12-row block unevenly) adds its share of the terms to its own copy (the bodies
    on the first, the joints, limits and drives, of every kind, on the other two), and the copies'
    sum is the whole system.  (A prismatic joint's limit and a drive on it ride on the joint's own
    term, and a revolute joint's limit and drives are one term on its angle, terms.joint_terms:
    five kinds of work are left.)  ``band``: each copy holds only the block band of the scene's
    four bodies (Model.banded), packed."""
    import warp as wp

    before = wp.config.enable_cpu_blocks
    wp.config.enable_cpu_blocks = True
    try:
        sim = ag.Simulator(scene, num_worlds=2, dt=0.01, dtype="float64", device="cpu", integrator="implicit_euler",
                           plan=ag.ExecutionPlan(scratch="lanes", block_dim=lanes, lane_groups=groups,
                                                 envelope=band))  # fmt: skip
        assert sim.solver.block_dim == lanes and sim.solver.lane_groups == groups and sim.solver.band == band
        sim.solver.fused_system(sim.state)  # builds the kernel and the groups' shares
        if groups > 1:
            kinds, _, counts = sim.solver.work
            from abd_gym.solver import fused

            left = {int(k) for c in range(groups) for k in kinds[c, : counts[c]]}
            assert (counts[1:] > 0).all() and len(left) == 5 and fused.WORK_ANGLE in left
            assert fused.WORK_PRISMATIC_LIMIT not in left and fused.WORK_REVOLUTE_LIMIT not in left
        for case_name in CASES:
            check_fused_system(sim, ref, case_name)
    finally:
        wp.config.enable_cpu_blocks = before


def test_gradient_only_assembly(sims, ref):
    """derivs=GRADIENT (an iteration that reuses its Cholesky factor) adds the same energies and
    gradient as HESSIAN, and nothing to H, for every constitution with its limits active."""
    sim = sims["float64"]
    case = make_case(ref, np.random.default_rng(35), **CASES["limits_active"])
    load(sim, case)
    E, g, H = assemble(sim)
    E1, g1, H1 = assemble(sim, derivs=GRADIENT)
    np.testing.assert_array_equal(E1, E)
    np.testing.assert_allclose(g1, g, rtol=1e-13, atol=1e-13 * np.abs(g).max())
    assert np.abs(H).max() > 0 and not H1.any()


@pytest.mark.parametrize("dtype, rtol", [("float64", 1e-10), ("float32", 1e-4)])
def test_warp_prismatic_limit_fallback_and_normalisation(sims, ref, dtype, rtol):
    """Per-world bounds: world 0 a zero-width range (u = l, s|x−l|³), world 1 a wide one ((x−u)/(u−l))."""
    rng = np.random.default_rng(5)
    case = make_case(ref, rng, rev_angles=(0.2, 0.2), slides=(0.3, 0.3))
    case["limits"] = [{**LIMITS, 1: (0.1, 0.1, 50.0)}, {**LIMITS, 1: (-0.5, 0.15, 50.0)}]
    want = compare(sims[dtype], ref, case, rtol)
    x = [ref.coordinate(case["q"][w], case["q_prev"][w], case["unwrapped"][w], 1)[0] for w in range(2)]
    assert want[0]["prismatic_limit"][0] == pytest.approx(50.0 * abs(x[0] - 0.1) ** 3, rel=1e-12)
    assert want[1]["prismatic_limit"][0] == pytest.approx(50.0 * ((x[1] - 0.15) / 0.65) ** 3, rel=1e-12)


@pytest.mark.parametrize("dtype, rtol", [("float64", 1e-10), ("float32", 1e-4)])
def test_warp_revolute_limit_across_pi(sims, ref, dtype, rtol):
    """q_prev just inside ±π, q across the cut: the kernel's x = θ0 + δ goes past ±π by the increment
    (a limit at ±(π − 0.005) pushes back), the drives count the multi-turn angle."""
    rng = np.random.default_rng(6)
    lim = (-math.pi + 0.005, math.pi - 0.005, 1e3)
    case = make_case(ref, rng, rev_angles=(math.pi + 0.02, -math.pi - 0.02), slides=(0.0, 0.0),
                     limits=[{**LIMITS, 0: lim}] * 2, prev_angles=(math.pi - 0.01, -math.pi + 0.01))  # fmt: skip
    j0 = ref.joints[0]
    xs = [angles.revolute_angle_np(ref.pair(case["q"][w], j0), ref.pair(case["q_prev"][w], j0),
                                   ref.pair(ref.q0, j0), ref.frames(j0))[0] for w in range(2)]  # fmt: skip
    assert xs[0] > math.pi + 0.005 and xs[1] < -math.pi - 0.005
    want = compare(sims[dtype], ref, case, rtol)
    assert want[0]["revolute_limit"][0] > 0 and want[1]["revolute_limit"][0] > 0
    # the coordinate the simulator reports agrees
    sim = sims[dtype]
    sim.solver.update_coordinates(sim.state, accumulate=False)
    np.testing.assert_allclose(sim.joint_coordinates()[:, 0], xs, rtol=0, atol=1e-12 if dtype == "float64" else 1e-5)


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_warp_revolute_limit_exactly_zero_at_the_bounds(sims, ref, dtype):
    """Bounds set to the kernel's own x (read back as the joint coordinate): energy, gradient and
    Hessian exactly zero, also just inside the range; a few ulps past the bound they are not."""
    sim = sims[dtype]
    rng = np.random.default_rng(7)
    case = make_case(ref, rng, rev_angles=(0.3, -0.2), slides=(0.05, 0.05), hinge2_angles=(0.2, -0.1))
    load(sim, case)
    sim.solver.update_coordinates(sim.state, accumulate=False)
    eps = np.finfo(sim.model.np_dtype).eps
    for k, other in ((0, 3), (3, 0)):  # hinge 0 (base fixed) and hinge 3 (both bodies free)
        x = sim.joint_coordinates()[:, k]
        sim.set_limit(other, lower=-3.0, upper=3.0, strength=1e3)
        for lo, up in ((x, x + 0.5), (x - 0.5, x), (x, x), (x - 0.5, x + 1e-4), (x - 1e-4, x + 0.5)):
            sim.set_limit(k, lower=lo, upper=up, strength=1e3)
            E, g, H = assemble(sim, [revolute_limit])
            assert not E.any() and not g.any() and not H.any(), (k, lo, up)
        sim.set_limit(k, lower=x - 0.5, upper=x - 4 * eps * np.abs(x), strength=1e3)
        E, g, H = assemble(sim, [revolute_limit])
        assert (E[:, sim.solver.cols["revolute_limit"]] > 0).all() and g.any(axis=1).all()
        sim.set_limit(k, lower=x + 4 * eps * np.abs(x), upper=x + 0.5, strength=1e3)
        E, g, H = assemble(sim, [revolute_limit])
        assert (E[:, sim.solver.cols["revolute_limit"]] > 0).all() and g.any(axis=1).all()


@pytest.mark.parametrize("dtype, rtol", [("float64", 1e-10), ("float32", 1e-4)])
def test_energies_report_each_terms_own_formula(sims, ref, dtype, rtol):
    """energies(): orthogonality without h², joints K/(2ĥ₀²)Σ‖C‖², limits the seed's E(x)/h², kinetic
    ½q̇ᵀMq̇, gravity −g·(m p + A m c), drive ½k(x − x*)² of position drives."""
    rng = np.random.default_rng(8)
    case = make_case(ref, rng, rev_angles=(0.75, -0.7), slides=(0.3, -0.25))
    sim = sims[dtype]
    load(sim, case)
    got = sim.energies()
    assert set(got) == {"kinetic", "gravity", "orthogonality", "revolute_joint", "prismatic_joint", "fixed_joint",
                        "revolute_limit", "prismatic_limit", "drive"}  # fmt: skip
    for w in range(2):
        want = ref.physical(case["q"][w], case["qd"][w], case["q_prev"][w], case["unwrapped"][w], case["control"][w],
                            case["limits"][w])  # fmt: skip
        for name, value in want.items():
            assert value != 0.0, name
            assert got[name][w] == pytest.approx(value, rel=rtol), (name, w)


# ============================================================================ 5. mass moments
def _monte_carlo(inside, half, rng, n=400_000):
    """Volume and ∫x xᵀ dV of a region inside the box [-half, half] by Monte-Carlo."""
    half = np.asarray(half, float)
    x = rng.uniform(-half, half, size=(n, 3))
    x = x[inside(x)]
    box = np.prod(2 * half)
    return box * len(x) / n, box * np.einsum("ni,nj->ij", x, x) / n


SHAPES = [
    (ag.Box((0.1, 0.2, 0.35)), lambda x: np.ones(len(x), bool), (0.1, 0.2, 0.35)),
    (ag.Sphere(0.3), lambda x: np.sum(x**2, 1) <= 0.09, (0.3, 0.3, 0.3)),
    (ag.Cylinder(0.1, 0.4), lambda x: (x[:, 0] ** 2 + x[:, 1] ** 2 <= 0.01) & (np.abs(x[:, 2]) <= 0.4),
     (0.1, 0.1, 0.4)),
    (ag.Capsule(0.15, 0.2),
     lambda x: x[:, 0] ** 2 + x[:, 1] ** 2 + np.maximum(np.abs(x[:, 2]) - 0.2, 0.0) ** 2 <= 0.0225, (0.15, 0.15, 0.35)),
]  # fmt: skip


@pytest.mark.parametrize("shape, inside, half", SHAPES, ids=["box", "sphere", "cylinder", "capsule"])
def test_shape_moments_against_monte_carlo(shape, inside, half):
    rng = np.random.default_rng(9)
    vol, second = _monte_carlo(inside, half, rng)
    assert shape.volume() == pytest.approx(vol, rel=1e-2)
    m = shape.moments(mass=2.5)
    assert m.mass == 2.5 and not m.com.any()
    want = 2.5 * second / vol
    np.testing.assert_allclose(m.second_moment, want, rtol=1e-2, atol=1e-2 * np.abs(want).max())
    # density path: mass = ρ V
    assert shape.moments(density=700.0).mass == pytest.approx(700.0 * shape.volume(), rel=1e-14)


def test_capsule_limits_are_a_sphere_and_a_long_cylinder():
    r = 0.2
    np.testing.assert_allclose(ag.Capsule(r, 1e-9).unit_second_moment(), ag.Sphere(r).unit_second_moment(), rtol=1e-6)
    long = ag.Capsule(r, 1e4).unit_second_moment()
    np.testing.assert_allclose(long, ag.Cylinder(r, 1e4).unit_second_moment(), rtol=1e-4)


def test_inertia_round_trip_and_mass_matrix():
    """An explicit inertia tensor about the com gives back tr(Σ)·1 − Σ = I about the com, with
    Σ = S − m c cᵀ; it matches the Box it was taken from; M = ∫ρJᵀJ by Monte-Carlo."""
    rng = np.random.default_rng(21)
    m, h = 1.7, np.array([0.1, 0.2, 0.05])
    R = random_rotation(rng)
    box_sigma = R @ (m * np.diag(h**2) / 3.0) @ R.T  # a rotated box about its centre
    inertia = np.trace(box_sigma) * np.eye(3) - box_sigma
    com = np.array([0.03, -0.02, 0.01])
    mm = ag.Inertia(m, com=tuple(com), inertia=tuple(map(tuple, inertia))).moments()
    sigma = mm.second_moment - m * np.outer(com, com)
    np.testing.assert_allclose(np.trace(sigma) * np.eye(3) - sigma, inertia, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(sigma, box_sigma, rtol=1e-12, atol=1e-15)
    assert mm.mass == m
    np.testing.assert_allclose(mm.com, com)
    scaled = ag.Inertia(m, com=tuple(com), inertia=tuple(map(tuple, inertia))).moments(mass=2 * m)
    np.testing.assert_allclose(scaled.second_moment, 2 * mm.second_moment, rtol=1e-14)
    with pytest.raises(ValueError, match="triangle"):
        ag.Inertia(1.0, inertia=((1.0, 0, 0), (0, 1.0, 0), (0, 0, 3.0))).moments()
    # the mass matrix of that body, by Monte-Carlo over the rotated, shifted box
    x = rng.uniform(-h, h, size=(200_000, 3)) @ R.T + com
    J = np.zeros((len(x), 3, 12))
    J[:, :, :3] = np.eye(3)
    for k in range(3):
        J[:, k, 3 + 3 * k : 6 + 3 * k] = x
    M_mc = m * np.einsum("nki,nkj->ij", J, J) / len(x)
    M = affine.mass_matrix(mm.mass, mm.com, mm.second_moment)
    np.testing.assert_allclose(M, M_mc, rtol=1e-2, atol=1e-2 * np.abs(M).max())


def test_model_takes_the_moments_and_frames_of_the_scene(sims, scene, ref):
    """The compiled model's per-world mass moments and joint data are the scene's (what the Warp
    comparison assumes), in both precisions."""
    for sim in sims.values():
        m = sim.model
        for k, b in enumerate(scene.bodies):
            np.testing.assert_allclose(m.mass.numpy()[1, k], b.mass, rtol=1e-7)
            np.testing.assert_allclose(m.mc.numpy()[1, k], b.mass * b.moments.com, rtol=1e-6, atol=1e-12)
            np.testing.assert_allclose(m.S.numpy()[1, k], b.moments.second_moment, rtol=1e-6, atol=1e-12)
        for k, j in enumerate(ref.joints):
            np.testing.assert_allclose(m.K.numpy()[0, k], j["K"], rtol=1e-7)
            for name in ("ci", "cj", "ti", "tj", "ni", "nj", "bi", "bj"):
                arr = getattr(m, {"i": "{}_a", "j": "{}_b"}[name[1]].format(name[0])).numpy()[1, k]
                np.testing.assert_allclose(arr, j[name], rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("dtype, rtol", [("float64", 1e-10)])
def test_fused_step_assembles_the_same_system(sims, ref, dtype, rtol):
    """The fused Newton kernel (the default step path) assembles the same gradient and Hessian as
    the reference.  One iteration leaves g as assembled and H as its in-place Cholesky factor:
    the lower triangle holds L, so H = L Lᵀ.  float64 only: the fused kernel calls the same per-term
    evaluators as the staged kernels checked in float32 above, and compiling it takes ~15 s a dtype."""
    sim, s = sims[dtype], sims[dtype].solver
    rng = np.random.default_rng(40)
    case = make_case(ref, rng, **CASES["limits_active"])
    want = reference(ref, case)
    load(sim, case)
    s.g.zero_()
    s.H.zero_()
    saved = s.settings.max_iterations
    s.settings.max_iterations = 1
    try:
        s._fused_newton(sim.state)
    finally:
        s.settings.max_iterations = saved
    # (a one-iteration budget ends unconverged: the step is rejected, the system stays as assembled)
    assert set(sim.state.status.numpy().tolist()) <= {int(WorldStatus.OK), int(WorldStatus.UNCONVERGED)}
    sim.state.status.zero_()  # (the module's simulators are shared)
    assert (sim.state.iterations.numpy() == 1).all()
    g, Hraw = s.gradient().astype(np.float64), s.hessian(fused=True).astype(np.float64)
    for w in range(2):
        g_ref = sum(v[1] for v in want[w].values())
        H_ref = sum(v[2] for v in want[w].values())
        assert close(g[w], g_ref, rtol)
        L = np.tril(Hraw[w])
        assert close(L @ L.T, H_ref, rtol)


def test_warp_bdf2_uses_its_effective_step(scene):
    """integrator="bdf2": orthogonality and drives sit inside ĥ² (ĥ = 2h/3), PD drives damp towards
    x̂ = (4xⁿ − xⁿ⁻¹)/3 with gain d/ĥ; inertia, joints and limits are as under implicit Euler."""
    sim = ag.Simulator(scene, num_worlds=2, dt=0.01, dtype="float64", integrator="bdf2")
    ref = SceneRef(scene, 0.01, h_eff=0.02 / 3)
    case = make_case(ref, np.random.default_rng(50), **CASES["limits_active"])
    case["x_hist"] = case["unwrapped"] - np.array([0.03, -0.02, 0.0, 0.01])
    want = compare(sim, ref, case, 1e-10)
    euler = SceneRef(scene, 0.01).solve_terms(case["q"][0], case["q_prev"][0], case["q_tilde"][0],
                                              case["unwrapped"][0], case["control"][0], case["limits"][0])  # fmt: skip
    for name in ("orthogonality", "drive"):  # the check tells the two integrators apart
        assert abs(want[0][name][0] - euler[name][0]) > 1e-3 * abs(euler[name][0])


@pytest.mark.parametrize("rail_first", [True, False])
def test_prismatic_joint_to_a_fixed_body(rail_first):
    """A slider between a fixed rail and a free block (rail as body i or as body j): the Warp
    evaluator leaves the fixed body's blocks out, and the free body's gradient and Hessian block
    match the float64 reference's, staged and fused."""
    scene = ag.Scene(gravity=(0.0, 0.0, 0.0))
    rail = scene.add_body(ag.Box(half_extents=(1.0, 0.02, 0.02)), mass=1.0, fixed=True)
    block = scene.add_body(ag.Box(half_extents=(0.1, 0.1, 0.1)), mass=0.7, position=(0.2, 0.0, 0.0))
    pair = (rail, block) if rail_first else (block, rail)
    scene.add_prismatic_joint(*pair, anchor=(0.0, 0.0, 0.0), axis=(1.0, 0.2, 0.0), strength_ratio=50.0)
    sim = ag.Simulator(scene, num_worlds=2, dtype="float64", plan=ag.ExecutionPlan(fused=False))
    m, s = sim.model, sim.solver
    rng = np.random.default_rng(41)
    q = sim.body_q().astype(np.float64)
    q[:, block] += rng.normal(scale=0.05, size=(2, 12))
    sim.state.q.assign(q)
    (part,) = [c for c in s.parts if c.name == "prismatic_joint"]
    E, g, H = assemble(sim, [part])
    fr = {k: getattr(m, k).numpy()[0, 0] for k in ("c_a", "c_b", "t_a", "t_b", "n_a", "n_b", "b_a", "b_b")}
    K = m.K.numpy()[0, 0]
    o = 12 if rail_first else 0  # the free body's rows in the stacked pair
    for w in range(2):
        qa, qb = (q[w, k] for k in pair)
        e, g_ref, _, H_ref = prismatic_joint.prismatic_joint_np(np.concatenate([qa, qb]), fr["c_a"], fr["c_b"], fr["t_a"],
                                                                fr["t_b"], fr["n_a"], fr["n_b"], fr["b_a"], fr["b_b"], K)
        assert E[w, s.cols["prismatic_joint"]] == pytest.approx(e, rel=1e-12)
        np.testing.assert_allclose(g[w], g_ref[o:o + 12], rtol=1e-10, atol=1e-12 * np.abs(g_ref).max())
        np.testing.assert_allclose(H[w], H_ref[o:o + 12, o:o + 12], rtol=1e-10, atol=1e-12 * np.abs(H_ref).max())
    # the fused step's assembly of the whole potential agrees with the staged one
    E_all, g_all, H_all = assemble(sim)
    Ef, gf, Hf = s.fused_system(sim.state)
    np.testing.assert_allclose(Ef, E_all.sum(axis=1), rtol=1e-12)
    np.testing.assert_allclose(gf, g_all, rtol=1e-11, atol=1e-12 * np.abs(g_all).max())
    np.testing.assert_allclose(Hf, np.tril(H_all), rtol=1e-11, atol=1e-12 * np.abs(H_all).max())


@pytest.mark.parametrize("parent_first", [True, False])
def test_fused_rank_one_terms_between_free_bodies(parent_first):
    """Limits and PD drives between two free bodies, with the joint's body i before or after body j
    in the unknowns: the fused step adds their E''∇x∇xᵀ blocks entry by entry (fused.put_outer, each
    ordering of the pair its own branch) and must match the staged kernels' assembly."""
    def build(limit):
        scene = ag.Scene(gravity=(0.0, 0.0, -9.81))
        base = scene.add_body(ag.Box(half_extents=(0.1, 0.1, 0.1)), fixed=True)
        a = scene.add_body(ag.Box(half_extents=(0.02, 0.02, 0.25)), mass=1.0, position=(0.0, 0.0, -0.25))
        b = scene.add_body(ag.Box(half_extents=(0.02, 0.02, 0.25)), mass=0.5, position=(0.0, 0.0, -0.75))
        scene.add_revolute_joint(base, a, anchor=(0.0, 0.0, 0.0), axis=(0, 1, 0))
        pair = (a, b) if parent_first else (b, a)
        hinge = scene.add_revolute_joint(*pair, anchor=(0.0, 0.0, -0.5), axis=(0, 1, 0))
        if limit:
            scene.add_revolute_limit(hinge, lower=-0.2, upper=0.2, strength=1e3)
        scene.add_drive(hinge, "position", stiffness=40.0, damping=1.0, max_effort=100.0)
        return scene

    # poses past the limit's bound (the limit acts in both worlds, the drive is linear), placed by
    # a twin without the limit: set_joint_state refuses a joint outside its limit
    twin = ag.Simulator(build(limit=False), num_worlds=2, dtype="float64", plan=ag.ExecutionPlan(fused=False))
    twin.set_joint_state([[0.3, 0.5], [-0.2, -0.45]])
    sim = ag.Simulator(build(limit=True), num_worlds=2, dtype="float64", plan=ag.ExecutionPlan(fused=False))
    sim.set_body_states(twin.body_positions(), twin.body_rotations())
    sim.set_controls([[0.1], [-0.1]])
    E, g, H = assemble(sim)
    assert E[:, sim.solver.cols["revolute_limit"]].min() > 0
    Ef, gf, Hf = sim.solver.fused_system(sim.state)
    np.testing.assert_allclose(Ef, E.sum(axis=1), rtol=1e-12)
    np.testing.assert_allclose(gf, g, rtol=1e-11, atol=1e-12 * np.abs(g).max())
    np.testing.assert_allclose(Hf, np.tril(H), rtol=1e-11, atol=1e-12 * np.abs(H).max())
