"""The fused Newton step: one thread runs every iteration, line search and stop test of a world's
solve in a single kernel launch, world after world when there are more worlds than threads.

Same arithmetic and the same Newton rules as the staged kernels of ``solver.py`` (each
constitution's per-instance evaluator; point joints' Hessian blocks added from their 4 × 4
Kronecker factors and bodies' from their parts, neither built as a 12 × 12 matrix; effort drives'
gradient only, as their blocks are zero; an iteration that reuses the last Cholesky factor
assembles the gradient only and leaves H, which holds the factor; ``Solver.fused_system`` checks
this assembly against the staged one), without atomics (a thread owns its scratch column of the
flat ``g``/``H``/``dq``, indexed as in ``solver_kernels``), without per-iteration
launches, and with the code of absent constitutions compiled out (``wp.static`` on what the scene
has).  ``Solver(fused=True)`` uses it.

``scratch="lanes"``: a block of L threads (lanes) per world instead of one thread, the world's
g, H (packed) and Δq in the block's shared memory on CUDA (else contiguous in the global
scratch).  Lane l owns the rows i ≡ l (mod L) of g and H: every lane evaluates every term (the
same energy, in the same order, on each: no reduction) and adds only its rows' entries of the
term's blocks, so a block's puts, most of a one-thread assembly, run L rows at once without
atomics; the factor is an L D Lᵀ by rows (``ldl_lanes``) and the substitutions likewise, one
barrier (``block_sync``, also on the CPU's cooperative blocks) a column; on a GPU with 32 lanes
(one warp) and up to 32 unknowns the same factor and substitutions run with each lane's row in
registers, the pivots and columns passed by warp shuffles (``warp_ldl_solve``, no barrier); the
bodies' trial steps and updates are split by body.  Every lane takes every branch, decided from
the same numbers.  Meant for few worlds, where one thread per world leaves most of the GPU idle,
waiting on each thread's chain of dependent loads.

``bracket`` (``Solver.one_launch``): the kernel also opens and closes each world's step (the
kernels of ``Solver._open`` and ``_close`` as functions, a body or a joint per lane), so a step is
one launch.
"""
import functools
from typing import Any

import numpy as np
import warp as wp

from . import coordinates, solver_kernels
from .angles import angle_ops
from .constitutions import _point_joint, affine_body, drive, prismatic_joint, prismatic_limit, revolute_limit
from .warp_ops import ENERGY, GRADIENT, HESSIAN, ops

OK, FAILED = 0, 1
# the kinds of Terms.work's items (a lane group's joints, limits and drives)
WORK_REVOLUTE, WORK_FIXED, WORK_PRISMATIC, WORK_REVOLUTE_LIMIT, WORK_PRISMATIC_LIMIT, WORK_DRIVE = 1, 2, 3, 4, 5, 6
WORK_ANGLE = 7  # a revolute joint's limit and drives on its one angle (fused_kernel's rev_angles)


@wp.func_native("WP_TILE_SYNC();")
def block_sync():
    """A barrier for the threads of a block (``__syncthreads`` on CUDA; on the CPU a yield to the
    block's other fibers when ``wp.config.enable_cpu_blocks``, else a no-op for its one thread)."""
    ...


whole_block_sync = block_sync  # (kept under its own name: a kernel's block_sync may be its world's)


@wp.func_native("""
#if defined(__CUDA_ARCH__)
return clock64();
#else
return 0;
#endif
""")
def cycles() -> wp.int64:
    """The SM's cycle counter on CUDA (0 on the CPU), for fused_kernel(phase_clock=True)."""
    ...


@wp.func_native("return WP_TILE_THREAD_IDX;")
def lane_index() -> int:
    """The thread's index within its block (a CPU block's fiber, or 0 for a one-thread block)."""
    ...


def shared_array(dtype, count: int):
    """A function returning the address of a static shared-memory array of ``count`` ``dtype``
    words, one per CUDA block (for kernels built for CUDA only)."""
    ctype = "float" if dtype == wp.float32 else "double"

    @wp.func_native(f"__shared__ {ctype} scratch[{count}];\nreturn (uint64_t)scratch;\n")
    def shared_scratch() -> wp.uint64:
        ...

    return shared_scratch


def lanes_scratch_words(n: int, groups: int) -> int:
    """Words of one world's scratch in the lane-split step (its block's shared memory on CUDA):
    ``groups`` copies of H's packed lower triangle (n(n+1)/2 each), g (n, then the bodies' energies
    and, with groups, the copies' g, the groups' energies and the factor's flag) and Δq (n)."""
    tri, nf = n * (n + 1) // 2, n // 12
    glen = n + nf if groups == 1 else (groups - 1) * tri + n + nf + groups + 1
    return groups * tri + glen + n


