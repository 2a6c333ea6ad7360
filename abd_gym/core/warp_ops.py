"""Warp building blocks shared by the constitutions, made once per scalar type.

Every kernel is built by a cached factory for float32 or float64 (MuJoCo Warp's pattern), so the
same source serves both precisions.  Per-world arrays: ``q`` (W, bodies) of vec12, energy terms
``E`` (W, terms); the gradient ``g`` (n, W) and Hessian ``H`` (n, n, W) are stored world-minor so
that the per-world solve (one thread per world) reads them coalesced.  ``dof[b]`` is body b's
first unknown or -1 for a fixed body, whose rows are simply skipped.
"""

import functools
from types import SimpleNamespace

import warp as wp

# no adjoints: the solver differentiates by hand, and skipping them halves compile time
wp.config.enable_backward = False

# what an evaluator computes, its ``derivs`` argument: the energy; also the gradient; also the Hessian
ENERGY, GRADIENT, HESSIAN = 0, 1, 2


@functools.lru_cache(maxsize=None)
def ops(dtype):
    vec3 = wp.types.vector(3, dtype)
    vec12 = wp.types.vector(12, dtype)
    mat33 = wp.types.matrix((3, 3), dtype)
    mat12 = wp.types.matrix((12, 12), dtype)
    vec4 = wp.types.vector(4, dtype)
    mat44 = wp.types.matrix((4, 4), dtype)

    @wp.func
    def point(q: vec12, x: vec3):
        """p + A x."""
        return vec3(
            q[0] + q[3] * x[0] + q[4] * x[1] + q[5] * x[2],
            q[1] + q[6] * x[0] + q[7] * x[1] + q[8] * x[2],
            q[2] + q[9] * x[0] + q[10] * x[1] + q[11] * x[2],
        )

    @wp.func
    def direction(q: vec12, v: vec3):
        """A v."""
        return vec3(
            q[3] * v[0] + q[4] * v[1] + q[5] * v[2],
            q[6] * v[0] + q[7] * v[1] + q[8] * v[2],
            q[9] * v[0] + q[10] * v[1] + q[11] * v[2],
        )

    @wp.func
    def JT(x: vec3, u: vec3, tr: dtype):
        """J(x)ᵀ u (tr = 1) or J̊(x)ᵀ u (tr = 0): the gradient of u·(p·tr + A x)."""
        return vec12(
            tr * u[0], tr * u[1], tr * u[2],
            u[0] * x[0], u[0] * x[1], u[0] * x[2],
            u[1] * x[0], u[1] * x[1], u[1] * x[2],
            u[2] * x[0], u[2] * x[1], u[2] * x[2],
        )  # fmt: skip

    @wp.func
    def kron_index(m: int, c: int):
        """The q index of component m (x, y, z) times factor c of u = (1, x̄): p_m, or row m of A."""
        return wp.where(c == 0, m, 3 + 3 * m + c - 1)

    @wp.func
    def kron3(U: mat44):
        """U ⊗ I₃ in the q = (p, a1, a2, a3) layout: J(x) = [I₃, x̄ᵀ ⊗ I₃] rows, so Σ_m J(x)ᵀe_m e_mᵀJ(y)
        = (u_x u_yᵀ) ⊗ I₃ with u = (1, x̄): entry (a, b) is U[c(a), c(b)] where a and b act on the
        same component m, else 0 (48 of 144 entries)."""
        M = mat12()
        for m in range(3):
            for c in range(4):
                for d in range(4):
                    M[kron_index(m, c), kron_index(m, d)] = U[c, d]
        return M

    @wp.func
    def outer_blocks(gi: vec12, gj: vec12, c: dtype, derivs: int):
        """c·(gᵢgᵢᵀ, gᵢgⱼᵀ, gⱼgⱼᵀ): the blocks of c ∇x∇xᵀ for a scalar coordinate x of a body pair
        with gradient (gᵢ, gⱼ) (a limit's or a drive's Hessian), built for HESSIAN and c ≠ 0 only."""
        hii = mat12()
        hij = mat12()
        hjj = mat12()
        if derivs == HESSIAN and c != dtype(0.0):
            hii = c * wp.outer(gi, gi)
            hij = c * wp.outer(gi, gj)
            hjj = c * wp.outer(gj, gj)
        return hii, hij, hjj

    @wp.func
    def add_energy(E: wp.array2d(dtype=dtype), w: int, col: int, e: dtype):
        wp.atomic_add(E, w, col, e)

    @wp.func
    def add_grad(g: wp.array2d(dtype=dtype), w: int, o: int, v: vec12):
        if o >= 0:
            for r in range(12):
                wp.atomic_add(g, o + r, w, v[r])

    @wp.func
    def add_block(H: wp.array3d(dtype=dtype), w: int, oa: int, ob: int, m: mat12):
        """H[oa:, ob:] += m and, off the diagonal, the transpose into H[ob:, oa:]."""
        if oa >= 0 and ob >= 0:
            for r in range(12):
                for c in range(12):
                    wp.atomic_add(H, oa + r, ob + c, w, m[r, c])
                    if oa != ob:
                        wp.atomic_add(H, ob + c, oa + r, w, m[r, c])

    @wp.func
    def scatter_pair(
        g: wp.array2d(dtype=dtype), H: wp.array3d(dtype=dtype), w: int, oi: int, oj: int,
        gi: vec12, gj: vec12, hii: mat12, hij: mat12, hjj: mat12,
    ):  # fmt: skip
        add_grad(g, w, oi, gi)
        add_grad(g, w, oj, gj)
        add_block(H, w, oi, oi, hii)
        add_block(H, w, oi, oj, hij)
        add_block(H, w, oj, oj, hjj)

    @wp.func
    def skew_row(t: vec3, m: int):
        """Row m of [t]×, the matrix with [t]× v = t × v."""
        r = vec3(dtype(0.0), -t[2], t[1])
        if m == 1:
            r = vec3(t[2], dtype(0.0), -t[0])
        elif m == 2:
            r = vec3(-t[1], t[0], dtype(0.0))
        return r

    @wp.func
    def unit(m: int):
        r = vec3(dtype(0.0), dtype(0.0), dtype(0.0))
        r[m] = dtype(1.0)
        return r

    return SimpleNamespace(**{k: v for k, v in locals().items() if k != "dtype"}, dtype=dtype)


