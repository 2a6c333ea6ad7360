"""How the step runs on a device: the execution plan, derived from device × batch × scene.

What a physicist chooses (dt, integrator, dtype, tolerance, iteration budget) is the Simulator's
and ``SolverSettings``'; everything here changes how the work is laid out on the device, never the
arithmetic of a world's step (the layouts give the same trajectories to rounding, most of them bit
for bit; tests/test_graph.py).  ``ExecutionPlan`` holds the choices, None meaning "derive it";
``resolve_plan`` derives every None for a model (its device, number of worlds, unknowns, dtype and
terms) by the ``default_*`` rules below, and refuses inconsistent choices with a ValueError
naming the value.  The measurement behind each rule is in docs/performance.md ("Why the
execution plan chooses what it does") or results/solver_notes.md.  An expert overrides any of them by
passing a plan: ``Simulator(scene, plan=ExecutionPlan(scratch="global", threads=1024))``.
"""
from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass

import numpy as np
import warp as wp

from .fused import lanes_scratch_words
from .kernels import h_words
from .terms import joint_terms, term_counts

SCRATCHES = ("global", "shared", "lanes")


@dataclass(frozen=True)
class ExecutionPlan:
    """How the step runs on the device; None: derived by resolve_plan (Simulator.plan: the resolved plan)."""

    # one kernel runs each world's whole Newton solve (abd_gym/solver/fused); False: the staged kernels (the reference); None: True
    fused: bool | None = None
    # the fused step's g, H, Δq: "global" (a column a thread), "shared" (a thread a world, H packed in its block's
    # shared memory) or "lanes" (block_dim lanes a world, its system packed); None: default_scratch
    scratch: str | None = None
    # fused-step threads, each solving worlds in turn from the launch's queue (not with "lanes"); None: default_threads
    threads: int | None = None
    # CUDA block size, lanes a world with "lanes"; None: default_block_dim / _block_dim_shared / default_lane_width
    block_dim: int | None = None
    # "lanes": groups of a world's lanes (a warp each on a GPU), each assembling a share of the terms;
    # None: default_lane_groups
    lane_groups: int | None = None
    # "lanes" on a GPU, one group: warps a block whose worlds start each step together; None: default_lockstep_warps
    lockstep_warps: int | None = None
    # where a step is one launch of the lane-split kernel, steps a launch at most; None: default_steps_per_launch
    steps_per_launch: int | None = None
    # the fused kernel also opens and closes each world's step, so a step is one launch; None: with "lanes"
    one_launch: bool | None = None
    # factor only the Hessian's envelope (Model.first); a thread per world on a scene with Model.banded
    # stores only its block band, packed; None: where the scene has one ("shared": a banded one; "lanes": never)
    envelope: bool | None = None
    # CPU: the fused step's threads as this many launches run at once on as many cores; None: default_cpu_workers
    cpu_workers: int | None = None
    # Simulator.step replays the step as a captured graph (CUDA graph, or Warp's CPU command replay); None: True
    use_graph: bool | None = None
    # profiling only: the fused step adds each phase's cycles to Solver.phase_cycles (fused.PHASES); None: False
    phase_clock: bool | None = None
    # a thread per world: the Newton direction at an acting limit takes the limit's secant curvature, or
    # leaves the limit out where the solution lies off it (fused.limit_secant); None: default_limit_secant
    limit_secant: bool | None = None


