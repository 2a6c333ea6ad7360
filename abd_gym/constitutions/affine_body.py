"""Affine body (libuipc UID 1): inertia and the orthogonality potential.

Inertia of the incremental potential: ``½ (q − q̃)ᵀ M (q − q̃)`` with ``M = ∫ρ J(x)ᵀJ(x) dV``
built from the mass m [kg], first moment m·c [kg·m] and second moment S [kg·m²].

Orthogonality: ``V(A) = κ·vol·‖A Aᵀ − I‖²_F`` [J] (κ [Pa]), inside h² in the solve.  With
``R = A Aᵀ − I`` and rows a_k: ``∂V/∂a_k = 4κv Σ_l R_kl a_l`` and the exact Hessian block
``4κv (δ_kl AᵀA + a_l a_kᵀ + R_kl I)``.  The first two terms sum to a PSD form (½‖X + Xᵀ‖²,
X = A dAᵀ); the last is R ⊗ I, indefinite where A is compressed along some direction.  The solver
uses R⁺, R's positive part (R itself where R ⪰ 0, the Hessian then exact; else from R's
eigenvalues in closed form, ``psd_part``), so the Hessian stays PSD and is exact in R's positive
directions.  R is tiny (|R| ~ 1e-5) but 4κv·h²·R is not: along a thin link's slender directions it
exceeds the inertia's second moments, so dropping the whole R term when one eigenvalue is
negative leaves Newton converging only linearly (its rate: results/solver_notes.md).
"""

import functools
from types import SimpleNamespace

import numpy as np
import warp as wp

from ..core import affine
from ..core.warp_ops import HESSIAN, ops
from .protocol import BODY, Constitution

UID = 1
NAME = "affine_body"
TERMS = ("inertia", "orthogonality")


# ----------------------------------------------------------------------------- float64 NumPy
def orthogonality_np(q, kv):
    """V, gradient, exact Hessian and the PSD Hessian the solver uses (12-vector q)."""
    A = q[3:].reshape(3, 3)
    R = A @ A.T - np.eye(3)
    V = kv * np.sum(R * R)
    g = np.zeros(12)
    g[3:] = (4.0 * kv * R @ A).reshape(-1)
    ata = A.T @ A
    Rp = psd_part_np(R)
    H, Hp = np.zeros((12, 12)), np.zeros((12, 12))
    for k in range(3):
        for l in range(3):
            blk = 4.0 * kv * ((k == l) * ata + np.outer(A[l], A[k]))
            H[3 + 3 * k : 6 + 3 * k, 3 + 3 * l : 6 + 3 * l] = blk + 4.0 * kv * R[k, l] * np.eye(3)
            Hp[3 + 3 * k : 6 + 3 * k, 3 + 3 * l : 6 + 3 * l] = blk + 4.0 * kv * Rp[k, l] * np.eye(3)
    return V, g, H, Hp


def psd_part_np(R):
    """R⁺: the symmetric R with its negative eigenvalues set to 0."""
    if is_psd3_np(R):
        return R
    lam, V = np.linalg.eigh(0.5 * (R + R.T))
    return (V * np.maximum(lam, 0.0)) @ V.T


def is_psd3_np(R):
    """Symmetric 3 × 3 R ⪰ 0: every principal minor is non-negative."""
    minors = (R[0, 0], R[1, 1], R[2, 2], R[0, 0] * R[1, 1] - R[0, 1] ** 2, R[0, 0] * R[2, 2] - R[0, 2] ** 2,
              R[1, 1] * R[2, 2] - R[1, 2] ** 2, np.linalg.det(R))  # fmt: skip
    return all(m >= 0.0 for m in minors)


def inertia_np(q, q_tilde, mass, com, second_moment):
    M = affine.mass_matrix(mass, com, second_moment)
    d = q - q_tilde
    return 0.5 * d @ M @ d, M @ d, M


