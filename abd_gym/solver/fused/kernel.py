"""The fused kernels, composed from the stage modules, and ``fused_kernel``, their cached factory:
``newton`` (a thread per world, scratch "global" or "shared"), ``newton_lanes`` (a block of
lanes per world) and ``assemble_system`` (the fused assembly alone, for checking it against the
staged one)."""
import functools

import warp as wp

from .bracket import world_step
from .clock import PHASE_CLOSE, PHASE_OPEN, clock
from .layout import KernelSpec, block_sync as whole_block_sync, indexing, shared_array, tile_address
from .assembly import assembly
from .newton import newton as newton_funcs
from .structs import structs
from ...core.warp_ops import ops

# loops stay loops: unrolling the 12×12 block loops of every inlined evaluator multiplies the
# code size, and with it NVRTC's compile time (minutes), for little or no gain in the step's
# speed
options = dict(module="unique", module_options={"max_unroll": 1})


@functools.lru_cache(maxsize=None)
def assembly_kernel(spec: KernelSpec):
    """``assemble_system``: the fused assembly of every world, as a kernel of its own."""
    dtype, TRI, LANES, G, lanes = spec.dtype, spec.TRI, spec.LANES, spec.G, spec.lanes
    vec12 = ops(dtype).vec12
    Terms = structs(dtype).Terms
    assemble = assembly(spec).assemble

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

    return assemble_system