@functools.lru_cache(maxsize=None)
def body_dofs(axis: int):
    """A free body's unknowns in a world's system: all 12 of q = (p, a1, a2, a3) (``axis`` −1), or
    the 6 in the plane ⟂ e_axis of a planar scene (sim/planar.py: p_i and A_ij for i, j ≠ axis).
    ``D`` unknowns a body; ``slot(r)``: the unknown of q's entry r within its body's (−1: held);
    ``sel(u)``: the entry of q that unknown u moves (u < D).  With 12 both are the identity."""
    a = int(axis)
    if a < 0:

        @wp.func
        def slot(r: int):
            return r

        @wp.func
        def sel(u: int):
            return u

        return SimpleNamespace(D=12, slot=slot, sel=sel, axis=-1)

    @wp.func
    def slot(r: int):
        # p_i (r < 3) or A_kj (r = 3 + 3k + j); i, k, j = a are held, the others keep their order
        s = int(-1)
        if r < 3:
            if r != a:
                s = r - wp.where(r > a, 1, 0)
        else:
            k = (r - 3) // 3
            j = (r - 3) - 3 * k
            if k != a and j != a:
                s = 2 + 2 * (k - wp.where(k > a, 1, 0)) + j - wp.where(j > a, 1, 0)
        return s

    @wp.func
    def sel(u: int):
        r = u + wp.where(u >= a, 1, 0)
        if u >= 2:
            k = (u - 2) // 2
            j = (u - 2) - 2 * k
            r = 3 + 3 * (k + wp.where(k >= a, 1, 0)) + j + wp.where(j >= a, 1, 0)
        return r

    return SimpleNamespace(D=6, slot=slot, sel=sel, axis=a)