def retract_np(q, d, alpha, m, mc, rigid=False):
    """Float64 reference of the Warp ``retract``: q + αd with A's part bent along the rotation
    Cay(αK), K = skew(ΔA Aᵀ), about the centre of mass mc/m."""
    A, D = q[3:].reshape(3, 3), d[3:].reshape(3, 3)
    M = D @ A.T
    k = 0.5 * np.array([M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1]])
    if not rigid and k @ k > 0.01:
        return q + alpha * d
    k = alpha * k
    X = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    C = (0.5 * X @ X - 0.25 * (k @ k) * X) / (1.0 + 0.25 * (k @ k))
    if rigid:
        C = C - alpha * 0.5 * (M + M.T)
    dA = C @ A
    out = q + alpha * d
    out[:3] -= dA @ (np.asarray(mc) / m)
    out[3:] += dA.ravel()
    return out


# ----------------------------------------------------------------------------- Warp
@functools.lru_cache(maxsize=None)
def psd_funcs(dtype):
    """R⁺ of a symmetric 3 × 3 R in closed form (``psd_part``), with its PSD test and null vector."""
    mat33 = ops(dtype).mat33

    @wp.func
    def is_psd3(R: mat33):
        """Symmetric 3 × 3 R ⪰ 0: every principal minor is non-negative."""
        z = dtype(0.0)
        return (R[0, 0] >= z and R[1, 1] >= z and R[2, 2] >= z and R[0, 0] * R[1, 1] - R[0, 1] * R[0, 1] >= z
                and R[0, 0] * R[2, 2] - R[0, 2] * R[0, 2] >= z and R[1, 1] * R[2, 2] - R[1, 2] * R[1, 2] >= z
                and wp.determinant(R) >= z)  # fmt: skip

    @wp.func
    def null_vector(M: mat33):
        """A unit vector v with M v ≈ 0 for a symmetric M of rank 2: the largest cross product of
        two of its rows (each is normal to both, so along the null space)."""
        c0 = wp.cross(M[0], M[1])
        c1 = wp.cross(M[0], M[2])
        c2 = wp.cross(M[1], M[2])
        n0 = wp.dot(c0, c0)
        n1 = wp.dot(c1, c1)
        n2 = wp.dot(c2, c2)
        v = c0
        n = n0
        if n1 > n:
            v = c1
            n = n1
        if n2 > n:
            v = c2
            n = n2
        if n > dtype(0.0):
            v = v / wp.sqrt(n)
        return v

    @wp.func
    def psd_part(R: mat33):
        """R⁺: symmetric R with its negative eigenvalues set to 0.  Eigenvalues in closed form
        (the trigonometric solution of the characteristic cubic), then R less its one negative
        eigen-part, or the one positive eigen-part alone; the eigenvector from cross products of
        rows of R − λI (a few hundred operations, without wp.eig3's iterations)."""
        z = dtype(0.0)
        if is_psd3(R):
            return R
        I = wp.identity(3, dtype)
        q = (R[0, 0] + R[1, 1] + R[2, 2]) / dtype(3.0)
        d0 = R[0, 0] - q
        d1 = R[1, 1] - q
        d2 = R[2, 2] - q
        p2 = d0 * d0 + d1 * d1 + d2 * d2 + dtype(2.0) * (R[0, 1] * R[0, 1] + R[0, 2] * R[0, 2] + R[1, 2] * R[1, 2])
        if not (p2 > z):
            return mat33()  # R = qI, q < 0
        p = wp.sqrt(p2 / dtype(6.0))
        # (a matrix over a scalar divides every entry: one reciprocal instead, fewer instructions in
        # the fused step's code)
        r = wp.clamp(wp.determinant((R - q * I) * (dtype(1.0) / p)) / dtype(2.0), dtype(-1.0), dtype(1.0))
        phi = wp.acos(r) / dtype(3.0)
        l1 = q + dtype(2.0) * p * wp.cos(phi)  # the largest
        l3 = q + dtype(2.0) * p * wp.cos(phi + dtype(2.0943951023931953))  # the smallest (+2π/3)
        l2 = dtype(3.0) * q - l1 - l3
        if not (l1 > z):
            return mat33()
        if l2 >= z:  # one negative eigenvalue: remove its part
            v = null_vector(R - l3 * I)
            return R - l3 * wp.outer(v, v)
        v = null_vector(R - l1 * I)  # one positive eigenvalue: keep its part
        return l1 * wp.outer(v, v)

    return SimpleNamespace(is_psd3=is_psd3, null_vector=null_vector, psd_part=psd_part)