@functools.lru_cache(maxsize=None)
def thread_kernel(spec: KernelSpec):
    """``newton``: a thread per world (scratch "global" or "shared")."""
    dtype, N, TRI, block, bracket = spec.dtype, spec.N, spec.TRI, spec.block, spec.bracket
    vec12 = ops(dtype).vec12
    Terms, Bracket = structs(dtype).Terms, structs(dtype).Bracket
    ws = world_step(spec)
    held, open_world, close_world = ws.held, ws.open_world, ws.close_world
    nt = newton_funcs(spec)
    open_solve, iterate = nt.open_solve, nt.iterate
    clock_now, tick = clock(spec).clock_now, clock(spec).tick
    zero = dtype(0.0)
    SIZE = 4 if dtype == wp.float32 else 8
    # a thread per world with its g, H, Δq in the block's shared memory (scratch="shared", CUDA): the
    # factor's and solves' ~n³/6 dependent loads then wait ~30 cycles each instead of an L1 miss's
    # trip to L2 (131,072 worlds' columns exceed L1); H packed, so a block of 32 float32 threads of
    # 24 unknowns fits in 44.5 KB; with ``band`` only H's block band.  A shared tile, not a static
    # array: Warp gives the kernel dynamic shared memory past 48 KB (plan.default_block_dim_shared)
    in_smem = spec.in_smem
    if in_smem:
        one_count = (TRI + 2 * N) * block
        one_address = tile_address(dtype, one_count)

    @wp.func
    def run_worlds(q: wp.array2d(dtype=vec12), q_trial: wp.array2d(dtype=vec12), t: Terms, k: Bracket,
                   g: wp.array(dtype=dtype), H: wp.array(dtype=dtype), dq: wp.array(dtype=dtype), col: int, B: int,
                   row: int, c: int, Tw: int, wa: int, wb: int, threshold: dtype, max_iterations: int,
                   max_line_search: int, reuse: int, status: wp.array(dtype=wp.int32),
                   iterations: wp.array(dtype=wp.int32), factorizations: wp.array(dtype=wp.int32),
                   converged: wp.array(dtype=wp.int32), queue: wp.array(dtype=wp.int32)):  # fmt: skip
        """Thread c's worlds, one Newton iteration a pass: world wa + c first, then those it claims
        from the launch's queue (queue[0]: worlds wa + Tw, wa + Tw + 1, … taken so far) whenever its
        world's solve is over, until none is left.  A GPU warp runs its threads' passes together: a
        thread whose world has converged takes the next world while a slower world of the warp
        iterates on, instead of idling until that world converges.  A claim returns only once the
        counter has moved, so when the last thread out (queue[1] counts them) empties the queue for
        the next launch, every claim of this one is done."""
        w = wa + c
        fresh = int(1)  # 1: w is a world this thread has not opened yet
        skip = int(0)
        solving = int(0)
        chord = int(0)
        d_prev = zero
        nfact = int(0)
        its = int(0)
        cap = int(0)
        spare = int(0)
        exact = int(0)
        while w < wb:
            if fresh != 0:
                fresh = 0
                solving = 0
                skip = held(k, w)
                if skip == 0:
                    if wp.static(bracket):
                        ck = clock_now()
                        open_world(q, t, k, status, w, 0)
                        tick(t, w, 0, PHASE_OPEN, ck)
                    solving, chord, d_prev, nfact, its, cap, spare, exact = open_solve(
                        t, w, max_iterations, reuse, status, iterations, factorizations, converged, 0)  # fmt: skip
            over = int(1)
            if solving != 0:
                over, chord, d_prev, nfact, its, cap, spare, exact = iterate(
                    q, q_trial, t, g, H, dq, w, col, B, row, threshold, max_iterations, max_line_search, reuse,
                    status, iterations, factorizations, converged, 0, chord, d_prev, nfact, its, cap, spare,
                    exact)  # fmt: skip
            if over != 0:
                if wp.static(bracket):
                    if skip == 0:
                        ck = clock_now()
                        close_world(q, t, k, status, w, 0)
                        tick(t, w, 0, PHASE_CLOSE, ck)
                w = wa + Tw + wp.atomic_add(queue, 0, 1)
                fresh = 1
        if wp.atomic_add(queue, 1, 1) == Tw - 1:
            queue[0] = 0
            queue[1] = 0

    @wp.kernel(**options)
    def newton(
        q: wp.array2d(dtype=vec12), q_trial: wp.array2d(dtype=vec12), t: Terms, k: Bracket,
        g: wp.array(dtype=dtype), H: wp.array(dtype=dtype), dq: wp.array(dtype=dtype),
        s0: int, Tw: int, wa: int, wb: int, threshold: dtype, max_iterations: int, max_line_search: int, reuse: int,
        status: wp.array(dtype=wp.int32), iterations: wp.array(dtype=wp.int32),
        factorizations: wp.array(dtype=wp.int32), converged: wp.array(dtype=wp.int32), queue: wp.array(dtype=wp.int32),
    ):  # fmt: skip
        """The launch's Tw threads solve worlds wa … wb − 1 (run_worlds), each a world at a time: a
        thread's scratch is reused world after world, so it stays in cache however many worlds there
        are.  On the CPU ranges of threads and worlds run as concurrent launches, each with its own
        scratch (g, H, dq: Tw columns), its own run of worlds and its own queue (2 words); s0 + c is
        the thread's row of q_trial.  (One step a launch: a loop of steps around a world's step
        is slower at large batches.)"""
        c = wp.tid()
        s = c + s0
        if wp.static(in_smem):
            base = one_address(wp.tile_empty(shape=(one_count,), dtype=dtype, storage="shared"))
            Hs = wp.array(ptr=base, shape=(TRI * block,), dtype=dtype)
            gs = wp.array(ptr=base + wp.uint64(TRI * block * SIZE), shape=(N * block,), dtype=dtype)
            ds = wp.array(ptr=base + wp.uint64((TRI + N) * block * SIZE), shape=(N * block,), dtype=dtype)
            # the thread's column c % block of its block's scratch
            run_worlds(q, q_trial, t, k, gs, Hs, ds, c % block, block, s, c, Tw, wa, wb, threshold, max_iterations,
                       max_line_search, reuse, status, iterations, factorizations, converged, queue)  # fmt: skip
        else:
            run_worlds(q, q_trial, t, k, g, H, dq, c, Tw, s, c, Tw, wa, wb, threshold, max_iterations,
                       max_line_search, reuse, status, iterations, factorizations, converged, queue)  # fmt: skip

    return newton