def available_cores() -> int:
    """The CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def default_threads(device, num_worlds: int, cpu_workers: int = 1) -> int:
    """Threads of the fused step.  On a GPU at most 256 per SM: a large batch then steps about as
    fast as on one thread per world, with the dense Newton scratch (n² values per thread, the
    largest per-world array) shared among the worlds a thread takes in turn, so memory per world
    falls (``python -m abd_gym.bench threads``).  On the CPU, where Warp runs a launch's threads
    one after another, 16, or one per worker where there are more."""
    if device.is_cuda:
        return min(num_worlds, 256 * device.sm_count)
    return min(num_worlds, max(16, cpu_workers))


def default_cpu_workers(num_worlds: int) -> int:
    """Concurrent launches of the fused step on the CPU: one per core, each with at least 64 worlds.
    Below that a second launch costs more than it shares out: the phases around the launches
    replay as two graphs instead of one (``python -m abd_gym.bench --device cpu --cpu-workers 1,2``)."""
    return max(1, min(available_cores(), num_worlds // 64))


def default_block_dim(device, threads: int) -> int:
    """CUDA block size of the fused step: small blocks while there are few threads, so they spread
    over every SM (each thread's solve is latency-bound, so an idle SM is time lost), 128 once
    every SM is busy."""
    sms = device.sm_count if device.is_cuda else 1
    return 32 if threads <= 32 * sms else 64 if threads <= 128 * sms else 128


SHARED_BLOCK_BYTES = 48 * 1024 - 1024  # static shared memory a block, less Warp's own (its tile base)


def shared_bytes_per_thread(n: int, dtype, band: bool = False) -> int:
    """A thread's Newton system in shared memory: H's packed lower triangle (``band``: its packed
    block band), g and Δq [bytes]."""
    return (h_words(n, True, band) + 2 * n) * (4 if dtype == wp.float32 else 8)


# shared memory of an SM by compute capability (CUDA C++ Programming Guide), for the blocks of
# scratch="shared" of which four fill one; other devices take the 48 KB rule
SM_SHARED_BYTES = {80: 164 * 1024, 87: 164 * 1024, 90: 228 * 1024, 100: 228 * 1024, 103: 228 * 1024}
# a block's shared memory besides its threads' systems: the driver's 1 KB and Warp's tile base
BLOCK_SHARED_OVERHEAD = 1024 + 128


def quarter_sm_block_dim(device, n: int, dtype, band: bool = False) -> int:
    """Threads of a block for scratch="shared" four of which fill an SM's shared memory (one warp
    a scheduler), at most 32: 24 four-bar systems of 36 unknowns (block band) on an H100, 13 of a
    5-link chain's 60; 0 where the device's SM is not in SM_SHARED_BYTES."""
    room = SM_SHARED_BYTES.get(getattr(device, "arch", 0), 0) // 4 - BLOCK_SHARED_OVERHEAD
    return max(min(32, room // shared_bytes_per_thread(n, dtype, band)), 0)


def default_block_dim_shared(n: int, dtype, band: bool = False, device=None, num_worlds: int = 0) -> int:
    """Threads a block for scratch="shared": 32 (one warp) where their systems fit 48 KB (a static
    array's most); else as many as fit; 0 when not even one does.  On a GPU (``device``) whose SM
    holds four blocks of more (quarter_sm_block_dim), those, where ``num_worlds`` fill a wave of
    them (four a SM): an SM's four warps then hold more worlds, and the threads' world queue
    (fused.kernel.run_worlds) keeps them busy past the wave.  Below a wave the larger blocks leave
    SMs idle, so the 48 KB rule stays."""
    fit = min(32, SHARED_BLOCK_BYTES // shared_bytes_per_thread(n, dtype, band))
    big = quarter_sm_block_dim(device, n, dtype, band) if getattr(device, "is_cuda", False) else 0
    if big > fit and num_worlds >= 4 * device.sm_count * big:
        return big
    return fit


# warps an SM holds of a thread-per-world step: its threads take up to 255 registers (65,536 an SM)
THREAD_WARPS_PER_SM = 8


def resident_threads_shared(device, n: int, dtype, band: bool, block_dim: int) -> int:
    """Threads of scratch="shared" that a GPU holds at once, in blocks of ``block_dim``: as many
    blocks an SM as its shared memory holds (SM_SHARED_BYTES), at most THREAD_WARPS_PER_SM, on
    every SM; 0 where the SM is not in SM_SHARED_BYTES.  The step's threads claim worlds from a
    queue as they finish (fused.kernel.run_worlds), so a launch of these many keeps every SM
    full with no second wave."""
    sm = SM_SHARED_BYTES.get(getattr(device, "arch", 0), 0)
    per_block = block_dim * shared_bytes_per_thread(n, dtype, band) + BLOCK_SHARED_OVERHEAD
    blocks = min(sm // per_block, THREAD_WARPS_PER_SM // -(-block_dim // 32))
    return blocks * device.sm_count * block_dim


def shared_block_room(device) -> int:
    """The dynamic shared memory one block of scratch="shared" may take [bytes]: the device's opt-in
    maximum (227 KB on an H100), else SHARED_BLOCK_BYTES."""
    return getattr(device, "max_shared_memory_per_block", 0) or SHARED_BLOCK_BYTES


def max_block_dim_shared(device, n: int, dtype, band: bool = False) -> int:
    """The most threads a block of scratch="shared" holds: their systems in shared_block_room."""
    return shared_block_room(device) // shared_bytes_per_thread(n, dtype, band)


def default_steps_per_launch(lockstep_warps: int = 1) -> int:
    """Steps a launch where a step is one launch: 50 where the lane-split step's warps run in
    lockstep blocks (``lockstep_warps`` > 1), else 2.  Each launch saved is its overhead saved; but
    without lockstep, a launch's warps drift apart over many steps of the large kernel and the SM's
    instruction caches miss more, which loses what the launches saved."""
    return 50 if lockstep_warps > 1 else 2


def default_lockstep_warps(device, scratch: str, num_worlds: int, lanes: int, groups: int, n: int, dtype,
                           band: bool = False) -> int:
    """Warps a block of the lane-split step on a GPU (ExecutionPlan.lockstep_warps): the most of 8
    (LANE_WARPS_PER_SM, an SM's worth), 4, 2 that split the worlds into whole blocks (worlds ×
    lanes a multiple of 32 × warps) whose systems fit the block's shared memory; 1 for one thread
    a world, lane groups and the CPU."""
    if scratch != "lanes" or groups != 1 or not getattr(device, "is_cuda", False) or lanes > 32:
        return 1
    return next(k for k in (8, 4, 2, 1) if k == 1 or (num_worlds * lanes % (32 * k) == 0 and lanes_scratch_bytes(
        n, dtype, 1, 32 * k // lanes, band) <= SHARED_BLOCK_BYTES))  # fmt: skip


# warps of the lane-split kernel an SM holds at once: its threads take ~255 registers (65,536 a SM)
LANE_WARPS_PER_SM = 8


def lanes_scratch_bytes(n: int, dtype, groups: int = 1, per_block: int = 1, band: bool = False) -> int:
    """Shared memory of a block of the lane-split step on CUDA: ``per_block`` worlds of ``n``
    unknowns, each with ``groups`` copies of its system (fused.lanes_scratch_words; ``band``: H's
    block band)."""
    return per_block * lanes_scratch_words(n, groups, band) * (4 if dtype == wp.float32 else 8)


# the lane-split step keeps a banded scene's block band where a world's rows do not fit its warp's
# registers (more than 3 rows a lane of 32: warp_ldl_solve, which reads the triangle): chains of
# 9 links and more, whose packed triangle is slower to factor than the band, or (20 links) does
# not fit a block at all
LANES_BAND_MIN_UNKNOWNS = 3 * 32 + 1


def lanes_band(n: int, banded: bool) -> bool:
    """Whether the lane-split step stores the block band of a world of ``n`` unknowns (``banded``:
    Model.banded) by default."""
    return bool(banded and n >= LANES_BAND_MIN_UNKNOWNS)


def default_lane_groups(device, scratch: str, num_worlds: int, terms: int = 3, n: int = 0, dtype=wp.float32,
                        band: bool = False) -> int:
    """Lane groups a world of the lane-split step on a GPU: one for the bodies and one for each of
    the world's ``terms`` (joints, limits and drives, term_counts), at most 4, else 2, else 1: the
    most whose blocks (a warp a group) all fit on the GPU at once (LANE_WARPS_PER_SM), else the
    launch runs in two waves, which costs more than the groups save.  With ``n`` unknowns: no more
    groups than a block's shared memory holds copies of the system.  The CPU: 1."""
    if scratch != "lanes" or not getattr(device, "is_cuda", False):
        return 1
    top = min(4, 1 + terms)
    # a block's warps share an SM: LANE_WARPS_PER_SM // g blocks of g warps fit on one
    return next(g for g in sorted({top, min(top, 2), 1}, reverse=True)
                if g == 1 or (num_worlds <= LANE_WARPS_PER_SM // g * device.sm_count
                              and lanes_scratch_bytes(n, dtype, g, 1, band) <= SHARED_BLOCK_BYTES))  # fmt: skip


def default_lane_width(device, num_worlds: int, dtype=wp.float32, n: int = 0, band: bool = False) -> int:
    """Lanes a world of the lane-split step on a GPU: for up to LANES_MAX_UNKNOWNS unknowns ``n``,
    the most of 32, 16, 8 whose warps all fit on the GPU at once (LANE_WARPS_PER_SM; under 32
    lanes, 32 // lanes worlds share a warp), else 0; for more, 32 up to WIDE_LANES_MAX_WORLDS
    worlds where one world's system (``band``: a banded scene's block band) fits a block's shared
    memory, else 0.  A world's step is a chain of dependent work on its lanes, so the GPU runs ~8 warps an SM (its
    registers' worth) each taking about as long whether it holds 1, 2 or 4 worlds: narrower worlds
    pay only once one wave of full-width worlds no longer holds them, and past one wave of the
    narrowest a thread per world is as fast.  float64: 32 lanes only (narrower worlds hold 2-3 rows
    of twice the registers a lane; not measured)."""
    room = LANE_WARPS_PER_SM * getattr(device, "sm_count", 0)
    if n > LANES_MAX_UNKNOWNS:
        fits = room and lanes_scratch_bytes(n, dtype, band=band) <= SHARED_BLOCK_BYTES
        return 32 if fits and 0 < num_worlds <= WIDE_LANES_MAX_WORLDS else 0
    widths = (32, 16, 8) if dtype == wp.float32 else (32,)
    return next((L for L in widths if 0 < num_worlds and -(-num_worlds * L // 32) <= room), 0)


# the most unknowns of a world that the default lane-split step gives 16 or 8 lanes where 32 would
# not fit the GPU at once (three free bodies: the closed-loop tasks FourBar-v0 and SliderCrank-v0);
# larger worlds take 32 lanes, up to WIDE_LANES_MAX_WORLDS worlds: a narrow chain holds too many
# rows a lane, and past those worlds a thread per world is faster.
LANES_MAX_UNKNOWNS = 36
WIDE_LANES_MAX_WORLDS = 4096
# past those worlds, a chain's systems in shared memory where this many fit a block (fewer threads
# than a warp): with fewer a block, its few threads leave the SM's warps idle and global memory is
# faster, so 10-link chains (5 a block with the block band, Model.banded) stay global.
SHARED_MIN_SYSTEMS = 6


def default_scratch(device, n: int, dtype, fused: bool = True, num_worlds: int = 0, band: bool = False) -> str:
    """On a GPU, for up to LANES_MAX_UNKNOWNS unknowns (a cart-pole, a double pendulum, a four-bar
    or slider-crank linkage): "lanes" where the worlds' warps fit the GPU at once
    (default_lane_width: up to 4,224 worlds on an H100's 132 SMs), where one thread per world
    leaves most SMs idle; for more (chains): "lanes" at 32 lanes up to WIDE_LANES_MAX_WORLDS worlds
    where a world's system fits a block's shared memory; else "shared" where SHARED_MIN_SYSTEMS
    threads' systems fit a block's shared memory (32 of them up to 24 unknowns in float32, 16 at
    36; with ``band``, a Model.banded scene's block band, 20 at 36 and 11 at 60); else "global".
    Shared memory is nearer than global memory to a thread that reads its system at every step of
    the factor and solve; lanes spread a world's work over a warp, which wins while the batch
    alone would leave SMs idle (``python -m abd_gym.bench --scratch global,shared,lanes``)."""
    if not (fused and device.is_cuda):
        return "global"
    if default_lane_width(device, num_worlds, dtype, n, lanes_band(n, band)):
        return "lanes"
    fit = default_block_dim_shared(n, dtype, band)
    if fit >= SHARED_MIN_SYSTEMS:
        return "shared"
    return "global"


# the one-launch step (one_launch None): with the lane-split step only, whose short steps the five
# kernels that open and close a step would otherwise weigh on (scripts/profile_step.py --split).
# With a thread per world one launch gains nothing: each thread then walks its world's bodies and
# joints in turn, where the separate kernels spread them over threads


def resolve_plan(plan, model) -> ExecutionPlan:
    """``plan`` (an ExecutionPlan, a dict of its fields, or None) for ``model`` (its device,
    num_worlds, num_dofs, dtype and scene), every None derived: the plan a Solver runs.  Resolving
    a resolved plan returns it unchanged.  Raises ValueError on a bad or inconsistent value."""
    plan = as_plan(plan)
    _check_values(plan)
    device, W, n, dtype = wp.get_device(model.device), model.num_worlds, model.system_size, model.dtype
    fused = True if plan.fused is None else bool(plan.fused)
    banded = model.banded
    scratch = plan.scratch or default_scratch(device, n, dtype, fused, W, banded and plan.envelope is not False)
    if scratch != "global" and not fused:
        raise ValueError(f"scratch={scratch!r} needs the fused step (fused=True)")
    lanes, shared = scratch == "lanes", scratch == "shared"
    if (shared or lanes) and plan.envelope and not banded:
        raise ValueError(f"scratch={scratch!r} factors densely (H packed) but for a banded scene (Model.banded: three "
                         "or more free bodies, each coupled to the one before it at most): it takes envelope=False or "
                         "None here")  # fmt: skip
    default = lanes_band(n, banded) if lanes else banded if shared else model.envelope
    envelope = default if plan.envelope is None else bool(plan.envelope)
    if plan.lane_groups not in (None, 1) and not lanes:
        raise ValueError(f"lane_groups={plan.lane_groups!r} needs scratch='lanes'")
    workers, threads = _threads(plan, device, W, fused, scratch)
    block_dim, groups = _blocks(plan, model, device, scratch, threads, envelope)
    if shared and device.is_cuda and plan.threads is None:
        threads = min(threads, resident_threads_shared(device, n, dtype, envelope and banded, block_dim) or threads)
    lock = _lockstep(plan, device, W, scratch, block_dim, groups, n, dtype, envelope)
    steps = int(plan.steps_per_launch or default_steps_per_launch(lock))
    if plan.limit_secant and (lanes or not fused):
        raise ValueError(f"limit_secant=True is a thread per world's (scratch 'global' or 'shared', fused=True), "
                         f"not scratch={scratch!r} with fused={fused}")  # fmt: skip
    secant = default_limit_secant(device, scratch, W, threads) if plan.limit_secant is None else bool(plan.limit_secant)
    out = ExecutionPlan(fused=fused, scratch=scratch, threads=threads, block_dim=block_dim, lane_groups=groups,
                        lockstep_warps=lock, steps_per_launch=steps,
                        one_launch=bool(fused and (lanes if plan.one_launch is None else plan.one_launch)),
                        envelope=envelope, cpu_workers=workers,
                        use_graph=True if plan.use_graph is None else bool(plan.use_graph),
                        phase_clock=bool(plan.phase_clock), limit_secant=bool(secant and fused))  # fmt: skip
    _check_memory(out, device, n, dtype, banded)
    return out


# the most worlds a thread of the fused step's launch (world queue) at which the plan takes the
# limits' secant direction (default_limit_secant says why)
SECANT_MAX_WORLDS_PER_THREAD = 2.75


def default_limit_secant(device, scratch: str, num_worlds: int, threads: int) -> bool:
    """Whether the fused step's thread per world takes the limits' secant direction (fused.limit_secant):
    on a GPU where its threads hold at most SECANT_MAX_WORLDS_PER_THREAD worlds each.  A step then
    lasts about as long as its slowest worlds' solves, and those are the worlds striking and
    leaving limits, whose iterations the secant saves; with many worlds a thread, the world queue
    evens their iterations out and the acting limits' check at every iteration is a loss.  On the
    CPU, whose threads run one after another, no slowest world sets the pace: never."""
    return bool(device.is_cuda and scratch != "lanes" and num_worlds <= SECANT_MAX_WORLDS_PER_THREAD * threads)


def plan_band(plan: ExecutionPlan, banded: bool) -> bool:
    """Whether a resolved plan's step stores only H's block band (packed): the fused step's thread
    per world or lanes with the envelope on a scene with Model.banded (``banded``)."""
    return bool(banded and plan.fused and plan.envelope)


def worlds_per_block(plan: ExecutionPlan, device) -> int:
    """Worlds a CUDA block of a resolved lane-split plan: 32 // block_dim where worlds of under 32
    lanes (a power of two, one group) share a warp (fused.world_funcs), times lockstep_warps; else 1."""
    L = plan.block_dim
    share = plan.scratch == "lanes" and device.is_cuda and L < 32 and not L & (L - 1) and plan.lane_groups == 1
    return (32 // L if share else 1) * plan.lockstep_warps


def as_plan(plan) -> ExecutionPlan:
    """``plan`` (an ExecutionPlan, a dict of its fields or None) as an ExecutionPlan, unresolved."""
    if plan is None:
        return ExecutionPlan()
    if isinstance(plan, ExecutionPlan):
        return plan
    if isinstance(plan, dict):
        names = {f.name for f in dataclasses.fields(ExecutionPlan)}
        unknown = sorted(set(plan) - names)
        if unknown:
            raise ValueError(f"plan has no field {unknown[0]!r}: ExecutionPlan's fields are {sorted(names)}")
        return ExecutionPlan(**plan)
    raise ValueError(f"plan must be an ExecutionPlan, a dict of its fields or None, got {plan!r}")


def _positive(value) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool) and value > 0


def _check_values(plan: ExecutionPlan):
    """Each field's own range (their consistency is resolve_plan's)."""
    for name in ("fused", "one_launch", "envelope", "use_graph", "phase_clock", "limit_secant"):
        value = getattr(plan, name)
        if value is not None and not isinstance(value, (bool, np.bool_)):
            raise ValueError(f"{name} must be True, False or None, got {value!r}")
    if plan.scratch is not None and plan.scratch not in SCRATCHES:
        raise ValueError(f"scratch must be 'global', 'shared' or 'lanes', got {plan.scratch!r}")
    if plan.cpu_workers is not None and not _positive(plan.cpu_workers):
        raise ValueError(f"cpu_workers must be a positive integer or None, got {plan.cpu_workers!r}")
    if plan.threads is not None and not _positive(plan.threads):
        raise ValueError(f"threads must be a positive integer, got {plan.threads!r}")
    if plan.block_dim is not None and not _positive(plan.block_dim):
        raise ValueError(f"block_dim must be a positive integer or None, got {plan.block_dim!r}")
    if plan.lane_groups is not None and not _positive(plan.lane_groups):
        raise ValueError(f"lane_groups must be a positive integer or None, got {plan.lane_groups!r}")
    if plan.steps_per_launch is not None and not _positive(plan.steps_per_launch):
        raise ValueError(f"steps_per_launch must be a positive integer or None, got {plan.steps_per_launch!r}")
    lock = plan.lockstep_warps
    if lock is not None and not (_positive(lock) and lock <= LANE_WARPS_PER_SM):
        raise ValueError(f"lockstep_warps must be an integer from 1 to {LANE_WARPS_PER_SM} or None, got {lock!r}")


def _threads(plan: ExecutionPlan, device, W: int, fused: bool, scratch: str):
    """(CPU workers, threads) of the step: concurrent launches on the CPU's fused thread-per-world
    step (else 1); its threads, at most one per world (else one per world: the staged step's
    scratch columns, the lane-split step's blocks)."""
    workers = 1
    if device.is_cpu and fused and scratch != "lanes":
        workers = default_cpu_workers(W) if plan.cpu_workers is None else int(plan.cpu_workers)
    if not fused or scratch == "lanes":
        if plan.threads is not None and plan.threads != W:
            step = "the lane-split step runs a block a world" if fused else "the staged step keeps a column a world"
            raise ValueError(f"threads={plan.threads!r} applies to a thread per world (scratch 'global' or 'shared'): "
                             f"{step}")
        return workers, W
    T = default_threads(device, W, workers) if plan.threads is None else plan.threads
    if scratch == "shared" and device.is_cuda and plan.threads is None:
        T = W  # a system in shared memory lives as long as its block: no scratch to keep small
    return workers, int(min(T, W))


def _blocks(plan: ExecutionPlan, model, device, scratch: str, threads: int, band: bool = False):
    """(block_dim, lane_groups): lanes a world and their groups for the lane-split step (narrow
    worlds where the GPU must hold more of them at once, one group each), the threads a block
    whose systems fit its shared memory for "shared" on CUDA, default_block_dim otherwise."""
    W, n, dtype = model.num_worlds, model.system_size, model.dtype
    lanes = scratch == "lanes"
    width = plan.block_dim or (lanes and default_lane_width(device, W, dtype, n, band)) or 32
    narrow = lanes and width < 32
    terms = sum(term_counts(model, joint_terms(model)).values())
    groups = int(plan.lane_groups or (1 if narrow else default_lane_groups(device, scratch, W, terms, n, dtype, band)))
    block_dim = plan.block_dim or ((width if narrow else 32 * groups) if lanes else default_block_dim(device, threads))
    if scratch == "shared" and device.is_cuda:
        fit = max_block_dim_shared(device, n, dtype, band)
        block_dim = plan.block_dim or default_block_dim_shared(n, dtype, band, device, W) or fit
        if not 1 <= block_dim <= fit:
            per = shared_bytes_per_thread(n, dtype, band)
            raise ValueError(f"scratch='shared': {block_dim or 1} thread(s) of {n} unknowns need "
                             f"{max(block_dim, 1) * per} B of shared memory a block, more than the "
                             f"{shared_block_room(device)} B "
                             f"a block may take; at most {fit} fit (block_dim), else use scratch='global'")  # fmt: skip
    if lanes and not 1 <= block_dim <= 256:
        raise ValueError(f"scratch='lanes' takes 1 to 256 lanes a world (block_dim), got {block_dim!r}")
    if lanes and device.is_cpu and not wp.config.enable_cpu_blocks:
        return 1, 1  # Warp runs a CPU block's threads as one unless cooperative blocks are on
    if lanes and block_dim % groups:
        raise ValueError(f"scratch='lanes': {block_dim} lanes a world (block_dim) do not split into "
                         f"{groups} equal groups (lane_groups)")  # fmt: skip
    return int(block_dim), groups


def _lockstep(plan: ExecutionPlan, device, W: int, scratch: str, L: int, groups: int, n: int, dtype,
              band: bool = False) -> int:
    """Warps a lockstep block: only where a block's warps are worlds of one group on a GPU (narrow
    worlds sharing a warp, or a warp a world); else 1."""
    lanes = scratch == "lanes" and device.is_cuda and groups == 1
    if not (lanes and (L == 32 or (L < 32 and not L & (L - 1)))):
        return 1
    lock = plan.lockstep_warps
    if lock is None:
        return default_lockstep_warps(device, scratch, W, L, groups, n, dtype, band)
    if W * L % (32 * lock):
        raise ValueError(f"lockstep_warps={lock}: {W} worlds of {L} lanes do not fill whole blocks of {lock} "
                         "warps (worlds × lanes a multiple of 32 × lockstep_warps)")  # fmt: skip
    return int(lock)


def _check_memory(plan: ExecutionPlan, device, n: int, dtype, banded: bool = False):
    """A lane-split block's systems within its shared memory; the flat scratch within 32-bit indices."""
    band = plan_band(plan, banded)
    if plan.scratch == "lanes" and device.is_cuda:
        per_block = worlds_per_block(plan, device)
        need = lanes_scratch_bytes(n, dtype, plan.lane_groups, per_block, band)
        if need > SHARED_BLOCK_BYTES:
            raise ValueError(f"scratch='lanes': a block of {per_block} world(s) of {n} unknowns in "
                             f"{plan.lane_groups} lane group(s) needs {need} B of shared memory, more than its "
                             f"{SHARED_BLOCK_BYTES} B: take 32 lanes a world (block_dim=32), lane_groups=1 and "
                             "lockstep_warps=1, or scratch='shared' or 'global'")  # fmt: skip
    if h_words(n, band or plan.scratch != "global", band) * plan.threads >= 2**31:  # 32-bit indices
        raise ValueError(f"the Newton scratch of {plan.threads} columns of {n} unknowns exceeds 2**31 entries: use the "
                         "fused step (fused=True, its threads reuse their scratch) or fewer worlds")  # fmt: skip