@functools.lru_cache(maxsize=None)
def body_funcs(dtype):
    """One body's inertia and orthogonality: energies and gradient (``body_grad``), with the Hessian
    whole (``body_eval``) or by its parts for the fused step (``hessian_parts``, ``a_block``); ``row``
    reads row k of q's A."""
    o = ops(dtype)
    vec3, vec12, mat33, mat12 = o.vec3, o.vec12, o.mat33, o.mat12
    half, four = dtype(0.5), dtype(4.0)
    psd_part = psd_funcs(dtype).psd_part

    @wp.func
    def row(q: vec12, k: int):
        return vec3(q[3 + 3 * k], q[4 + 3 * k], q[5 + 3 * k])

    @wp.func
    def hessian_parts(qb: vec12, exact: int):
        """(R⁺, AᵀA) of the orthogonality Hessian: R⁺ = R = AAᵀ − I where R ⪰ 0, else R with its
        negative eigenvalues set to 0 (the Hessian's PSD part); R itself where ``exact`` (the exact
        Hessian, indefinite where A is compressed)."""
        A = wp.matrix_from_rows(row(qb, 0), row(qb, 1), row(qb, 2))
        R = A * wp.transpose(A) - wp.identity(3, dtype)
        if exact == 0:
            R = psd_part(R)
        return R, wp.transpose(A) * A

    @wp.func
    def a_block(qb: vec12, kk: int, ll: int, Rp: mat33, ata: mat33, ks: dtype, s: mat33):
        """Block (k, l) of the Hessian's A rows: 4κ(a_l a_kᵀ + R⁺_kl I + δ_kl AᵀA) + δ_kl S
        (orthogonality, then the mass matrix's second moments S)."""
        blk = wp.outer(row(qb, ll), row(qb, kk)) + Rp[kk, ll] * wp.identity(3, dtype)
        if kk == ll:
            blk = blk + ata
        blk = (four * ks) * blk
        if kk == ll:
            blk = blk + s
        return blk

    @wp.func
    def body_grad(qb: vec12, qt: vec12, m: dtype, c: vec3, s: mat33, ks: dtype, derivs: int):
        """Inertia and (scaled) orthogonality of one body: (energies, gradient), the gradient for
        derivs != 0 (the fused step adds the Hessian from its parts, without a 12 × 12 matrix)."""
        d = qb - qt
        # M d: translation m dp + A_d c; row k of A: c dp_k + S da_k
        dp = vec3(d[0], d[1], d[2])
        f = vec12()
        f[0] = m * dp[0] + wp.dot(row(d, 0), c)
        f[1] = m * dp[1] + wp.dot(row(d, 1), c)
        f[2] = m * dp[2] + wp.dot(row(d, 2), c)
        for r in range(3):
            fr = c * dp[r] + s * row(d, r)
            f[3 + 3 * r] = fr[0]
            f[4 + 3 * r] = fr[1]
            f[5 + 3 * r] = fr[2]
        e_inertia = half * wp.dot(d, f)
        # orthogonality: R = A Aᵀ − I
        A = wp.matrix_from_rows(row(qb, 0), row(qb, 1), row(qb, 2))
        R = A * wp.transpose(A) - wp.identity(3, dtype)
        e_ortho = ks * wp.ddot(R, R)
        if derivs == 0:
            return e_inertia, e_ortho, f
        G = (four * ks) * (R * A)
        for r in range(3):
            f[3 + 3 * r] += G[r, 0]
            f[4 + 3 * r] += G[r, 1]
            f[5 + 3 * r] += G[r, 2]
        return e_inertia, e_ortho, f

    @wp.func
    def body_eval(qb: vec12, qt: vec12, m: dtype, c: vec3, s: mat33, ks: dtype, derivs: int):
        """Inertia and (scaled) orthogonality of one body: energies, gradient, PSD Hessian."""
        e_inertia, e_ortho, f = body_grad(qb, qt, m, c, s, ks, derivs)
        h = mat12()
        if derivs != HESSIAN:
            return e_inertia, e_ortho, f, h
        # Hessian: mass matrix plus the PSD orthogonality blocks
        Rp, ata = hessian_parts(qb, 0)
        for r in range(3):
            h[r, r] = m
            for a in range(3):
                h[r, 3 + 3 * r + a] = c[a]
                h[3 + 3 * r + a, r] = c[a]
        for kk in range(3):
            for ll in range(3):
                blk = a_block(qb, kk, ll, Rp, ata, ks, s)
                for a in range(3):
                    for bb in range(3):
                        h[3 + 3 * kk + a, 3 + 3 * ll + bb] = blk[a, bb]
        return e_inertia, e_ortho, f, h

    return SimpleNamespace(row=row, hessian_parts=hessian_parts, a_block=a_block, body_grad=body_grad,
                           body_eval=body_eval)


