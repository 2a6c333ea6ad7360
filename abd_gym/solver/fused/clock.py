"""The phase clock (``fused_kernel(phase_clock=True)``, profiling only): lane 0 of a world adds the
SM's cycles spent in each phase of its step to ``Terms.clock[w, phase]``.  Built without it,
``clock_now`` and ``tick`` compile to nothing that reads the clock (``wp.static``), so the
production kernel carries no profiling."""
import functools
from types import SimpleNamespace

import warp as wp

from .layout import KernelSpec
from .structs import structs

# the phases the clock times, columns of Terms.clock (cycles summed per world)
PHASES = ("zero", "assemble", "factor", "solve", "step", "step: energy", "step: trial", "assemble: bodies",
          "assemble: revolute", "assemble: fixed", "assemble: prismatic", "assemble: limits", "assemble: drives",
          "open", "close", "open: bodies", "open: joints", "open: predict", "close: finalize", "close: joints")
# each phase's column (tick's k)
(PHASE_ZERO, PHASE_ASSEMBLE, PHASE_FACTOR, PHASE_SOLVE, PHASE_STEP, PHASE_STEP_ENERGY, PHASE_STEP_TRIAL,
 PHASE_ASSEMBLE_BODIES, PHASE_ASSEMBLE_REVOLUTE, PHASE_ASSEMBLE_FIXED, PHASE_ASSEMBLE_PRISMATIC, PHASE_ASSEMBLE_LIMITS,
 PHASE_ASSEMBLE_DRIVES, PHASE_OPEN, PHASE_CLOSE, PHASE_OPEN_BODIES, PHASE_OPEN_JOINTS, PHASE_OPEN_PREDICT,
 PHASE_CLOSE_FINALIZE, PHASE_CLOSE_JOINTS) = range(len(PHASES))  # fmt: skip
# the phases that partition a world's step (the rest split these)
WORLD_PHASES = (PHASE_ZERO, PHASE_ASSEMBLE, PHASE_FACTOR, PHASE_SOLVE, PHASE_STEP, PHASE_OPEN, PHASE_CLOSE)


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


@functools.lru_cache(maxsize=None)
def clock(spec: KernelSpec):
    """``clock_now()``: the cycle count (0 without the clock); ``tick(t, w, lane, k, c)``: phase k
    of world w ends now, begun at count c."""
    phase_clock = spec.phase_clock
    Terms = structs(spec.dtype).Terms

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

    return SimpleNamespace(clock_now=clock_now, tick=tick)