@functools.lru_cache(maxsize=None)
def lanes_kernel(spec: KernelSpec):
    """``newton_lanes``: a block of LANES lanes per world (scratch "lanes")."""
    dtype, N, TRI, LANES, G, WPB, LOCKSTEP = spec.dtype, spec.N, spec.TRI, spec.LANES, spec.G, spec.WPB, spec.LOCKSTEP
    lanes, cuda, GLEN, WORDS = spec.lanes, spec.cuda, spec.GLEN, spec.WORDS
    vec12 = ops(dtype).vec12
    Terms, Bracket = structs(dtype).Terms, structs(dtype).Bracket
    block_sync = indexing(spec).block_sync
    step_world = world_step(spec).step_world
    SIZE = 4 if dtype == wp.float32 else 8
    # the world's g, H (packed) and Δq in its block's shared memory on CUDA (1.4 KB for 24 unknowns
    # in float32): every lane reads every row in the factor and the solves
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

    return newton_lanes


@functools.lru_cache(maxsize=None)
def fused_kernel(dtype, own=(), folds=(), scratch="global", n=0, envelope=False, phase_clock=False, cuda=False,
                 block=0, bracket=True, groups=1, per_block=1, quadratic=0.0, hold=False, band=False,
                 limits=(0, 0), secant=False, exact=False, axis=-1):  # fmt: skip
    """The Newton kernel for a scene with the given constitutions and ``n`` rows a world's system
    (Model.system_size); ``axis``: a planar scene's normal axis (6 unknowns a body, in the plane;
    −1: 12).

    ``own``: the names of the joint and coordinate constitutions with terms of their own; ``folds``:
    the (name, joint kind) of the coordinate terms folded into a joint's term (a prismatic joint's
    limit and a drive on it, on the displacement and frames the joint has loaded, prismatic_term; a
    revolute joint's limit and up to two drives on it, one term on its angle, its cos, sin,
    increment and gradient computed once, angle_term), each with one put of the summed gradient;
    both in registry order, as terms.fused_flags gives them.

    ``scratch``: "global": a thread per world, its g, H, Δq in global arrays (one column per thread);
    "shared": a thread per world as "global", H's lower triangle packed (n(n+1)/2 words) and, built
    for CUDA (``cuda``), the block's ``block`` threads' g, H, Δq in its shared memory, one column
    per thread (on the CPU the packed columns stay in the global arrays);
    ``band`` (a thread per world, a scene with Model.banded): only H's block band, packed
    (solver.kernels.h_words: 2,076 words for a 10-link chain's 120 unknowns, against 7,260 for the
    triangle and 14,400 square), and the dense factor's loops within it;
    "lanes": a block of ``block`` lanes per world, its system packed (see the package's docstring).
    ``cuda``: built for a GPU (the lane-split step then keeps its scratch in shared memory).
    ``phase_clock``: lane 0 adds each phase's cycles (PHASES) to ``Terms.clock`` (profiling only).
    ``bracket``: the kernel also opens each world's step before its solve (the finite check, the
    joints' references, the prediction q̃ and the initial guess) and closes it after (velocities,
    histories, joint coordinates), so a step is one launch; else those run as kernels of their own
    (``Solver.open_step``, ``Solver.close_step``).
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
    ``quadratic``
    (SolverSettings.quadratic_stop): a Newton step from a fresh factor accepted at α = 1 under this
    many times q's rounding floor ends the solve (take_step).  ``hold`` (with
    ``bracket``): the step leaves alone the worlds of Bracket.hold and, while Bracket.go[0] is 0,
    every world (step_world; a vector env's step graph), a check that a scene stepped on its own
    does not carry.  ``limits``: the scene's (revolute, prismatic) limit counts, for the line
    search's model of them (limit_model.limit_step).  ``secant`` (a thread per world): the Newton
    direction at an acting limit takes the limit's secant curvature (limit_secant).  ``exact``: after
    an iteration that converged only linearly, a world's solve assembles the orthogonality Hessian
    exact (R for its PSD part R⁺, affine_body) until a factor of it breaks down (newton.iterate); for
    scenes with a joint past conditioning.STIFF_JOINT (Model.stiff)."""
    spec = KernelSpec(dtype, tuple(own), tuple(folds), scratch, n, envelope, phase_clock, cuda, block, bracket, groups,
                      per_block, quadratic, hold, band, tuple(limits), bool(secant), bool(exact), int(axis))  # fmt: skip
    kernel = lanes_kernel(spec) if spec.lanes else thread_kernel(spec)
    return kernel, structs(dtype).Terms, structs(dtype).Bracket, assembly_kernel(spec)
