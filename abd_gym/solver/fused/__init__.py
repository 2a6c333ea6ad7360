"""The fused Newton step: one thread runs every iteration, line search and stop test of a world's
solve in a single kernel launch, world after world when there are more worlds than threads.

Same arithmetic and the same Newton rules as the staged kernels of ``solver.py`` (each
constitution's per-instance evaluator; point joints' Hessian blocks added from their 4 × 4
Kronecker factors and bodies' from their parts, neither built as a 12 × 12 matrix; effort drives'
gradient only, as their blocks are zero; an iteration that reuses the last Cholesky factor
assembles the gradient only and leaves H, which holds the factor; ``Solver.fused_system`` checks
this assembly against the staged one), without atomics (a thread owns its scratch column of the
flat ``g``/``H``/``dq``, indexed as in ``solver.kernels``), without per-iteration
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
kernels of ``Solver.open_step`` and ``close_step`` as functions, a body or a joint per lane), so a step is
one launch.

The stages, one module each, each a factory cached on the kernel's ``KernelSpec`` that returns
its ``wp.func`` functions (data flows down this list):

- ``layout``: the spec and its constants, the scratch's indexing, the world's barrier and lane;
- ``structs``: the kernel's struct arguments (``Terms``, ``Bracket``);
- ``clock``: the phase clock (profiling, compiled out unless ``phase_clock``);
- ``puts``: adding a term's gradient and Hessian blocks to the scratch;
- ``terms``: each constitution's term (coordinate terms folded into their joint's, as the registry declares);
- ``assembly``: a world's incremental potential, gradient and Hessian, per layout;
- ``factor``: the lane-split L D Lᵀ factor and substitutions;
- ``limit_secant``: a thread per world's Newton direction at an acting limit (its secant curvature);
- ``newton``: the Newton iteration, line search and stop tests of a world's solve;
- ``bracket``: opening and closing a world's step around its solve;
- ``kernel``: the kernels, and ``fused_kernel``, the factory the solver calls."""
from .clock import PHASES, WORLD_PHASES
from .factor import warp_ldl_solve
from .kernel import fused_kernel
from .layout import KernelSpec, block_sync, lane_index, lanes_scratch_words, shared_array, world_funcs
from .structs import (WORK_ANGLE, WORK_DRIVE, WORK_FIXED, WORK_KINDS, WORK_PRISMATIC, WORK_PRISMATIC_LIMIT,
                      WORK_REVOLUTE, WORK_REVOLUTE_LIMIT)  # fmt: skip

__all__ = ["PHASES", "WORLD_PHASES", "WORK_ANGLE", "WORK_DRIVE", "WORK_FIXED", "WORK_KINDS", "WORK_PRISMATIC",
           "WORK_PRISMATIC_LIMIT", "WORK_REVOLUTE", "WORK_REVOLUTE_LIMIT", "KernelSpec", "block_sync", "fused_kernel",
           "lane_index", "lanes_scratch_words", "shared_array", "warp_ldl_solve", "world_funcs"]