@functools.lru_cache(maxsize=None)
def retract_func(dtype):
    """``retract``: a body's trial point bent along the rotation its step makes."""
    o = ops(dtype)
    vec3, vec12 = o.vec3, o.vec12
    half = dtype(0.5)
    row = body_funcs(dtype).row

    @wp.func
    def retract(qb: vec12, d: vec12, alpha: dtype, m: dtype, mc: vec3, rigid: int):
        """qb + α d, bent along the rotation the step makes: A + αΔA + (Cay(αK) − I − αK) A with
        K = skew(ΔA Aᵀ) (Cayley's rotation, exactly orthogonal), p shifted so that the centre of
        mass moves by α d alone.  The path leaves q along d (same first derivative, so Armijo's test
        is unchanged) and differs from the straight one at O(α²): a straight step in A rotates by
        turning A off the rotations by ~½(αθ)², which the stiff orthogonality energy (κ·vol·h²)
        then pushes back across several Newton iterations.  ``rigid``: A turns by Cay(αK) alone,
        the symmetric part S = sym(ΔA Aᵀ) dropped (A' = Cay(αK) A): for an extrapolated motion,
        whose ΔA already holds the rotation's own curvature (½h²W²A of a quadratic extrapolation),
        which the Cayley term would count twice.  Without ``rigid``, a step whose full rotation
        |K| exceeds 0.1 rad is taken along the line (the same path for every α of the step)."""
        A = wp.matrix_from_rows(row(qb, 0), row(qb, 1), row(qb, 2))
        D = wp.matrix_from_rows(row(d, 0), row(d, 1), row(d, 2))
        M = D * wp.transpose(A)
        k1 = half * vec3(M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1])
        if rigid == 0 and wp.dot(k1, k1) > dtype(0.01):
            # a Newton step that turns A by over 0.1 rad stays straight: along so bent a path the
            # trial points leave Newton's model, and the solve converges only linearly
            return qb + alpha * d
        k = alpha * k1
        X = wp.skew(k)
        kk = dtype(0.25) * wp.dot(k, k)
        # Cay(X) − I − X = (X + X²/2)/(1 + |k|²/4) − X, written without the cancellation
        C = (half * (X * X) - kk * X) * (dtype(1.0) / (dtype(1.0) + kk))  # (one division, not nine)
        if rigid != 0:
            C = C - alpha * half * (M + wp.transpose(M))
        dA = C * A
        out = qb + alpha * d
        dp = dA * (mc * (dtype(1.0) / m))
        for r in range(3):
            out[r] = out[r] - dp[r]
            for l in range(3):
                out[3 + 3 * r + l] = out[3 + 3 * r + l] + dA[r, l]
        return out

    return retract


