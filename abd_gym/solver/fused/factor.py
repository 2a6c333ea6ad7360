"""The lane-split solve of H Δq = −g by H = L D Lᵀ (H packed, lane l owning the rows i ≡ l
(mod lanes)): right-looking, column j's pivot D_j = H[j, j] and each row's update
H[i, k] −= H[i, j] H[k, j] / D_j (j < k ≤ i); then forward L y = −g and backward
Δq = D⁻¹ L⁻ᵀ y.  The factor is left in H (D_j L_ij below the diagonal, 1/D_j on it) so that a later
iteration may reuse it.  ``ldl_lanes`` and ``solve_lanes``: one barrier a column, H in shared (or
global) memory; ``warp_ldl_solve``: the same arithmetic in the same order, each lane's rows in
registers and the columns passed by warp shuffles (CUDA, up to 3 rows a lane)."""
import functools

import warp as wp
from types import SimpleNamespace

from .layout import KernelSpec, indexing


def _prelude(ctype: str, n: int, lanes: int) -> str:
    """The declarations the pieces read: the scalar type, the compile-time sizes (R rows a lane),
    the shuffle mask of the world's segment of the warp, and the lane's registers."""
    L = int(lanes)
    R = -(-int(n) // L)
    return f"""typedef {ctype} T;
const int N = {int(n)};
const int L = {L};
const int R = {R};
const unsigned MASK = {"0xffffffffu" if L == 32 else f"((1u << {L}) - 1u) << ((threadIdx.x & 31u) & ~{L - 1}u)"};
T* Hs = H.data;
const int l = lane;
T h[R][N];
T dinv[R];
"""


# regs_ldl_solve's CUDA body (warp_ldl_solve) in the order it runs, after _prelude's declarations
# (T, the sizes N, L, R, the segment's MASK, H's data Hs, the lane l, its rows h and their 1/D in
# dinv); each piece is plain CUDA, the sizes being compile-time constants.

# the lane's rows of H into registers, and their 1/D where H holds a factor to reuse
_LOAD_ROWS = """\
#pragma unroll
for (int r = 0; r < R; ++r) {
    const int i = l + r * L;
    const int ri = (i * (i + 1)) >> 1;
#pragma unroll
    for (int k = 0; k < N; ++k) {
        h[r][k] = T(0);
        if (i < N && k <= i) h[r][k] = Hs[ri + k];
    }
    dinv[r] = i < N ? Hs[ri + i] : T(0);  // 1/D_i, where a reused factor holds it
}
"""

# with ``factor``: column j's pivot and multipliers shuffled from its lanes, each lane's rows
# updated; ok 0 at a pivot not positive and finite; the factor written back to H
_FACTOR = """\
int ok = 1;
if (factor) {
#pragma unroll
    for (int r = 0; r < R; ++r) dinv[r] = T(0);
#pragma unroll
    for (int j = 0; j < N; ++j) {
        const T dj = __shfl_sync(MASK, h[j / L][j], j % L, L);
        if (!(dj > T(0)) || !isfinite(dj)) ok = 0;
        const T inv = T(1) / dj;
        T cj[R];
#pragma unroll
        for (int r = 0; r < R; ++r) {
            if (l + r * L == j) dinv[r] = inv;
            cj[r] = h[r][j] * inv;
        }
#pragma unroll
        for (int k = j + 1; k < N; ++k) {
            const T hk = __shfl_sync(MASK, h[k / L][j], k % L, L);
#pragma unroll
            for (int r = 0; r < R; ++r) {
                if (l + r * L >= k) h[r][k] -= cj[r] * hk;
            }
        }
    }
    if (!ok) return 0;
#pragma unroll
    for (int r = 0; r < R; ++r) {
        const int i = l + r * L;
        const int ri = (i * (i + 1)) >> 1;
        if (i < N) {
#pragma unroll
            for (int k = 0; k < N; ++k) {
                if (k < i) Hs[ri + k] = h[r][k];
            }
            Hs[ri + i] = dinv[r];
        }
    }
    __syncwarp(MASK);
}
"""

# each lane's columns of the factor (the rows' entries above the diagonal) and y = −g
_LOAD_COLUMNS = """\
T c[R][N];
T y[R];
#pragma unroll
for (int r = 0; r < R; ++r) {
    const int i = l + r * L;
#pragma unroll
    for (int k = 0; k < N; ++k) {
        c[r][k] = T(0);
        if (i < N && k > i) c[r][k] = Hs[((k * (k + 1)) >> 1) + i];
    }
    y[r] = i < N ? -g.data[i] : T(0);
}
"""

# L y = −g, y_j / D_j shuffled from row j's lane
_FORWARD = """\
#pragma unroll
for (int j = 0; j < N; ++j) {
    const T tj = __shfl_sync(MASK, y[j / L] * dinv[j / L], j % L, L);
#pragma unroll
    for (int r = 0; r < R; ++r) {
        if (l + r * L > j) y[r] -= h[r][j] * tj;
    }
}
"""

# Lᵀ Δq = D⁻¹ y from the last row, x_k shuffled to the rows above it; Δq to dq
_BACKWARD = """\
#pragma unroll
for (int k = N - 1; k >= 0; --k) {
    const T xk = __shfl_sync(MASK, y[k / L] * dinv[k / L], k % L, L);
#pragma unroll
    for (int r = 0; r < R; ++r) {
        if (l + r * L < k) y[r] -= c[r][k] * xk;
    }
}
#pragma unroll
for (int r = 0; r < R; ++r) {
    if (l + r * L < N) dq.data[l + r * L] = y[r] * dinv[r];
}
__syncwarp(MASK);
return ok;
"""


@functools.lru_cache(maxsize=None)
def warp_ldl_solve(dtype, n: int, lanes: int = 32):
    """A native CUDA function: the lane-split step's L D Lᵀ factor and substitutions for one world
    of ``n`` unknowns, solved by its ``lanes`` lanes (32: a warp; 16 or 8: a segment of a warp that
    holds 2 or 4 worlds) with the system in registers.

    ``regs_ldl_solve(H, g, dq, lane, factor) -> ok``.  Lane l holds rows l, l + lanes, … (R =
    ⌈n / lanes⌉ of them) of the packed H (shared memory) in registers.  With ``factor``, column j of
    the right-looking factor takes D_j = H[j, j] and each H[k, j] from their lanes by shuffles
    within the world's segment, and each lane updates its rows in place, H[i, k] −= H[i, j] H[k, j]
    / D_j (j < k ≤ i): the arithmetic of ``ldl_lanes``, in the same order, without its barrier and
    shared-memory round trip a column (so the same factor for any lane count).  The factor goes
    back to H as ldl_lanes leaves it (D_j L_ij below the diagonal, 1/D_j on it), so a later
    iteration can reuse it (``factor`` 0 loads it).  Then Δq = −(L D Lᵀ)⁻¹g: forward, y_i −=
    H[i, j] y_j / D_j with y_j / D_j shuffled from row j's lane; backward from the last row, with
    each lane holding its rows' columns of H (loaded once the factor is in H), so x_k is shuffled
    to the rows above it.  Δq goes to dq.  ok: 0 when a pivot is not positive and finite (the same
    broadcast pivot decides it on every lane).  Every loop is unrolled over the compile-time n, so
    the rows stay in registers.  CUDA only (the CPU's lanes use ldl_lanes and solve_lanes)."""
    ctype = "float" if dtype == wp.float32 else "double"
    body = _prelude(ctype, n, lanes) + _LOAD_ROWS + _FACTOR + _LOAD_COLUMNS + _FORWARD + _BACKWARD
    snippet = "\n#if defined(__CUDA_ARCH__)\n" + body + "#else\nreturn 0;\n#endif\n"

    @wp.func_native(snippet)
    def regs_ldl_solve(H: wp.array(dtype=dtype), g: wp.array(dtype=dtype), dq: wp.array(dtype=dtype), lane: int,
                       factor: int) -> int:  # fmt: skip
        ...

    return regs_ldl_solve


@functools.lru_cache(maxsize=None)
def factor(spec: KernelSpec):
    """The lane-split factor and solves (``ldl_lanes``, ``solve_lanes``) for the kernel's N
    unknowns and LANES lanes a world."""
    dtype, N, LANES = spec.dtype, spec.N, spec.LANES
    staged = spec.staged()
    reductions, row_first, column_end = staged["reductions"], staged["row_first"], staged["column_end"]
    at = indexing(spec)
    hrow, own_all, block_sync = at.hrow, at.own_all, at.block_sync
    zero, one = dtype(0.0), dtype(1.0)

    @wp.func
    def ldl_lanes(H: wp.array(dtype=dtype), s: int, lane: int):
        """H = L D Lᵀ in place (H packed from s), right-looking, lane l on its rows i ≡ l (mod LANES):
        at column j every lane reads D_j = H[j, j] and updates its rows below it, H[i, k] −=
        H[i, j] H[k, j] / D_j for j < k ≤ i (four k at a time: independent loads), which reads
        column j and writes right of it only: one barrier a column.  Left in H: D_j L_ij below the
        diagonal (no pass to scale it) and 1/D_j on it, stored a column late by the row's owner,
        once no lane reads D_j.  0 when H is not positive definite (the same test of the same D_j
        on every lane).  In the block band (``band``) column j reaches only the rows up to the
        next body's, and those rows store every column from j on: the dense factor, bit for bit."""
        inv = zero
        for j in range(N):
            dj = H[s + hrow(j) + j]
            if not (dj > zero) or not wp.isfinite(dj):
                return 0
            if j > 0 and (j - 1) % LANES == lane:
                H[s + hrow(j - 1) + j - 1] = inv
            inv = one / dj
            for i in range(j + 1 + own_all(j + 1, lane), column_end(j, N), LANES):
                ri = s + hrow(i)
                cj = H[ri + j] * inv
                k = j + 1
                while k + 4 <= i + 1:
                    a0 = H[s + hrow(k) + j]
                    a1 = H[s + hrow(k + 1) + j]
                    a2 = H[s + hrow(k + 2) + j]
                    a3 = H[s + hrow(k + 3) + j]
                    H[ri + k] = H[ri + k] - cj * a0
                    H[ri + k + 1] = H[ri + k + 1] - cj * a1
                    H[ri + k + 2] = H[ri + k + 2] - cj * a2
                    H[ri + k + 3] = H[ri + k + 3] - cj * a3
                    k += 4
                while k <= i:
                    H[ri + k] = H[ri + k] - cj * H[s + hrow(k) + j]
                    k += 1
            block_sync()
        if (N - 1) % LANES == lane:
            H[s + hrow(N - 1) + N - 1] = inv
        return 1

    @wp.func
    def solve_lanes(H: wp.array(dtype=dtype), g: wp.array(dtype=dtype), dq: wp.array(dtype=dtype), s: int, lane: int):
        """Δq = −(L D Lᵀ)⁻¹g from ldl_lanes' factor (1/D on the diagonal), each lane on its own rows'
        entries: forward, L y = −g a column at a time (every lane reads y_j, the rows below it are
        updated by their owners); backward, Δq_k = (y_k − Σ_{i>k} H[i, k] Δq_i) / D_k from the last
        row, the same way.
        One barrier a column; a backward Δq_k is stored after its barrier, once no lane reads y_k.
        Then every lane forms (ok, gᵀΔq, ‖Δq‖∞, ‖g‖₁).  In the block band, only the stored entries:
        rows up to column_end(j) forward, columns from row_first(k) backward."""
        for i in range(lane, N, LANES):
            dq[s + i] = -g[s + i]
        block_sync()
        for j in range(N):
            tj = dq[s + j] * H[s + hrow(j) + j]  # y_j / D_j: L_ij y_j = H[i, j] y_j / D_j
            for i in range(j + 1 + own_all(j + 1, lane), column_end(j, N), LANES):
                dq[s + i] = dq[s + i] - H[s + hrow(i) + j] * tj
            block_sync()
        for kk in range(N):
            k = N - 1 - kk
            xk = dq[s + k] * H[s + hrow(k) + k]
            rk = s + hrow(k)
            lo = row_first(k)
            for i in range(lo + own_all(lo, lane), k, LANES):
                dq[s + i] = dq[s + i] - H[rk + i] * xk
            block_sync()
            if k % LANES == lane:
                dq[s + k] = xk
        block_sync()
        return reductions(g, dq, s, N, 1)

    return SimpleNamespace(ldl_lanes=ldl_lanes, solve_lanes=solve_lanes)