@functools.lru_cache(maxsize=None)
def world_funcs(lanes: int, per_block: int):
    """(world_sync, world_lane) for a kernel whose worlds have ``lanes`` threads each, ``per_block``
    worlds to a CUDA block: a barrier for one world's lanes and the thread's lane in its world.  One
    world a block: the block's barrier and thread index (block_sync, lane_index).  Several: worlds
    of 32 lanes (a warp each, lockstep blocks) ``__syncwarp`` over their warp; worlds of 8 or 16
    lanes side by side in a warp over the world's own lanes, so a world waits only for itself (two
    worlds of a warp may take different branches)."""
    if per_block <= 1:
        return block_sync, lane_index
    if lanes & (lanes - 1) or lanes > 32 or lanes * per_block % 32:
        raise ValueError(f"{per_block} worlds of {lanes} lanes do not fill whole warps")
    mask = "" if lanes == 32 else f"((1u << {lanes}) - 1u) << ((threadIdx.x & 31u) & ~{lanes - 1}u)"
    sync = f"""
#if defined(__CUDA_ARCH__)
__syncwarp({mask});
#else
WP_TILE_SYNC();
#endif
"""
    index = f"return WP_TILE_THREAD_IDX % {lanes};"

    @wp.func_native(sync)
    def world_sync():
        ...

    @wp.func_native(index)
    def world_lane() -> int:
        ...

    return world_sync, world_lane


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
    L = int(lanes)
    R = -(-int(n) // L)
    snippet = f"""
#if defined(__CUDA_ARCH__)
typedef {ctype} T;
const int N = {int(n)};
const int L = {L};
const int R = {R};
const unsigned MASK = {"0xffffffffu" if L == 32 else f"((1u << {L}) - 1u) << ((threadIdx.x & 31u) & ~{L - 1}u)"};
T* Hs = H.data;
const int l = lane;
T h[R][N];
T dinv[R];
#pragma unroll
for (int r = 0; r < R; ++r) {{
    const int i = l + r * L;
    const int ri = (i * (i + 1)) >> 1;
#pragma unroll
    for (int k = 0; k < N; ++k) {{
        h[r][k] = T(0);
        if (i < N && k <= i) h[r][k] = Hs[ri + k];
    }}
    dinv[r] = i < N ? Hs[ri + i] : T(0);  // 1/D_i, where a reused factor holds it
}}
int ok = 1;
if (factor) {{
#pragma unroll
    for (int r = 0; r < R; ++r) dinv[r] = T(0);
#pragma unroll
    for (int j = 0; j < N; ++j) {{
        const T dj = __shfl_sync(MASK, h[j / L][j], j % L, L);
        if (!(dj > T(0)) || !isfinite(dj)) ok = 0;
        const T inv = T(1) / dj;
        T cj[R];
#pragma unroll
        for (int r = 0; r < R; ++r) {{
            if (l + r * L == j) dinv[r] = inv;
            cj[r] = h[r][j] * inv;
        }}
#pragma unroll
        for (int k = j + 1; k < N; ++k) {{
            const T hk = __shfl_sync(MASK, h[k / L][j], k % L, L);
#pragma unroll
            for (int r = 0; r < R; ++r) {{
                if (l + r * L >= k) h[r][k] -= cj[r] * hk;
            }}
        }}
    }}
    if (!ok) return 0;
#pragma unroll
    for (int r = 0; r < R; ++r) {{
        const int i = l + r * L;
        const int ri = (i * (i + 1)) >> 1;
        if (i < N) {{
#pragma unroll
            for (int k = 0; k < N; ++k) {{
                if (k < i) Hs[ri + k] = h[r][k];
            }}
            Hs[ri + i] = dinv[r];
        }}
    }}
    __syncwarp(MASK);
}}
T c[R][N];
T y[R];
#pragma unroll
for (int r = 0; r < R; ++r) {{
    const int i = l + r * L;
#pragma unroll
    for (int k = 0; k < N; ++k) {{
        c[r][k] = T(0);
        if (i < N && k > i) c[r][k] = Hs[((k * (k + 1)) >> 1) + i];
    }}
    y[r] = i < N ? -g.data[i] : T(0);
}}
#pragma unroll
for (int j = 0; j < N; ++j) {{
    const T tj = __shfl_sync(MASK, y[j / L] * dinv[j / L], j % L, L);
#pragma unroll
    for (int r = 0; r < R; ++r) {{
        if (l + r * L > j) y[r] -= h[r][j] * tj;
    }}
}}
#pragma unroll
for (int k = N - 1; k >= 0; --k) {{
    const T xk = __shfl_sync(MASK, y[k / L] * dinv[k / L], k % L, L);
#pragma unroll
    for (int r = 0; r < R; ++r) {{
        if (l + r * L < k) y[r] -= c[r][k] * xk;
    }}
}}
#pragma unroll
for (int r = 0; r < R; ++r) {{
    if (l + r * L < N) dq.data[l + r * L] = y[r] * dinv[r];
}}
__syncwarp(MASK);
return ok;
#else
return 0;
#endif
"""

    @wp.func_native(snippet)
    def regs_ldl_solve(H: wp.array(dtype=dtype), g: wp.array(dtype=dtype), dq: wp.array(dtype=dtype), lane: int,
                       factor: int) -> int:  # fmt: skip
        ...

    return regs_ldl_solve


# the phases fused_kernel(phase_clock=True) times, columns of Terms.clock (cycles summed per world)
PHASES = ("zero", "assemble", "factor", "solve", "step", "step: energy", "step: trial", "assemble: bodies",
          "assemble: revolute", "assemble: fixed", "assemble: prismatic", "assemble: limits", "assemble: drives",
          "open", "close", "open: bodies", "open: joints", "open: predict", "close: finalize", "close: joints")
WORLD_PHASES = (0, 1, 2, 3, 4, 13, 14)  # the phases that partition a world's step (the rest split these)


@functools.lru_cache(maxsize=None)
def fused_kernel(dtype, has_rev, has_fix, has_pri, has_rlim, has_plim, has_drive, scratch="global", n=0,
                 envelope=False, phase_clock=False, cuda=False, block=0, bracket=True, groups=1, per_block=1,
                 pri_limits=False, pri_drives=False, rev_angles=False, quadratic=0.0, hold=False):  # fmt: skip
    """The Newton kernel for a scene with the given constitutions and ``n`` unknowns per world.

    ``scratch``: "global": a thread per world, its g, H, Δq in global arrays (one column per thread);
    "shared": a thread per world as "global", H's lower triangle packed (n(n+1)/2 words) and, built
    for CUDA (``cuda``), the block's ``block`` threads' g, H, Δq in its shared memory, one column
    per thread (on the CPU the packed columns stay in the global arrays);
    "lanes": a block of ``block`` lanes per world, its system packed (see the module's docstring).  (The
    "tiled" layout, a block per world repeating every evaluator on all lanes with H in shared memory,
    measured slower than "global" but for 1,024 double pendulums and was removed; a third layout,
    g, H and Δq in each thread's local memory, measured
    slower than "global" at every batch size on an H100 and was removed; see results/.)
    ``cuda``: built for a GPU (the lane-split step then keeps its scratch in shared memory).
    ``phase_clock``: lane 0 adds each phase's cycles (PHASES) to ``Terms.clock`` (profiling only).
    ``bracket``: the kernel also opens each world's step before its solve (the finite check, the
    joints' references, the prediction q̃ and the initial guess) and closes it after (velocities,
    histories, joint coordinates), so a step is one launch; else those run as kernels of their own
    (``Solver._open``, ``Solver._close``).
    ``groups`` (lanes only): the world's ``block`` lanes split into this many groups of
    block/groups lanes (a warp each on a GPU), each group evaluating its own share of the terms
    (``Terms.work``: the bodies on group 0, each joint, limit and drive on one group, balanced by
    the host, ``Solver.lane_work``) into its own copy of g and H, which are then summed (one
    barrier); the factor and everything after it as with one group.  A world's chain of dependent
    evaluations, one warp evaluating every term in turn, is cut to its busiest group's share.
    ``per_block`` (lanes on CUDA, one group): worlds a block, in whole warps (world_funcs); worlds
    of 8 or 16 lanes side by side in a warp, so a warp's instructions serve 4 or 2 worlds at once.
    A block of several warps starts each step of a launch (``steps``) at a barrier of the whole
    block: its warps then run each stretch of the kernel's code together (Solver.lockstep_warps).
    ``pri_limits`` / ``pri_drives``: a prismatic joint's limit / one drive on it are evaluated in
    the joint's own term (``Terms.pri_lim``, ``pri_drv``; prismatic_term), on the displacement and
    frames the joint has loaded, with one put of the summed gradient; the limits and drives left
    (``has_plim``, ``has_drive``: ``Terms.drive_rest``) keep terms of their own.  ``rev_angles``:
    a revolute joint's limit and up to two drives on it are one term on the joint's angle
    (``Terms.ang_joint``, ``ang_lim``, ``ang_drv``; angle_term), its cos, sin, increment and
    gradient computed once; ``has_rlim`` then has no limits left.  ``quadratic``
    (SolverSettings.quadratic_stop): a Newton step from a fresh factor accepted at α = 1 under this
    many times q's rounding floor ends the solve (take_step).  ``hold`` (with
    ``bracket``): the step leaves alone the worlds of Bracket.hold and, while Bracket.go[0] is 0,
    every world (step_world; a vector env's step graph), a check that a scene stepped on its own
    does not carry."""
    # loops stay loops: unrolling the 12×12 block loops of every inlined evaluator multiplies the
    # code size, and with it NVRTC's compile time (minutes); on an H100 unrolling the 3-loops
    # (max_unroll 3) made the cart-pole step 15% slower, max_unroll 4 compiled for minutes for 5%
    options = dict(module="unique", module_options={"max_unroll": 1})
    lanes = scratch == "lanes"
    # lanes keep their world's system packed too (in shared memory on CUDA, else contiguous in the
    # global scratch); LANES threads per world, a constant of the kernel (``block``)
    packed = scratch in ("shared", "lanes")
    LANES = max(int(block), 1) if lanes else 1
    # lane groups (a warp each on a GPU): RL lanes share a copy of g and H, each owning its rows
    G = max(int(groups), 1) if lanes else 1
    if LANES % G:
        raise ValueError(f"{LANES} lanes a world do not split into {G} equal groups")
    RL = LANES // G
    WPB = max(int(per_block), 1) if lanes and cuda else 1  # worlds a block
    if WPB > 1 and G > 1:
        raise ValueError("lane groups take a block per world (per_block 1)")
    # a world's barrier and lane: the block's, or its own lanes' of a warp shared with other worlds
    block_sync, lane_index = world_funcs(LANES, WPB)  # noqa: F811 (the kernel's own, shadowing the module's)
    # a block of several warps (lockstep): its worlds start each step of a launch together, so the
    # SM's warps run the same stretch of the kernel's code at once (Solver.lockstep_warps)
    LOCKSTEP = LANES * WPB > 32
    # on a GPU, a world whose lanes (the first group's warp, when there are several) hold at most
    # 3 of its rows each, factors and solves in registers
    warp_regs = lanes and cuda and RL in (8, 16, 32) and (G == 1 or RL == 32) and n <= 3 * RL
    # compact code where a world's step is a latency-bound chain (lanes): blocks of a term in loops
    # of selected arguments, one inlined assemble per mode (cart-pole's kernel 414 KB of SASS ->
    # 291 KB, 1,024 worlds 5% faster on an H100, results/code_size_h100.md); a thread per world
    # (throughput-bound) keeps the branches, whose selects cost it 1-5% there
    compact = lanes
    regs_ldl_solve = warp_ldl_solve(dtype, n, RL) if warp_regs else None
    N = n  # unknowns per world (12 per free body), a constant of the kernel
    TRI = N * (N + 1) // 2  # H's packed lower triangle (and, lanes, the stride of the groups' copies)
    o = ops(dtype)
    vec3, vec4, vec12, mat33, mat44 = o.vec3, o.vec4, o.vec12, o.mat33, o.mat44
    body_grad = affine_body.kernels(dtype).body_grad
    hessian_parts, a_block = affine_body.kernels(dtype).hessian_parts, affine_body.kernels(dtype).a_block
    retract_body = affine_body.kernels(dtype).retract
    point_eval_kron = _point_joint.kernel(dtype).eval_kron
    kron3, kron_index = o.kron3, o.kron_index
    prismatic_grad = prismatic_joint.kernel(dtype).grad
    rlim_parts, rlim_cubic = revolute_limit.kernel(dtype).parts, revolute_limit.kernel(dtype).cubic
    cos_sin, delta_theta, theta_grad = angle_ops(dtype).cos_sin, angle_ops(dtype).delta_theta, angle_ops(dtype).theta_grad
    plim_parts, plim_cubic = prismatic_limit.kernel(dtype).parts, prismatic_limit.kernel(dtype).cubic
    drive_parts, drive_scalar = drive.kernel(dtype).parts, drive.kernel(dtype).scalar
    pri_displacement, pri_displacement_grad = angle_ops(dtype).displacement, angle_ops(dtype).displacement_grad
    staged = solver_kernels.kernels(dtype, envelope, packed)
    h_row = staged["h_row"]
    cholesky_solve, factored_solve = staged["cholesky_solve"], staged["factored_solve"]
    reductions = staged["reductions"]
    noise_floor, energy_noise = staged["noise_floor"], staged["energy_noise"]
    open_body, predict_body, finalize_body = staged["open_body"], staged["predict_body"], staged["finalize_body"]
    begin_joint, _, close_joint = coordinates.funcs(dtype)
    zero, one, half = dtype(0.0), dtype(1.0), dtype(0.5)
    EPS = dtype(float(np.finfo(np.float32 if dtype == wp.float32 else np.float64).eps))
    QUAD = dtype(4.0 * float(quadratic))  # × q's rounding (SolverSettings.quadratic_stop)

    # the thread's scratch column s of the flat g, H (solver_kernels: entry (i, j) of H at
    # (hrow(i) + j)·T + s, hrow(i) = i·N or, packed, i(i+1)/2; entry i of g at i·T + s); B is T, the
    # scratch width

    @wp.func
    def hrow(i: int):
        """Where row i of H starts in a scratch column (solver_kernels.h_row: square or packed)."""
        return h_row(i, N)

    @wp.func
    def own_from(o: int):
        """The first r ≥ 0 whose row o + r is this thread's in an assembly: every row for one thread
        per world; with lanes, lane l of its group owns the rows i ≡ l (mod RL) of the group's copy
        of g and H, so the lanes add their shares of a block at once, with no two lanes on one
        entry (row r, r + RL, … from here)."""
        if wp.static(lanes):
            return (lane_index() % RL - o % RL + RL) % RL
        return 0

    @wp.func
    def own_all(o: int, lane: int):
        """As own_from for the factor and the solves, which every lane of the world splits: lane l
        owns the rows i ≡ l (mod LANES) (row r, r + LANES, … from here)."""
        return (lane - o % LANES + LANES) % LANES

    @wp.func
    def kron_split(a: int):
        """(m, c) with kron_index(m, c) = a: component m, factor c of u = (1, x̄)."""
        if a < 3:
            return a, 0
        return (a - 3) // 3, (a - 3) % 3 + 1

    @wp.func
    def put_grad(g: Any, s: int, B: int, o: int, v: vec12):
        if o >= 0:
            for r in range(own_from(o), 12, RL):
                p = (o + r) * B + s
                g[p] = g[p] + v[r]

    @wp.func
    def body_row(H: Any, s: int, B: int, o: int, r: int, qb: vec12, m: dtype, c: vec3, S: mat33, ks: dtype, Rp: mat33,
                 ata: mat33):  # fmt: skip
        """Row r of body o's Hessian (put_body's entries of that row, lower triangle), for a lane."""
        p = hrow(o + r) + o
        if r < 3:
            H[(p + r) * B + s] = H[(p + r) * B + s] + m
        else:
            kk = (r - 3) // 3
            a = (r - 3) % 3
            H[(p + kk) * B + s] = H[(p + kk) * B + s] + c[a]
            for ll in range(kk + 1):
                blk = a_block(qb, kk, ll, Rp, ata, ks, S)
                for bb in range(3):
                    if kk != ll or bb <= a:
                        q = (p + 3 + 3 * ll + bb) * B + s
                        H[q] = H[q] + blk[a, bb]

    @wp.func
    def put_body(H: Any, s: int, B: int, o: int, qb: vec12, m: dtype, c: vec3, S: mat33, ks: dtype):
        """Body o's Hessian (affine_body.body_eval's h) added to the lower triangle from its parts,
        without building the 12 × 12 matrix in the thread's local memory: m on the translation
        diagonal, the first moments c below it, and the A rows' 3 × 3 blocks (a_block), 57
        entries where the dense block's lower triangle has 78.  (Lanes add bodies by rows: lane_bodies.)"""
        if o >= 0:
            Rp, ata = hessian_parts(qb)
            for r in range(3):
                p = (hrow(o + r) + o + r) * B + s
                H[p] = H[p] + m
                for a in range(3):
                    p = (hrow(o + 3 + 3 * r + a) + o + r) * B + s
                    H[p] = H[p] + c[a]
            for kk in range(3):
                for ll in range(kk + 1):
                    blk = a_block(qb, kk, ll, Rp, ata, ks, S)
                    for a in range(3):
                        p = (hrow(o + 3 + 3 * kk + a) + o + 3 + 3 * ll) * B + s
                        for bb in range(3):
                            if kk != ll or bb <= a:
                                H[p] = H[p] + blk[a, bb]
                            p += B

    @wp.func
    def kron_rows(H: Any, s: int, B: int, oa: int, ob: int, U: mat44):
        """Block (oa, ob), oa ≥ ob, += U ⊗ I₃ (a diagonal block's lower half), this thread's rows:
        row kron_index(m, c) holds U[c, d] at columns kron_index(m, d)."""
        for a in range(own_from(oa), 12, RL):
            m, c = kron_split(a)
            for d in range(4):
                b = kron_index(m, d)
                if oa > ob or b <= a:
                    p = (hrow(oa + a) + ob + b) * B + s
                    H[p] = H[p] + U[c, d]

    @wp.func
    def put_kron(H: Any, s: int, B: int, oa: int, ob: int, U: mat44):
        """Block (oa, ob) = U ⊗ I₃ (see warp_ops.kron3): its 48 non-zero entries only; above the
        diagonal as its transpose below it (lower triangle only, all the factor reads)."""
        if oa >= 0 and ob >= 0:
            if wp.static(compact):  # selects, not branches: one inlined kron_rows
                sw = oa < ob
                kron_rows(H, s, B, wp.max(oa, ob), wp.min(oa, ob), wp.where(sw, wp.transpose(U), U))
            elif oa < ob:
                kron_rows(H, s, B, ob, oa, wp.transpose(U))
            else:
                kron_rows(H, s, B, oa, ob, U)

    @wp.func
    def ksum_rows(H: Any, s: int, B: int, oa: int, ob: int, ua: vec4, ta: vec4, ub: vec4, tb: vec4, Pcc: mat33,
                  Pct: mat33, Ptc: mat33, Ptt: mat33, U: mat44):  # fmt: skip
        """put_ksum's block (oa, ob), oa ≥ ob, this thread's rows."""
        for ra in range(own_from(oa), 12, RL):
            al, a = kron_split(ra)
            for b in range(4):
                cc = ua[a] * ub[b]
                ct = ua[a] * tb[b]
                tc = ta[a] * ub[b]
                tt = ta[a] * tb[b]
                for be in range(3):
                    cb = kron_index(be, b)
                    if oa > ob or cb <= ra:
                        v = cc * Pcc[al, be] + ct * Pct[al, be] + tc * Ptc[al, be] + tt * Ptt[al, be]
                        if al == be:
                            v += U[a, b]
                        p = (hrow(oa + ra) + ob + cb) * B + s
                        H[p] = H[p] + v

    @wp.func
    def put_ksum(H: Any, s: int, B: int, oa: int, ob: int, ua: vec4, ta: vec4, ub: vec4, tb: vec4, Pcc: mat33,
                 Pct: mat33, Ptc: mat33, Ptt: mat33, U: mat44):  # fmt: skip
        """Add block (oa, ob) = (ua ubᵀ) ⊗ Pcc + (ua tbᵀ) ⊗ Pct + (ta ubᵀ) ⊗ Ptc + (ta tbᵀ) ⊗ Ptt
        + U ⊗ I₃
        (entry (kron_index(α, a), kron_index(β, b)) = Σ u[a] v[b] P[α, β] + δ_αβ U[a, b]), lower
        triangle only as put_outer: the Gauss–Newton block of rows J(x)ᵀ-type Kronecker products
        (prismatic_hessian), summed per entry in registers, without a 12 × 12 matrix.  Above the
        diagonal as the transpose, (ub uaᵀ) ⊗ Pccᵀ + (ub taᵀ) ⊗ Ptcᵀ + (tb uaᵀ) ⊗ Pctᵀ + …, below it."""
        if oa >= 0 and ob >= 0:
            if wp.static(compact):  # selects, not branches: one inlined ksum_rows
                sw = oa < ob
                ksum_rows(H, s, B, wp.max(oa, ob), wp.min(oa, ob), wp.where(sw, ub, ua), wp.where(sw, tb, ta),
                          wp.where(sw, ua, ub), wp.where(sw, ta, tb), wp.where(sw, wp.transpose(Pcc), Pcc),
                          wp.where(sw, wp.transpose(Ptc), Pct), wp.where(sw, wp.transpose(Pct), Ptc),
                          wp.where(sw, wp.transpose(Ptt), Ptt), wp.where(sw, wp.transpose(U), U))  # fmt: skip
            elif oa < ob:
                ksum_rows(H, s, B, ob, oa, ub, tb, ua, ta, wp.transpose(Pcc), wp.transpose(Ptc), wp.transpose(Pct),
                          wp.transpose(Ptt), wp.transpose(U))  # fmt: skip
            else:
                ksum_rows(H, s, B, oa, ob, ua, ta, ub, tb, Pcc, Pct, Ptc, Ptt, U)

    @wp.func
    def cross_gram(x: vec3, y: vec3):
        """Σ_m (row m of [x]×)ᵀ(row m of [y]×) = [x]×ᵀ[y]× = (x·y) I − y xᵀ."""
        return wp.dot(x, y) * wp.identity(3, dtype) - wp.outer(y, x)

    @wp.func
    def prismatic_hessian(H: Any, s: int, B: int, oi: int, oj: int, qi: vec12, qj: vec12, ci: vec3, cj: vec3, ti: vec3,
                          tj: vec3, ni: vec3, nj: vec3, bi: vec3, bj: vec3, kk: dtype):  # fmt: skip
        """The prismatic joint's Gauss–Newton Hessian (prismatic_joint.prismatic_eval's blocks) added
        straight into H.  Its rows are Kronecker products: C0's row m is J(c_i)ᵀ([T_i]×)_m +
        J̊(t_i)ᵀ([d]×)_m on body i and J(c_j)ᵀ([−T_i]×)_m on body j (C1's likewise), so Σ_m of their
        outer products is (ũ ũ'ᵀ) ⊗ [x]×ᵀ[y]× summed over the pairs of terms, ũ = (1, c̄) or (0, t̄);
        C2, C3 add (ũn ũnᵀ + ũb ũbᵀ) ⊗ I₃ as in prismatic_eval."""
        d = o.point(qj, cj) - o.point(qi, ci)
        Ti = o.direction(qi, ti)
        Tj = o.direction(qj, tj)
        uci = vec4(one, ci[0], ci[1], ci[2])
        uti = vec4(zero, ti[0], ti[1], ti[2])
        ucj = vec4(one, cj[0], cj[1], cj[2])
        utj = vec4(zero, tj[0], tj[1], tj[2])
        uni = vec4(zero, ni[0], ni[1], ni[2])
        unj = vec4(zero, nj[0], nj[1], nj[2])
        ubi = vec4(zero, bi[0], bi[1], bi[2])
        ubj = vec4(zero, bj[0], bj[1], bj[2])
        PT = kk * (cross_gram(Ti, Ti) + cross_gram(Tj, Tj))
        Pdd = kk * cross_gram(d, d)
        if wp.static(compact):
            # blocks (i, i), (j, j), (i, j) in a loop of selected arguments: one inlined put_ksum
            # where three calls inlined three (put_ksum skips a block of a fixed body, oi or oj < 0)
            for blk in range(3):
                ra = blk != 1  # the block's rows are body i's (else j's); its columns body i's for blk 0
                cb = blk == 0
                Pct = kk * cross_gram(wp.where(blk == 0, Ti, Tj), d)
                Ptc = kk * cross_gram(d, wp.where(blk == 1, Tj, Ti))
                U = wp.outer(wp.where(ra, uni, unj), wp.where(cb, uni, unj)) + wp.outer(wp.where(ra, ubi, ubj),
                                                                                       wp.where(cb, ubi, ubj))  # fmt: skip
                put_ksum(H, s, B, wp.where(ra, oi, oj), wp.where(cb, oi, oj), wp.where(ra, uci, ucj),
                         wp.where(ra, uti, utj), wp.where(cb, uci, ucj), wp.where(cb, uti, utj),
                         wp.where(blk == 2, -PT, PT), wp.where(blk == 1, -Pct, Pct), wp.where(blk == 0, Ptc, -Ptc),
                         wp.where(blk == 2, mat33(), Pdd), wp.where(blk == 2, -kk * U, kk * U))  # fmt: skip
        else:
            if oi >= 0:
                put_ksum(H, s, B, oi, oi, uci, uti, uci, uti, PT, kk * cross_gram(Ti, d), kk * cross_gram(d, Ti), Pdd,
                         kk * (wp.outer(uni, uni) + wp.outer(ubi, ubi)))  # fmt: skip
            if oj >= 0:
                put_ksum(H, s, B, oj, oj, ucj, utj, ucj, utj, PT, -kk * cross_gram(Tj, d), -kk * cross_gram(d, Tj), Pdd,
                         kk * (wp.outer(unj, unj) + wp.outer(ubj, ubj)))  # fmt: skip
            if oi >= 0 and oj >= 0:
                put_ksum(H, s, B, oi, oj, uci, uti, ucj, utj, -PT, kk * cross_gram(Tj, d), -kk * cross_gram(d, Ti),
                         mat33(), -kk * (wp.outer(uni, unj) + wp.outer(ubi, ubj)))  # fmt: skip

    @wp.func
    def trial(q: wp.array2d(dtype=vec12), q_trial: wp.array2d(dtype=vec12), t: Any, step: Any, w: int, row: int,
              s: int, T: int, alpha: dtype, lane: int):  # fmt: skip
        """q_trial[row] = q[w] + α Δq along the retraction's path (affine_body.retract), Δq in
        scratch column s of the flat ``step`` (T columns); lane ``lane`` of LANES moves bodies lane,
        lane + LANES, … (then the block synchronises)."""
        for b in range(lane, q.shape[1], LANES):
            qb = q[w, b]
            ob = t.dof[b]
            if ob >= 0:
                d = vec12()
                for r in range(12):
                    d[r] = step[(ob + r) * T + s]
                qb = retract_body(qb, d, alpha, t.mass[w, b], t.mc[w, b], 0)
            q_trial[row, b] = qb
        if wp.static(lanes):
            block_sync()

    @wp.func
    def put_kron_pair(g: Any, H: Any, s: int, B: int, derivs: int, oi: int, oj: int, gi: vec12, gj: vec12,
                      uii: mat44, uij: mat44, ujj: mat44):  # fmt: skip
        put_grad(g, s, B, oi, gi)
        put_grad(g, s, B, oj, gj)
        if derivs == HESSIAN:
            if wp.static(compact):
                for blk in range(3):  # (i, i), (i, j), (j, j): a loop, so one inlined put_kron
                    put_kron(H, s, B, wp.where(blk < 2, oi, oj), wp.where(blk == 0, oi, oj),
                             wp.where(blk == 0, uii, wp.where(blk == 1, uij, ujj)))  # fmt: skip
            else:
                put_kron(H, s, B, oi, oi, uii)
                put_kron(H, s, B, oi, oj, uij)
                put_kron(H, s, B, oj, oj, ujj)

    @wp.func
    def outer_rows(H: Any, s: int, B: int, oa: int, ob: int, ga: vec12, gb: vec12, cf: dtype):
        """Block (oa, ob), oa ≥ ob, += cf·ga gbᵀ (a diagonal block's lower half), this thread's rows."""
        for r in range(own_from(oa), 12, RL):
            p = (hrow(oa + r) + ob) * B + s
            v = cf * ga[r]
            for c in range(12):
                if oa != ob or c <= r:
                    H[p] = H[p] + v * gb[c]
                p += B

    @wp.func
    def put_outer(H: Any, s: int, B: int, oa: int, ob: int, ga: vec12, gb: vec12, cf: dtype):
        """Add block (oa, ob) = cf·ga gbᵀ and its transpose, lower triangle only (all the Cholesky
        reads): a diagonal block's lower half; (oa, ob) below the diagonal as it is, above it
        transposed.  Each entry is formed as it is added (no 12 × 12 matrix in local memory)."""
        if oa >= 0 and ob >= 0:
            if wp.static(compact):  # selects, not branches: one inlined outer_rows
                sw = oa < ob
                outer_rows(H, s, B, wp.max(oa, ob), wp.min(oa, ob), wp.where(sw, gb, ga), wp.where(sw, ga, gb), cf)
            elif oa < ob:
                outer_rows(H, s, B, ob, oa, gb, ga, cf)
            else:
                outer_rows(H, s, B, oa, ob, ga, gb, cf)

    @wp.func
    def put_rank1(g: Any, H: Any, s: int, B: int, derivs: int, oi: int, oj: int, gi: vec12, gj: vec12, de: dtype,
                  dde: dtype):  # fmt: skip
        """A term E(x) of a scalar joint coordinate x (a limit, a drive), ∇x = (gi, gj): its gradient
        E'∇x and, for HESSIAN where E'' ≠ 0, its Hessian E''∇x∇xᵀ (outer_blocks' blocks)."""
        if derivs != 0:
            put_grad(g, s, B, oi, de * gi)
            put_grad(g, s, B, oj, de * gj)
            if derivs == HESSIAN and dde != zero:
                put_outer_pair(H, s, B, oi, oj, gi, gj, dde)

    @wp.func
    def put_outer_pair(H: Any, s: int, B: int, oi: int, oj: int, gi: vec12, gj: vec12, dde: dtype):
        """The Hessian E''∇x∇xᵀ of a term of a scalar x, ∇x = (gi, gj): its blocks (i, i), (i, j), (j, j)."""
        if wp.static(compact):
            for blk in range(3):  # (i, i), (i, j), (j, j): a loop, so one inlined put_outer
                put_outer(H, s, B, wp.where(blk < 2, oi, oj), wp.where(blk == 0, oi, oj),
                          wp.where(blk < 2, gi, gj), wp.where(blk == 0, gi, gj), dde)  # fmt: skip
        else:
            put_outer(H, s, B, oi, oi, gi, gi, dde)
            put_outer(H, s, B, oi, oj, gi, gj, dde)
            put_outer(H, s, B, oj, oj, gj, gj, dde)

    @wp.struct
    class Terms:
        """Everything the incremental potential reads besides q: model, joint history, controls."""

        q_tilde: wp.array2d(dtype=vec12)
        free: wp.array(dtype=wp.int32)
        dof: wp.array(dtype=wp.int32)
        first: wp.array(dtype=wp.int32)  # the Hessian's envelope (Model.first)
        mass: wp.array2d(dtype=dtype)
        mc: wp.array2d(dtype=vec3)
        S: wp.array2d(dtype=mat33)
        kv: wp.array2d(dtype=dtype)
        h_step: wp.array(dtype=dtype)  # each world's effective step (Solver.h_step)
        body_a: wp.array(dtype=wp.int32)
        body_b: wp.array(dtype=wp.int32)
        joint_kind: wp.array(dtype=wp.int32)
        pts_a: wp.array3d(dtype=vec3)
        pts_b: wp.array3d(dtype=vec3)
        K: wp.array2d(dtype=dtype)
        c_a: wp.array2d(dtype=vec3)
        c_b: wp.array2d(dtype=vec3)
        t_a: wp.array2d(dtype=vec3)
        t_b: wp.array2d(dtype=vec3)
        n_a: wp.array2d(dtype=vec3)
        n_b: wp.array2d(dtype=vec3)
        b_a: wp.array2d(dtype=vec3)
        b_b: wp.array2d(dtype=vec3)
        rev_ids: wp.array(dtype=wp.int32)
        fix_ids: wp.array(dtype=wp.int32)
        pri_ids: wp.array(dtype=wp.int32)
        rlim_ids: wp.array(dtype=wp.int32)
        rlim_lo: wp.array2d(dtype=dtype)
        rlim_up: wp.array2d(dtype=dtype)
        rlim_s: wp.array2d(dtype=dtype)
        plim_ids: wp.array(dtype=wp.int32)
        plim_lo: wp.array2d(dtype=dtype)
        plim_up: wp.array2d(dtype=dtype)
        plim_s: wp.array2d(dtype=dtype)
        theta0: wp.array2d(dtype=dtype)
        c_prev: wp.array2d(dtype=dtype)
        s_prev: wp.array2d(dtype=dtype)
        drive_joint: wp.array(dtype=wp.int32)
        drive_rest: wp.array(dtype=wp.int32)  # the drives with a term of their own (has_drive)
        pri_lim: wp.array(dtype=wp.int32)  # prismatic joint k's limit (pri_limits), or −1
        pri_drv: wp.array(dtype=wp.int32)  # a drive on prismatic joint k (pri_drives), or −1
        ang_joint: wp.array(dtype=wp.int32)  # angle term a's revolute joint (rev_angles)
        ang_lim: wp.array(dtype=wp.int32)  # its limit (index of rlim_ids), or −1
        ang_drv: wp.array2d(dtype=wp.int32)  # up to two drives on it, or −1
        drive_mode: wp.array(dtype=wp.int32)
        kp: wp.array2d(dtype=dtype)
        kd: wp.array2d(dtype=dtype)
        fmax: wp.array2d(dtype=dtype)
        control: wp.array2d(dtype=dtype)
        unwrapped: wp.array2d(dtype=dtype)
        x_anchor: wp.array2d(dtype=dtype)
        clock: wp.array2d(dtype=wp.int64)  # (W, len(PHASES)) with phase_clock, else unused
        # lane groups: group c's joints, limits and drives, (kind WORK_*, index in its kind) for
        # it < work_n[c] (Solver.lane_work); unused with one group
        work_kind: wp.array2d(dtype=wp.int32)
        work_idx: wp.array2d(dtype=wp.int32)
        work_n: wp.array(dtype=wp.int32)

    @wp.struct
    class Bracket:
        """What opening and closing a world's step reads and writes besides Terms (bracket=True)."""

        qd: wp.array2d(dtype=vec12)
        q_prev: wp.array2d(dtype=vec12)
        q_hist: wp.array2d(dtype=vec12)
        qd_hist: wp.array2d(dtype=vec12)
        qd_hist2: wp.array2d(dtype=vec12)
        order3: wp.array2d(dtype=wp.int32)
        control_prev: wp.array2d(dtype=dtype)
        calm: wp.array(dtype=wp.int32)
        fresh: wp.array(dtype=wp.int32)
        c_ref: wp.array2d(dtype=dtype)
        s_ref: wp.array2d(dtype=dtype)
        x_hist: wp.array2d(dtype=dtype)
        coord: wp.array2d(dtype=dtype)
        velocity: wp.array2d(dtype=dtype)
        hold: wp.array(dtype=wp.int32)  # (W,): a world with hold[w] != 0 is not stepped (step_world)
        go: wp.array(dtype=wp.int32)  # (1,): 0 steps no world
        gravity: vec3
        h: dtype
        bdf2: int

    @wp.func
    def clock_now():
        if wp.static(phase_clock):
            return cycles()
        return wp.int64(0)

    @wp.func
    def tick(t: Terms, w: int, lane: int, k: int, c: wp.int64):
        """With phase_clock, add the cycles since c to phase k of world w; the cycle count now."""
        now = c
        if wp.static(phase_clock):
            now = cycles()
            if lane == 0:
                t.clock[w, k] = t.clock[w, k] + (now - c)
        return now

    # one term of the incremental potential each (kind k of assemble's loops): its energy, and per
    # derivs its gradient and Hessian added to scratch column s (of B) of g and H

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
                put_body(H, s, B, t.dof[b], qb, t.mass[w, b], t.mc[w, b], t.S[w, b], ks)
        return e_in + e_or

    @wp.func
    def point_term(q: wp.array2d(dtype=vec12), qr: int, w: int, s: int, B: int, derivs: int, t: Terms, g: Any,
                   H: Any, j: int, points: int):  # fmt: skip
        """A revolute (2 points) or fixed (4 points) joint j."""
        ej, gi, gj, uii, uij, ujj = point_eval_kron(q[qr, t.body_a[j]], q[qr, t.body_b[j]], t.pts_a, t.pts_b, w, j,
                                                    points, t.K[w, j], derivs)  # fmt: skip
        if derivs != 0:
            put_kron_pair(g, H, s, B, derivs, t.dof[t.body_a[j]], t.dof[t.body_b[j]], gi, gj, uii, uij, ujj)
        return ej

    @wp.func
    def drive_at(t: Terms, w: int, j: int, kd: int, x: dtype, hw: dtype):
        """(E, E′, E″) of drive kd on joint j at its coordinate x, inside ĥ² (drive.scalar from the
        joint's coordinate at the step's start, Terms.unwrapped): a drive in its joint's term."""
        ed, dd, ddd = drive_scalar(x, t.unwrapped[w, j], t.drive_mode[kd], t.control[w, kd], t.fmax[w, kd], t.kp[w, kd],
                                   t.kd[w, kd], t.x_anchor[w, j], hw)  # fmt: skip
        h2 = hw * hw
        return h2 * ed, h2 * dd, h2 * ddd

    @wp.func
    def prismatic_term(q: wp.array2d(dtype=vec12), qr: int, w: int, s: int, B: int, derivs: int, t: Terms, g: Any,
                       H: Any, kp: int):  # fmt: skip
        """Prismatic joint kp (of pri_ids) and, with pri_limits / pri_drives, its limit and a drive
        on it: their energies E(x) of the displacement x add E'∇x to the joint's gradient before its
        one put, and E''∇x∇xᵀ to its Hessian (limit.cubic, drive.scalar: the arithmetic of
        plim_term and drive_term on the same x and ∇x)."""
        j = t.pri_ids[kp]
        qi = q[qr, t.body_a[j]]
        qj = q[qr, t.body_b[j]]
        oi = t.dof[t.body_a[j]]
        oj = t.dof[t.body_b[j]]
        ca = t.c_a[w, j]
        cb = t.c_b[w, j]
        ta = t.t_a[w, j]
        # the Hessian goes straight into H (prismatic_hessian), so the evaluator builds none
        ej, gi, gj = prismatic_grad(qi, qj, ca, cb, ta, t.t_b[w, j], t.n_a[w, j], t.n_b[w, j], t.b_a[w, j],
                                    t.b_b[w, j], t.K[w, j], derivs)  # fmt: skip
        de = zero
        dde = zero
        gxi = vec12()
        gxj = vec12()
        if wp.static(pri_limits or pri_drives):
            x = pri_displacement(qi, qj, ca, cb, ta)
            if wp.static(pri_limits):
                kl = t.pri_lim[kp]
                if kl >= 0:
                    el, dl, ddl = plim_cubic(x, t.plim_lo[w, kl], t.plim_up[w, kl], t.plim_s[w, kl])
                    ej += el
                    de += dl
                    dde += ddl
            if wp.static(pri_drives):
                kd = t.pri_drv[kp]
                if kd >= 0:
                    ed, dd, ddd = drive_at(t, w, j, kd, x, t.h_step[w])
                    ej += ed
                    de += dd
                    dde += ddd
            if derivs != 0 and (de != zero or dde != zero):
                gxi, gxj = pri_displacement_grad(qi, qj, ca, cb, ta)
                gi = gi + de * gxi
                gj = gj + de * gxj
        if derivs != 0:
            put_grad(g, s, B, oi, gi)
            put_grad(g, s, B, oj, gj)
            if derivs == HESSIAN:
                prismatic_hessian(H, s, B, oi, oj, qi, qj, ca, cb, ta, t.t_b[w, j], t.n_a[w, j], t.n_b[w, j],
                                  t.b_a[w, j], t.b_b[w, j], t.K[w, j])  # fmt: skip
                if wp.static(pri_limits or pri_drives):
                    if dde != zero:
                        put_outer_pair(H, s, B, oi, oj, gxi, gxj, dde)
        return ej

    @wp.func
    def angle_term(q: wp.array2d(dtype=vec12), qr: int, w: int, s: int, B: int, derivs: int, t: Terms, g: Any,
                   H: Any, a: int, hw: dtype):  # fmt: skip
        """Angle term a (rev_angles): revolute joint j's limit, on x = θ0 + δ, and its drives, on
        x = x_prev + δ (δ = ΔΘ(q, q^{t−1}), the one increment both read), their E′ and E″ summed into
        one put of E′∇θ and E″∇θ∇θᵀ (revolute_limit.cubic, drive.scalar: the arithmetic of rlim_term
        and drive_term on the same angle); ∇θ only where they are not zero."""
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
        kl = t.ang_lim[a]
        if kl >= 0:
            el, d1, d2 = rlim_cubic(t.theta0[w, j] + dl, t.rlim_lo[w, kl], t.rlim_up[w, kl], t.rlim_s[w, kl])
            e += el
            de += d1
            dde += d2
        for slot in range(2):
            kd = t.ang_drv[a, slot]
            if kd >= 0:
                ed, d1, d2 = drive_at(t, w, j, kd, t.unwrapped[w, j] + dl, hw)
                e += ed
                de += d1
                dde += d2
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

    NF = N // 12  # free bodies (12 unknowns each, body k's from 12k: Model.dof)

    @wp.func
    def body_rows(q: wp.array2d(dtype=vec12), qr: int, w: int, s: int, B: int, derivs: int, t: Terms, g: Any,
                  H: Any, h2: dtype, first: int, stride: int):  # fmt: skip
        """The bodies' terms by rows: the lane evaluates the body of each of its rows ρ = first,
        first + stride, … and adds that row only; body k's energy to slot N + k of g (past the
        gradient) from the lane of its first row."""
        for rho in range(first, N, stride):
            k = rho // 12
            b = t.free[k]
            r = rho - 12 * k
            qb = q[qr, b]
            ks = t.kv[w, b] * h2
            e_in, e_or, f = body_grad(qb, t.q_tilde[w, b], t.mass[w, b], t.mc[w, b], t.S[w, b], ks, derivs)
            if derivs != 0:
                g[rho * B + s] = g[rho * B + s] + f[r]
                if derivs == HESSIAN:
                    Rp, ata = hessian_parts(qb)
                    body_row(H, s, B, 12 * k, r, qb, t.mass[w, b], t.mc[w, b], t.S[w, b], ks, Rp, ata)
            if r == 0:
                g[(N + k) * B + s] = e_in + e_or

    @wp.func
    def lane_bodies(q: wp.array2d(dtype=vec12), qr: int, w: int, s: int, B: int, derivs: int, t: Terms, g: Any,
                    H: Any, h2: dtype):  # fmt: skip
        """Lanes: the bodies' terms, each lane evaluating the body of each of its rows and adding that
        row only (12 lanes on one body at once, the bodies side by side, where every lane evaluating
        every body would take them one after another; body_rows).  Every lane then sums the bodies'
        energies from their slots in body order, the one-thread order.  Returns Σ_k E_k."""
        body_rows(q, qr, w, s, B, derivs, t, g, H, h2, lane_index(), LANES)
        block_sync()
        e = zero
        for k in range(NF):
            e += g[(N + k) * B + s]
        return e

    @wp.func
    def group_terms(q: wp.array2d(dtype=vec12), qr: int, w: int, s: int, B: int, derivs: int, t: Terms, g: Any,
                    H: Any, grp: int, hw: dtype, h2: dtype):  # fmt: skip
        """Lane groups: group grp's joints, limits and drives (its row of Terms.work, in order) into
        the group's copy of g and H (at s); their energy."""
        e = zero
        for it in range(t.work_n[grp]):
            kind = t.work_kind[grp, it]
            k = t.work_idx[grp, it]
            if wp.static(has_rev):
                if kind == WORK_REVOLUTE:
                    e += point_term(q, qr, w, s, B, derivs, t, g, H, t.rev_ids[k], 2)
            if wp.static(has_fix):
                if kind == WORK_FIXED:
                    e += point_term(q, qr, w, s, B, derivs, t, g, H, t.fix_ids[k], 4)
            if wp.static(has_pri):
                if kind == WORK_PRISMATIC:
                    e += prismatic_term(q, qr, w, s, B, derivs, t, g, H, k)
            if wp.static(has_rlim):
                if kind == WORK_REVOLUTE_LIMIT:
                    e += rlim_term(q, qr, w, s, B, derivs, t, g, H, k)
            if wp.static(has_plim):
                if kind == WORK_PRISMATIC_LIMIT:
                    e += plim_term(q, qr, w, s, B, derivs, t, g, H, k)
            if wp.static(has_drive):
                if kind == WORK_DRIVE:
                    e += drive_term(q, qr, w, s, B, derivs, t, g, H, t.drive_rest[k], hw, h2)
            if wp.static(rev_angles):
                if kind == WORK_ANGLE:
                    e += angle_term(q, qr, w, s, B, derivs, t, g, H, k, hw)
        return e

    @wp.func
    def assemble_groups(q: wp.array2d(dtype=vec12), qr: int, w: int, s: int, B: int, derivs: int, t: Terms, g: Any,
                        H: Any):  # fmt: skip
        """assemble with lane groups (B = 1): group c adds its terms to its copy of g and H at
        s + c·TRI (group 0: the bodies, body_rows, and its work), then, after a barrier, every lane
        sums its share of the copies' entries into copy 0 (g's for GRADIENT, H's too for HESSIAN,
        copies in group order) and the energy: the bodies' slots in body order, then the groups'
        (slot N + NF + c of copy 0) in group order.  A barrier after, so the sums are whole."""
        hw = t.h_step[w]
        h2 = hw * hw
        lane = lane_index()
        grp = lane // RL
        ck = clock_now()
        if grp == 0:
            body_rows(q, qr, w, s, B, derivs, t, g, H, h2, lane, RL)
            ck = tick(t, w, lane, 7, ck)
        e = group_terms(q, qr, w, s + grp * TRI, B, derivs, t, g, H, grp, hw, h2)
        if lane == grp * RL:
            g[(N + NF + grp) * B + s] = e
        block_sync()
        if derivs != 0:
            for i in range(lane, N, LANES):
                v = g[i * B + s]
                for c in range(1, G):
                    v += g[(i + c * TRI) * B + s]
                g[i * B + s] = v
            if derivs == HESSIAN:
                for p in range(lane, TRI, LANES):
                    v = H[p * B + s]
                    for c in range(1, G):
                        v += H[(p + c * TRI) * B + s]
                    H[p * B + s] = v
        e = zero
        for k in range(NF):
            e += g[(N + k) * B + s]
        for c in range(G):
            e += g[(N + NF + c) * B + s]
        block_sync()
        return e

    @wp.func
    def assemble(q: wp.array2d(dtype=vec12), qr: int, w: int, s: int, B: int, derivs: int, t: Terms, g: Any, H: Any):
        """Total incremental potential of world w at q[qr]; derivs GRADIENT adds its g, HESSIAN its g
        and H (to scratch column s of B).  Lanes: every lane evaluates every term (the same energy,
        in the same order, on each) and adds the entries of its own rows (own_from)."""
        if wp.static(G > 1):
            return assemble_groups(q, qr, w, s, B, derivs, t, g, H)
        e = zero
        hw = t.h_step[w]
        h2 = hw * hw
        ck = clock_now()  # the terms' cycles by kind (phase_clock)
        if wp.static(lanes):
            e = lane_bodies(q, qr, w, s, B, derivs, t, g, H, h2)
        else:
            for k in range(t.free.shape[0]):
                e += body_term(q, qr, w, s, B, derivs, t, g, H, k, h2)
        ck = tick(t, w, 0, 7, ck)
        if wp.static(has_rev):
            for k in range(t.rev_ids.shape[0]):
                e += point_term(q, qr, w, s, B, derivs, t, g, H, t.rev_ids[k], 2)
            ck = tick(t, w, 0, 8, ck)
        if wp.static(has_fix):
            for k in range(t.fix_ids.shape[0]):
                e += point_term(q, qr, w, s, B, derivs, t, g, H, t.fix_ids[k], 4)
            ck = tick(t, w, 0, 9, ck)
        if wp.static(has_pri):
            for k in range(t.pri_ids.shape[0]):
                e += prismatic_term(q, qr, w, s, B, derivs, t, g, H, k)
            ck = tick(t, w, 0, 10, ck)
        if wp.static(has_rlim):
            for k in range(t.rlim_ids.shape[0]):
                e += rlim_term(q, qr, w, s, B, derivs, t, g, H, k)
        if wp.static(has_plim):
            for k in range(t.plim_ids.shape[0]):
                e += plim_term(q, qr, w, s, B, derivs, t, g, H, k)
        if wp.static(rev_angles):
            for k in range(t.ang_joint.shape[0]):
                e += angle_term(q, qr, w, s, B, derivs, t, g, H, k, hw)
        ck = tick(t, w, 0, 11, ck)
        if wp.static(has_drive):
            for k in range(t.drive_rest.shape[0]):
                e += drive_term(q, qr, w, s, B, derivs, t, g, H, t.drive_rest[k], hw, h2)
            ck = tick(t, w, 0, 12, ck)
        return e

    @wp.func
    def whole_step(e0: dtype, gdq: dtype, dmax: dtype, floor: dtype, noise: dtype, chord: int):
        """(skip, done): take the Newton step whole, without a line search, when it is under the
        tolerance or when its predicted decrease −gᵀΔq is below what the energy's float rounding
        can resolve (the search could only halve it on noise; ``noise``: solver_kernels.energy_noise);
        done: the solve ends with it.  A step from a reused factor (chord) converges linearly: only
        one under the tolerance ends it."""
        unresolved = -gdq <= dtype(1600.0) * EPS * wp.abs(e0) or -gdq <= noise
        # within 10x the noise floor the step is taken whole: in float32 the energy's rounding there
        # exceeds the step's decrease (a joint's energy K/2‖Δx‖² at ‖Δx‖ ~ 1e-6 m is computed from
        # positions rounded to ~6e-8 m), and a search halves good steps on noise (measured: double
        # pendulums at dt 0.005 crawling at α = 1/32 where float64 takes α = 1 and converges in 2)
        skip = dmax < dtype(10.0) * floor or unresolved
        done = dmax < floor or (unresolved and dmax < dtype(1000.0) * floor and chord <= 0)
        return wp.where(skip, 1, 0), wp.where(done, 1, 0)

    @wp.func
    def armijo(e0: dtype, e1: dtype, alpha: dtype, gdq: dtype):
        """(accepted, stalled) for the trial energy e1 at step α: Armijo's test with rounding-level
        slack; stalled when the decrease is below what the precision resolves."""
        noise = dtype(16.0) * EPS * (wp.abs(e0) + wp.abs(e1))
        if e1 <= e0 + dtype(1.0e-4) * alpha * gdq + noise and wp.isfinite(e1):
            return 1, wp.where(e0 - e1 <= noise, 1, 0)
        return 0, 0

    @wp.func
    def search(q: wp.array2d(dtype=vec12), q_trial: wp.array2d(dtype=vec12), t: Terms, step: Any, g: Any, H: Any,
               w: int, row: int, s: int, B: int, e0: dtype, gdq: dtype, skip: int, done: int, chord: int,
               max_line_search: int, lane: int):  # fmt: skip
        """(accepted, stalled, α) for the step: taken whole when ``skip`` (whole_step); a reused
        factor's step tried at α = 1 only; else Armijo backtracking on the world's own energy.  The
        trial points go to row ``row`` of q_trial; s, B as in assemble, lane as in trial."""
        c = clock_now()
        alpha = one
        accepted = int(0)
        stalled = int(0)
        if wp.static(compact):
            # one trial and one energy in the code (a loop of tries, not a first try and a loop):
            # each inlined copy of assemble's energy costs ~28 KB of a cart-pole kernel's SASS
            tries = wp.where(skip != 0 or chord > 0, 1, max_line_search)
            for _ls in range(tries):
                trial(q, q_trial, t, step, w, row, s, B, alpha, lane)
                c = tick(t, w, lane, 6, c)
                if skip != 0:
                    accepted = 1
                    stalled = done
                    break
                accepted, stalled = armijo(e0, assemble(q_trial, row, w, s, B, ENERGY, t, g, H), alpha, gdq)
                c = tick(t, w, lane, 5, c)
                if accepted != 0:
                    break
                alpha = alpha * half  # (a rejected reused-factor step's α is unused: chord_step retries)
                if wp.static(lanes):
                    # the next trial moves q_trial: every lane's energy must have read it first
                    # (assemble ends on the joints' terms, with no barrier; without this one a
                    # fast lane's next trial raced a slow lane's energy: a SliderCrank-v0 world's
                    # lanes took different steps and failed, tests/test_graph.py)
                    block_sync()
        else:
            trial(q, q_trial, t, step, w, row, s, B, alpha, lane)
            c = tick(t, w, lane, 6, c)
            if skip != 0:
                accepted = 1
                stalled = done
            elif chord > 0:
                accepted, stalled = armijo(e0, assemble(q_trial, row, w, s, B, ENERGY, t, g, H), one, gdq)
                c = tick(t, w, lane, 5, c)
            else:
                for ls in range(max_line_search):
                    if ls > 0:
                        trial(q, q_trial, t, step, w, row, s, B, alpha, lane)
                        c = tick(t, w, lane, 6, c)
                    accepted, stalled = armijo(e0, assemble(q_trial, row, w, s, B, ENERGY, t, g, H), alpha, gdq)
                    c = tick(t, w, lane, 5, c)
                    if accepted != 0:
                        break
                    alpha = alpha * half
        return accepted, stalled, alpha

    @wp.func
    def chord_step(chord: int, reuse: int, accepted: int, alpha: dtype, dmax: dtype, d_prev: dtype):
        """(retry, chord) after an iteration; chord 1: the next iteration reuses the factor, 0: it
        factors, −1: it factors and the step reuses no factor again.  A step from a reused factor is
        tried at α = 1 only: rejected, it is not taken and the next iteration refactors at the same q
        (retry 1), and the rest of the step refactors every iteration (where a reused factor fails,
        the Hessian changes fast: alternating the two doubled a hard step's iterations, 13 → 22 on a
        float32 double pendulum at dt 0.05).  The factor is reused after a full step taken whole,
        and kept while the reused steps shrink at least 8× an iteration (they converge linearly, at
        the rate the Hessian has changed; a slow rate would leave the solve's error near the
        tolerance, where Newton's leaves it far below); a reused step that shrinks less also ends
        reuse for the step (where float32's noise makes steps ~1e-3 that are taken whole, refactor
        and reuse alternated forever: 1,024 double pendulums at dt 0.05, 6 world-steps reached the 50-iteration
        cap, 0 after)."""
        if chord > 0:
            if accepted == 0:
                return 1, -1
            return 0, wp.where(dmax <= dtype(0.125) * d_prev, 1, -1)
        if chord < 0:
            return 0, -1
        return 0, wp.where(accepted != 0 and alpha == one, reuse, 0)

    @wp.func
    def end_iteration(q: wp.array2d(dtype=vec12), q_trial: wp.array2d(dtype=vec12), w: int, row: int, accepted: int,
                      stalled: int, dmax: dtype, floor: dtype, converged: wp.array(dtype=wp.int32),
                      lane: int):  # fmt: skip
        """Take the accepted trial point (row of q_trial) as world w's q; 1 when its solve is over.
        A search that ran out takes no step: converged if the step was already near the tolerance.
        (Steps within 10x the noise floor are taken whole, see whole_step.)  Lane-split: each lane
        copies its bodies, lane 0 writes the flag."""
        if accepted == 0:
            if dmax < dtype(1000.0) * floor and lane == 0:
                converged[w] = 1
            return 1
        for b in range(lane, q.shape[1], LANES):
            q[w, b] = q_trial[row, b]
        if dmax < floor or stalled != 0:
            if lane == 0:
                converged[w] = 1
            return 1
        return 0

    @wp.func
    def take_step(q: wp.array2d(dtype=vec12), q_trial: wp.array2d(dtype=vec12), t: Terms, step: Any, g: Any, H: Any,
                  w: int, row: int, s: int, B: int, e0: dtype, gdq: dtype, dmax: dtype, g_abs: dtype, threshold: dtype, chord: int,
                  reuse: int, d_prev: dtype, max_line_search: int, converged: wp.array(dtype=wp.int32),
                  lane: int):  # fmt: skip
        """Everything after a Newton direction (both layouts): the stop test, the line search, the
        choice to reuse the factor next, and the update of q.  Returns (1 when the solve is over,
        chord for the next iteration)."""
        floor, rounding = noise_floor(q, w, threshold)
        # a Newton step under quadratic_stop × q's rounding ends the solve if accepted at α = 1
        quad = chord <= 0 and dmax < QUAD * rounding
        skip, done = whole_step(e0, gdq, dmax, floor, energy_noise(rounding, g_abs), chord)
        accepted, stalled, alpha = search(q, q_trial, t, step, g, H, w, row, s, B, e0, gdq, skip, done, chord,
                                          max_line_search, lane)  # fmt: skip
        if quad and accepted != 0 and alpha == one:
            stalled = 1  # taken whole or by Armijo: Newton's next step would be rounding (quadratic_stop)
        retry, chord_next = chord_step(chord, reuse, accepted, alpha, dmax, d_prev)
        stop = int(0)
        if retry == 0:
            stop = end_iteration(q, q_trial, w, row, accepted, stalled, dmax, floor, converged, lane)
        if wp.static(lanes):
            block_sync()  # q is read whole by the next iteration
        return stop, chord_next

    @wp.func
    def solve_world(q: wp.array2d(dtype=vec12), q_trial: wp.array2d(dtype=vec12), t: Terms, g: wp.array(dtype=dtype),
                    H: wp.array(dtype=dtype), dq: wp.array(dtype=dtype), w: int, s: int, T: int, row: int, threshold: dtype,
                    max_iterations: int, max_line_search: int, reuse: int, status: wp.array(dtype=wp.int32),
                    iterations: wp.array(dtype=wp.int32), factorizations: wp.array(dtype=wp.int32),
                    converged: wp.array(dtype=wp.int32), lane: int):  # fmt: skip
        """World w's whole Newton solve, in scratch column s (of T) of the flat g, H, dq and row
        ``row`` of q_trial; lane ``lane`` of LANES (one thread per world: 0 of 1).

        With ``reuse``, an iteration after a full step (α = 1) keeps the Cholesky factor it left in H
        and solves only the new gradient against it (a simplified-Newton step; see ``chord_step``).
        Lane-split, every lane takes every branch (each decides from the same sums in the same
        order) and lane 0 alone writes the world's counters."""
        if lane == 0:
            iterations[w] = 0
            factorizations[w] = 0
            converged[w] = 0
        if status[w] != OK:
            return 0
        chord = int(0)  # 1: H holds the factor of an earlier iteration, reused for this one (chord_step)
        d_prev = zero
        nfact = int(0)
        its = int(0)  # Newton iterations (solves) so far
        for it in range(max_iterations):
            c = clock_now()
            if wp.static(G > 1):  # every group's copy (lanes: T = 1)
                for cp in range(G):
                    for i in range(lane, N, LANES):
                        g[s + cp * TRI + i] = zero
                    if chord <= 0:
                        for p in range(lane, TRI, LANES):
                            H[s + cp * TRI + p] = zero
            else:
                for i in range(lane, N, LANES):
                    g[i * T + s] = zero
                    if chord <= 0:
                        j0 = int(0)
                        if wp.static(envelope):
                            j0 = t.first[i]
                        p = (hrow(i) + j0) * T + s
                        for j in range(j0, i + 1):
                            H[p] = zero
                            p += T
            if wp.static(lanes):
                block_sync()
            c = tick(t, w, lane, 0, c)
            e0 = zero
            ok = int(0)
            gdq = zero
            dmax = zero
            g_abs = zero
            if wp.static(compact):
                # one call with the derivatives chosen at run time: a second inlined assemble
                # (gradient only) would add ~54 KB of code
                e0 = assemble(q, w, w, s, T, wp.where(chord > 0, GRADIENT, HESSIAN), t, g, H)
            elif chord > 0:
                e0 = assemble(q, w, w, s, T, GRADIENT, t, g, H)
            else:
                e0 = assemble(q, w, w, s, T, HESSIAN, t, g, H)
            c = tick(t, w, lane, 1, c)
            if chord <= 0:
                nfact += 1
            if wp.static(warp_regs and G == 1):
                block_sync()  # the factor reads every lane's rows
                ok = regs_ldl_solve(H, g, dq, lane, wp.where(chord <= 0, 1, 0))
                c = tick(t, w, lane, 2, c)  # (the factor and the substitutions)
                if ok != 0:
                    ok, gdq, dmax, g_abs = reductions(g, dq, s, N, 1)
                c = tick(t, w, lane, 3, c)
            elif wp.static(warp_regs):
                # lane groups: the first group's warp factors and solves (assemble_groups ended with a
                # barrier), and passes ok to the others through slot N + NF + G of g
                if lane < 32:
                    ok = regs_ldl_solve(H, g, dq, lane, wp.where(chord <= 0, 1, 0))
                    if lane == 0:
                        g[s + N + NF + G] = wp.where(ok != 0, one, zero)
                block_sync()
                ok = wp.where(g[s + N + NF + G] != zero, 1, 0)
                c = tick(t, w, lane, 2, c)
                if ok != 0:
                    ok, gdq, dmax, g_abs = reductions(g, dq, s, N, 1)
                c = tick(t, w, lane, 3, c)
            elif wp.static(lanes):
                block_sync()  # the factor and the solves read every lane's rows
                ok = 1
                if chord <= 0:
                    ok = ldl_lanes(H, s, lane)
                c = tick(t, w, lane, 2, c)
                if ok != 0:
                    ok, gdq, dmax, g_abs = solve_lanes(H, g, dq, s, lane)
                c = tick(t, w, lane, 3, c)
            elif chord > 0:
                ok, gdq, dmax, g_abs = factored_solve(H, g, dq, s, N, T, t.first)
                c = tick(t, w, lane, 3, c)
            else:
                ok, gdq, dmax, g_abs = cholesky_solve(H, g, dq, s, N, T, t.first)
                c = tick(t, w, lane, 2, c)
            if lane == 0:
                factorizations[w] = nfact
            if ok == 0:
                if lane == 0:
                    status[w] = FAILED
                return 0
            its += 1
            if lane == 0:
                iterations[w] = its
            stop, chord = take_step(q, q_trial, t, dq, g, H, w, row, s, T, e0, gdq, dmax, g_abs, threshold, chord, reuse,
                                    d_prev, max_line_search, converged, lane)  # fmt: skip
            c = tick(t, w, lane, 4, c)
            if stop != 0:
                return 0
            d_prev = dmax
        return 0

    @wp.func
    def open_world(q: wp.array2d(dtype=vec12), t: Terms, k: Bracket, status: wp.array(dtype=wp.int32), w: int,
                   lane: int):  # fmt: skip
        """Solver._open's kernels for world w (bracket=True): open_step, begin_step and predict, a body
        or joint per lane (all of them for one thread per world), with a barrier after each: the
        references read q before the initial guess moves it, and the prediction reads the world's
        status and step."""
        nb = q.shape[1]
        c = clock_now()
        # fresh: the world was set since its last step (a reset, a state set), whose close then did
        # not leave the joints' references for this step (close_joint); the close clears it
        fresh = k.fresh[w]
        for b in range(lane, nb, LANES):
            open_body(q, k.qd, status, k.fresh, k.h, k.bdf2, t.h_step, t.control, k.control_prev, k.calm, w, b, 0)
        if wp.static(lanes):
            block_sync()
        c = tick(t, w, lane, 15, c)
        if fresh != 0:
            for j in range(lane, t.joint_kind.shape[0], LANES):
                begin_joint(q, t.body_a, t.body_b, t.joint_kind, t.n_a, t.b_a, t.n_b, t.b_b, k.c_ref, k.s_ref, t.theta0,
                            t.c_prev, t.s_prev, t.unwrapped, k.x_hist, t.h_step, k.h, t.x_anchor, w, j)  # fmt: skip
            if wp.static(lanes):
                block_sync()
        c = tick(t, w, lane, 16, c)
        for b in range(lane, nb, LANES):
            predict_body(q, k.qd, k.q_prev, k.q_hist, k.qd_hist, k.qd_hist2, k.order3, k.calm, t.q_tilde, t.dof, t.mass,
                         t.mc, k.gravity, k.h, t.h_step, status, w, b)  # fmt: skip
        if wp.static(lanes):
            block_sync()
        tick(t, w, lane, 17, c)

    @wp.func
    def close_world(q: wp.array2d(dtype=vec12), t: Terms, k: Bracket, status: wp.array(dtype=wp.int32), w: int,
                    lane: int):  # fmt: skip
        """Solver._close's kernels for world w (bracket=True): finalize a body per lane, then, once
        the world's q is final, its joints' coordinates (a healthy world's only)."""
        if wp.static(lanes):
            block_sync()
        c = clock_now()
        for b in range(lane, q.shape[1], LANES):
            finalize_body(q, k.q_prev, k.qd, k.q_hist, k.qd_hist, k.qd_hist2, k.order3, t.dof, k.h, t.h_step, status, w,
                          b)  # fmt: skip
        if wp.static(lanes):
            block_sync()
        c = tick(t, w, lane, 18, c)
        if status[w] == OK:
            for j in range(lane, t.joint_kind.shape[0], LANES):
                close_joint(q, k.q_prev, t.body_a, t.body_b, t.joint_kind, t.c_a, t.c_b, t.t_a, t.n_a, t.b_a, t.n_b,
                            t.b_b, t.theta0, t.c_prev, t.s_prev, k.c_ref, k.s_ref, k.h, k.bdf2, k.coord, k.velocity,
                            t.unwrapped, k.x_hist, t.x_anchor, w, j)  # fmt: skip
        if lane == 0:
            k.fresh[w] = 0  # (read by this step's open only, before its first barrier)
        tick(t, w, lane, 19, c)  # (lane 0's joints: no barrier follows them)

    @wp.func
    def step_world(q: wp.array2d(dtype=vec12), q_trial: wp.array2d(dtype=vec12), t: Terms, k: Bracket,
                   g: wp.array(dtype=dtype), H: wp.array(dtype=dtype), dq: wp.array(dtype=dtype), w: int, s: int, T: int,
                   row: int, threshold: dtype, max_iterations: int, max_line_search: int, reuse: int,
                   status: wp.array(dtype=wp.int32), iterations: wp.array(dtype=wp.int32),
                   factorizations: wp.array(dtype=wp.int32), converged: wp.array(dtype=wp.int32), lane: int):  # fmt: skip
        """World w's step: its solve (solve_world), opened and closed here when ``bracket``.  Built
        with ``hold`` (and bracket), a world held (k.hold[w] != 0) or a batch refused (k.go[0] == 0)
        is not stepped: no row of the world is read or written, so that another kernel may rewrite
        it meanwhile (the vector env's autoreset, on a second stream), and its Newton counters keep
        their last values."""
        if wp.static(bracket and hold):
            if k.go[0] == 0 or k.hold[w] != 0:
                return
        if wp.static(bracket):
            c = clock_now()
            open_world(q, t, k, status, w, lane)
            tick(t, w, lane, 13, c)
        solve_world(q, q_trial, t, g, H, dq, w, s, T, row, threshold, max_iterations, max_line_search, reuse, status,
                    iterations, factorizations, converged, lane)  # fmt: skip
        if wp.static(bracket):
            c = clock_now()
            close_world(q, t, k, status, w, lane)
            tick(t, w, lane, 14, c)

    @wp.kernel(**options)
    def assemble_system(q: wp.array2d(dtype=vec12), t: Terms, derivs: int, g: wp.array(dtype=dtype),
                        H: wp.array(dtype=dtype), E: wp.array(dtype=dtype)):  # fmt: skip
        """The incremental potential of world w and, per ``derivs``, its gradient and Hessian (lower
        triangle) as the fused step assembles them, into scratch column w of the zeroed flat g, H
        (one column per world): for checking the fused assembly against the staged one.  Lanes:
        launched as blocks of LANES threads, block w on world w, each lane on its own rows, world
        w's g and H (packed, and the groups' copies) contiguous from w·G·TRI, as newton_lanes'
        on the CPU."""
        c = wp.tid()
        w = c // LANES
        if wp.static(lanes):
            e = assemble(q, w, w, w * G * TRI, 1, derivs, t, g, H)
        else:
            e = assemble(q, w, w, w, q.shape[0], derivs, t, g, H)
        if c % LANES == 0:
            E[w] = e

    SIZE = 4 if dtype == wp.float32 else 8
    # a thread per world with its g, H, Δq in the block's shared memory (scratch="shared", CUDA): the
    # factor's and solves' ~n³/6 dependent loads then wait ~30 cycles each instead of an L1 miss's
    # trip to L2 (131,072 worlds' columns exceed L1); H packed, so a block of 32 float32 threads of
    # 24 unknowns fits the 48 KB of static shared memory (44.5 KB)
    in_smem = packed and cuda and not lanes
    if in_smem:
        one_count = (TRI + 2 * N) * block
        one_scratch = shared_array(dtype, one_count)

    if not lanes:

        @wp.kernel(**options)
        def newton(
            q: wp.array2d(dtype=vec12), q_trial: wp.array2d(dtype=vec12), t: Terms, k: Bracket,
            g: wp.array(dtype=dtype), H: wp.array(dtype=dtype), dq: wp.array(dtype=dtype),
            s0: int, Tw: int, wa: int, wb: int, threshold: dtype, max_iterations: int, max_line_search: int, reuse: int,
            status: wp.array(dtype=wp.int32), iterations: wp.array(dtype=wp.int32),
            factorizations: wp.array(dtype=wp.int32), converged: wp.array(dtype=wp.int32),
        ):  # fmt: skip
            """The launch's Tw threads solve worlds wa … wb − 1, thread c the worlds wa + c, wa + c + Tw,
            …: a thread's scratch is reused world after world, so it stays in cache however many worlds
            there are.  On a GPU one launch runs every world; on the CPU ranges of threads and worlds run
            as concurrent launches, each with its own scratch (g, H, dq: Tw columns) and its own run of
            worlds, so they share no cache lines; s0 + c is the thread's row of q_trial.  (One step a
            launch: a loop of steps around step_world cost 12% at 16,384 and 131,072 cart-poles on an
            H100, results/steps_per_launch_h100.md.)"""
            c = wp.tid()
            s = c + s0
            if wp.static(in_smem):
                col = c % block  # the thread's column of its block's scratch
                base = one_scratch()
                Hs = wp.array(ptr=base, shape=(TRI * block,), dtype=dtype)
                gs = wp.array(ptr=base + wp.uint64(TRI * block * SIZE), shape=(N * block,), dtype=dtype)
                ds = wp.array(ptr=base + wp.uint64((TRI + N) * block * SIZE), shape=(N * block,), dtype=dtype)
                for w in range(wa + c, wb, Tw):
                    step_world(q, q_trial, t, k, gs, Hs, ds, w, col, block, s, threshold, max_iterations,
                               max_line_search, reuse, status, iterations, factorizations, converged, 0)  # fmt: skip
            else:
                for w in range(wa + c, wb, Tw):
                    step_world(q, q_trial, t, k, g, H, dq, w, c, Tw, s, threshold, max_iterations, max_line_search,
                               reuse, status, iterations, factorizations, converged, 0)  # fmt: skip

        return newton, Terms, Bracket, assemble_system

    @wp.func
    def ldl_lanes(H: wp.array(dtype=dtype), s: int, lane: int):
        """H = L D Lᵀ in place (H packed from s), right-looking, lane l on its rows i ≡ l (mod LANES):
        at column j every lane reads D_j = H[j, j] and updates its rows below it, H[i, k] −=
        H[i, j] H[k, j] / D_j for j < k ≤ i (four k at a time: independent loads), which reads
        column j and writes right of it only: one barrier a column.  Left in H: D_j L_ij below the
        diagonal (no pass to scale it) and 1/D_j on it, stored a column late by the row's owner,
        once no lane reads D_j.  0 when H is not positive definite (the same test of the same D_j
        on every lane)."""
        inv = zero
        for j in range(N):
            dj = H[s + hrow(j) + j]
            if not (dj > zero) or not wp.isfinite(dj):
                return 0
            if j > 0 and (j - 1) % LANES == lane:
                H[s + hrow(j - 1) + j - 1] = inv
            inv = one / dj
            for i in range(j + 1 + own_all(j + 1, lane), N, LANES):
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
        Then every lane forms (ok, gᵀΔq, ‖Δq‖∞, ‖g‖₁)."""
        for i in range(lane, N, LANES):
            dq[s + i] = -g[s + i]
        block_sync()
        for j in range(N):
            tj = dq[s + j] * H[s + hrow(j) + j]  # y_j / D_j: L_ij y_j = H[i, j] y_j / D_j
            for i in range(j + 1 + own_all(j + 1, lane), N, LANES):
                dq[s + i] = dq[s + i] - H[s + hrow(i) + j] * tj
            block_sync()
        for kk in range(N):
            k = N - 1 - kk
            xk = dq[s + k] * H[s + hrow(k) + k]
            rk = s + hrow(k)
            for i in range(lane, k, LANES):
                dq[s + i] = dq[s + i] - H[rk + i] * xk
            block_sync()
            if k % LANES == lane:
                dq[s + k] = xk
        block_sync()
        return reductions(g, dq, s, N, 1)

    # the world's g, H (packed) and Δq in its block's shared memory on CUDA (1.4 KB for 24 unknowns
    # in float32): every lane reads every row in the factor and the solves
    # with lane groups, G copies of H and of g (copy c from c·TRI; copy 0's g holds past N the
    # bodies' energies, the groups' energies and the factor's ok, assemble_groups and solve_world)
    GLEN = N + NF if G == 1 else (G - 1) * TRI + N + NF + G + 1
    WORDS = lanes_scratch_words(N, G)  # a world's scratch words
    if lanes and cuda:
        lanes_scratch = shared_array(dtype, WPB * WORDS)

    @wp.kernel(**options)
    def newton_lanes(
        q: wp.array2d(dtype=vec12), q_trial: wp.array2d(dtype=vec12), t: Terms, k: Bracket,
        g: wp.array(dtype=dtype), H: wp.array(dtype=dtype), dq: wp.array(dtype=dtype),
        threshold: dtype, max_iterations: int, max_line_search: int, reuse: int,
        status: wp.array(dtype=wp.int32), iterations: wp.array(dtype=wp.int32),
        factorizations: wp.array(dtype=wp.int32), converged: wp.array(dtype=wp.int32), steps: int,
    ):  # fmt: skip
        """Block w (of LANES lanes; on CUDA with per_block > 1, the block of worlds w − w % WPB …,
        LANES lanes each) solves world w, its g, H (packed; G copies each) and Δq in the block's
        shared memory on CUDA (its slot w % WPB), else contiguous in the global scratch from
        w·G·TRI (G·TRI words a world in each of g, H and dq).  ``steps`` > 1 (with ``bracket`` only): the world's
        next steps follow in the same launch (worlds are independent; the controls stay), its
        state, model and controls then read from the SM's L1 cache instead of L2, with no launch
        between steps."""
        c = wp.tid()
        w = c // LANES
        if wp.static(lanes and cuda):
            base = lanes_scratch() + wp.uint64((w % WPB) * WORDS * SIZE)  # the world's slot of its block's
            Hs = wp.array(ptr=base, shape=(G * TRI,), dtype=dtype)
            gs = wp.array(ptr=base + wp.uint64(G * TRI * SIZE), shape=(GLEN,), dtype=dtype)
            ds = wp.array(ptr=base + wp.uint64((G * TRI + GLEN) * SIZE), shape=(N,), dtype=dtype)
            for st in range(steps):
                if st > 0:
                    if wp.static(LOCKSTEP):
                        whole_block_sync()  # the whole block's: also the world's (as below)
                    else:
                        block_sync()  # the last step's coordinates and histories, by other lanes
                step_world(q, q_trial, t, k, gs, Hs, ds, w, 0, 1, w, threshold, max_iterations, max_line_search,
                           reuse, status, iterations, factorizations, converged, c - w * LANES)  # fmt: skip
        else:
            for st in range(steps):
                if st > 0:
                    block_sync()
                step_world(q, q_trial, t, k, g, H, dq, w, w * G * TRI, 1, w, threshold, max_iterations,
                           max_line_search, reuse, status, iterations, factorizations, converged,
                           c - w * LANES)  # fmt: skip

    return newton_lanes, Terms, Bracket, assemble_system