@functools.lru_cache(maxsize=None)
def kernels(dtype):
    """The body terms' kernels (``body_terms``: energies, gradient and Hessian into the staged
    step's arrays; ``body_report``: kinetic and gravity energies) and, by name, the functions the
    fused step takes from psd_funcs, body_funcs and retract_func."""
    o = ops(dtype)
    vec3, vec12, mat33 = o.vec3, o.vec12, o.mat33
    add_energy, add_grad, add_block = o.add_energy, o.add_grad, o.add_block
    half = dtype(0.5)
    body = body_funcs(dtype)
    row, body_eval = body.row, body.body_eval

    @wp.kernel(module="unique")
    def body_terms(
        q: wp.array2d(dtype=vec12), q_tilde: wp.array2d(dtype=vec12),
        free: wp.array(dtype=wp.int32), dof: wp.array(dtype=wp.int32),
        mass: wp.array2d(dtype=dtype), mc: wp.array2d(dtype=vec3), S: wp.array2d(dtype=mat33),
        kv: wp.array2d(dtype=dtype), h_step: wp.array(dtype=dtype), physical: int, active: wp.array(dtype=wp.int32),
        derivs: int, col: int, col_ortho: int,
        E: wp.array2d(dtype=dtype), g: wp.array2d(dtype=dtype), H: wp.array3d(dtype=dtype),
    ):  # fmt: skip
        w, k = wp.tid()
        if active[w] == 0:
            return
        b = free[k]
        o = dof[b]
        ortho_scale = dtype(1.0)  # the physical energy [J], or inside the potential's ĥ²
        if physical == 0:
            ortho_scale = h_step[w] * h_step[w]
        e_in, e_or, f, h = body_eval(q[w, b], q_tilde[w, b], mass[w, b], mc[w, b], S[w, b], kv[w, b] * ortho_scale, derivs)
        add_energy(E, w, col, e_in)
        add_energy(E, w, col_ortho, e_or)
        if derivs != 0:
            add_grad(g, w, o, f)
            add_block(H, w, o, o, h)

    @wp.func
    def report_terms(v: vec12, qb: vec12, m: dtype, c: vec3, s: mat33, gravity: vec3):
        """(kinetic ½ q̇ᵀMq̇, gravity −g·(m p + A m c)) of one body [J]."""
        vp = vec3(v[0], v[1], v[2])
        ke = m * wp.dot(vp, vp)
        for r in range(3):
            vr = row(v, r)
            ke += dtype(2.0) * vp[r] * wp.dot(vr, c) + wp.dot(vr, s * vr)
        com = m * vec3(qb[0], qb[1], qb[2]) + vec3(wp.dot(row(qb, 0), c), wp.dot(row(qb, 1), c), wp.dot(row(qb, 2), c))
        return half * ke, -wp.dot(gravity, com)

    @wp.kernel(module="unique")
    def body_report(
        q: wp.array2d(dtype=vec12), qd: wp.array2d(dtype=vec12), free: wp.array(dtype=wp.int32),
        mass: wp.array2d(dtype=dtype), mc: wp.array2d(dtype=vec3), S: wp.array2d(dtype=mat33),
        gravity: vec3, E: wp.array2d(dtype=dtype), col_kinetic: int, col_gravity: int,
    ):  # fmt: skip
        """Physical kinetic ½ q̇ᵀMq̇ and gravity −g·(m p + A m c) energies [J] (report_terms)."""
        w, k = wp.tid()
        b = free[k]
        ke, ge = report_terms(qd[w, b], q[w, b], mass[w, b], mc[w, b], S[w, b], gravity)
        wp.atomic_add(E, w, col_kinetic, ke)
        wp.atomic_add(E, w, col_gravity, ge)

    return SimpleNamespace(psd_part=psd_funcs(dtype).psd_part, body_terms=body_terms, body_report=body_report,
                           report_terms=report_terms,
                           body_eval=body_eval, body_grad=body.body_grad, retract=retract_func(dtype),
                           hessian_parts=body.hessian_parts, a_block=body.a_block)


# ----------------------------------------------------------------------------- wiring
def terms(model, physical=False):
    return ("kinetic", "gravity", "orthogonality") if physical else TERMS


def launch(model, state, ctx, q, E, g, H, active, derivs, cols, physical=False):
    kk = kernels(model.dtype)
    body_terms, body_report = kk.body_terms, kk.body_report
    dim = (model.num_worlds, model.num_free)
    common = [model.free, model.mass, model.mc, model.S]
    if physical:
        wp.launch(body_report, dim=dim, inputs=[q, state.qd, *common, model.gravity, E,
                                                cols["kinetic"], cols["gravity"]], device=model.device)  # fmt: skip
        col_inertia = cols["scratch"]
    else:
        col_inertia = cols["inertia"]
    wp.launch(body_terms, dim=dim, inputs=[q, ctx.q_tilde, model.free, model.dof, model.mass, model.mc, model.S,
                                           model.kv, ctx.h_step, int(physical), active, derivs, col_inertia,
                                           cols["orthogonality"], E, g, H], device=model.device)  # fmt: skip


# work: a pass of the lanes over the bodies' rows (Solver.lane_work)
CONSTITUTION = Constitution(NAME, UID, BODY, (inertia_np, orthogonality_np), terms, launch, work=14.0)
