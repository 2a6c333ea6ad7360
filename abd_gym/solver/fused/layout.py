"""What a fused kernel is built for (``KernelSpec``) and where a world's system lies in its scratch.

A thread's scratch column s of the flat g, H (``solver_kernels``): entry (i, j) of H at
(hrow(i) + j)·B + s, hrow(i) = i·N (square), i(i+1)/2 (packed lower triangle) or the packed block
band's (solver_kernels.h_row_starts: body b's rows from column 12(b − 1)); entry i of g at
i·B + s, B the scratch width (the thread count, or 1 for a world's contiguous scratch).

Lanes (``scratch="lanes"``): a world's L lanes split its rows, lane l owning the rows i ≡ l (mod L)
(``own_all``), or, with lane groups of RL lanes, i ≡ l (mod RL) of its group's copy of g and H
(``own_from``); a world's lanes meet at its barrier (``world_funcs``).
"""
import dataclasses
import functools
from types import SimpleNamespace

import warp as wp

from .. import kernels as solver_kernels
from ...constitutions import REGISTRY


@wp.func_native("WP_TILE_SYNC();")
def block_sync():
    """A barrier for the threads of a block (``__syncthreads`` on CUDA; on the CPU a yield to the
    block's other fibers when ``wp.config.enable_cpu_blocks``, else a no-op for its one thread)."""
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


@functools.lru_cache(maxsize=None)
def tile_address(dtype, count: int):
    """A function returning the address of a shared tile of ``count`` ``dtype`` words (made by
    ``wp.tile_empty(shape=(count,), dtype=dtype, storage="shared")``).  Warp sizes a kernel's
    dynamic shared memory from its shared tiles and opts the kernel in past the 48 KB that a static
    array may take, so a block's scratch may fill a quarter of an SM's 228 KB (H100)."""

    @wp.func_native("return (uint64_t)(t.data.ptr);")
    def address(t: wp.tile(dtype=dtype, shape=(count,), storage="shared")) -> wp.uint64:
        ...

    return address


def lanes_scratch_words(n: int, groups: int, band: bool = False, body_dofs: int = 12) -> int:
    """Words of one world's scratch in the lane-split step (its block's shared memory on CUDA):
    ``groups`` copies of H's packed lower triangle (n(n+1)/2 each; ``band``: its packed block band,
    solver_kernels.h_words), g (n, then the bodies' energies and, with groups, the copies' g, the
    groups' energies and the factor's flag) and Δq (n); ``body_dofs`` unknowns a free body."""
    tri, nf = solver_kernels.h_words(n, True, band), n // body_dofs
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


@dataclasses.dataclass(frozen=True)
class KernelSpec:
    """The arguments of ``fused_kernel`` (see its docstring), and the kernel's constants derived
    from them (upper case: N unknowns a world, LANES threads a world, …)."""

    dtype: type
    own: tuple = ()
    folds: tuple = ()
    scratch: str = "global"
    n: int = 0
    envelope: bool = False
    phase_clock: bool = False
    cuda: bool = False
    block: int = 0
    bracket: bool = True
    groups: int = 1
    per_block: int = 1
    quadratic: float = 0.0
    hold: bool = False
    band: bool = False
    limits: tuple = (0, 0)
    secant: bool = False
    exact: bool = False
    axis: int = -1

    def __post_init__(self):
        if self.LANES % self.G:
            raise ValueError(f"{self.LANES} lanes a world do not split into {self.G} equal groups")
        if self.WPB > 1 and self.G > 1:
            raise ValueError("lane groups take a block per world (per_block 1)")
        if self.band and self.envelope:
            raise ValueError("the block band is a packed H, not the square envelope")
        for kind, count in zip(("revolute_limit", "prismatic_limit"), self.limits):
            # the bracket's guess (limit_reach) reads the constitutions, the line search the counts
            if self.models(kind) != (count > 0):
                raise ValueError(f"limits={self.limits} disagrees with the scene's {kind} terms")
        if self.secant and self.lanes:
            raise ValueError("the limits' secant direction (secant=True) is a thread per world's, not the lanes'")

    def has(self, name: str) -> bool:
        """Whether constitution ``name`` has fused terms of its own (terms.fused_flags)."""
        return name in self.own

    def models(self, name: str) -> bool:
        """Whether the scene has constitution ``name`` at all: terms of its own or folded into its
        joints' terms."""
        return self.has(name) or any(f[0] == name for f in self.folds)

    def folded(self, joint_kind: str) -> tuple:
        """The coordinate constitutions folded into joints of ``joint_kind``'s terms, in registry
        order (terms.fused_flags)."""
        return tuple(c for c in REGISTRY if (c.name, joint_kind) in self.folds)

    @property
    def lanes(self) -> bool:
        """A block of LANES lanes per world (else a thread per world)."""
        return self.scratch == "lanes"

    @property
    def packed(self) -> bool:
        """H's lower triangle packed: in shared memory on CUDA ("shared": the block's threads'
        columns; "lanes": the world's system), else contiguous in the global scratch; with
        ``band``, only its block band (solver_kernels.h_words), in any scratch."""
        return self.scratch in ("shared", "lanes") or self.band

    def staged(self) -> dict:
        """solver_kernels' functions for this scratch: square, packed, the square envelope's or the
        packed band's factor and solves."""
        return solver_kernels.kernels(self.dtype, self.envelope or self.band, self.packed)

    @property
    def in_smem(self) -> bool:
        """A thread per world with its g, H, Δq in the block's shared memory (scratch="shared", CUDA)."""
        return self.packed and self.cuda and not self.lanes

    @property
    def N(self) -> int:
        """Rows of a world's system (Model.system_size), a constant of the kernel: D per free body,
        then up to 3 padding rows to a multiple of 4 (the factor's tiles)."""
        return self.n

    @property
    def D(self) -> int:
        """Unknowns per free body: 12, or 6 in a planar scene's plane (``axis``: its normal, −1: none)."""
        return 6 if self.axis >= 0 else 12

    @property
    def NF(self) -> int:
        """Free bodies (D unknowns each, body k's from D·k: Model.dof)."""
        return self.N // self.D

    @property
    def NR(self) -> int:
        """The bodies' rows (D·NF); rows NR … N − 1 pad the system (H 1 on their diagonal, g 0)."""
        return self.D * self.NF

    @property
    def TRI(self) -> int:
        """Words of H packed: its lower triangle, or with ``band`` its block band (and, lanes, the
        stride of the groups' copies)."""
        return solver_kernels.h_words(self.N, True, self.band)

    @property
    def LANES(self) -> int:
        """Threads per world, a constant of the kernel (``block`` for lanes, else 1)."""
        return max(int(self.block), 1) if self.lanes else 1

    @property
    def G(self) -> int:
        """Lane groups (a warp each on a GPU)."""
        return max(int(self.groups), 1) if self.lanes else 1

    @property
    def RL(self) -> int:
        """Lanes of a group, which share a copy of g and H, each owning its rows."""
        return self.LANES // self.G

    @property
    def WPB(self) -> int:
        """Worlds a block."""
        return max(int(self.per_block), 1) if self.lanes and self.cuda else 1

    @property
    def LOCKSTEP(self) -> bool:
        """A block of several warps (lockstep): its worlds start each step of a launch together, so
        the SM's warps run the same stretch of the kernel's code at once (Solver.lockstep_warps)."""
        return self.LANES * self.WPB > 32

    @property
    def warp_regs(self) -> bool:
        """On a GPU, a world whose lanes (the first group's warp, when there are several) hold at
        most 3 of its rows each factors and solves in registers (warp_ldl_solve)."""
        one_warp = self.G == 1 or self.RL == 32
        regs = self.RL in (8, 16, 32) and one_warp and self.n <= 3 * self.RL
        return self.lanes and self.cuda and regs and not self.band

    @property
    def compact(self) -> bool:
        """Compact code where a world's step is a latency-bound chain (lanes): blocks of a term in
        loops of selected arguments, one inlined assemble per mode: a smaller kernel, whose
        instructions the SM's caches hold better, for a chain that waits on each one; a thread
        per world (throughput-bound) keeps the branches, which cost it less than the selects."""
        return self.lanes

    @property
    def GLEN(self) -> int:
        """Words of a lane-split world's g: with lane groups, G copies of H and of g (copy c from
        c·TRI; copy 0's g holds past N the bodies' energies, the groups' energies and the factor's
        ok: assemble_groups and solve_world)."""
        return self.N + self.NF if self.G == 1 else (self.G - 1) * self.TRI + self.N + self.NF + self.G + 1

    @property
    def WORDS(self) -> int:
        """A lane-split world's scratch words."""
        return lanes_scratch_words(self.N, self.G, self.band, self.D)


@functools.lru_cache(maxsize=None)
def indexing(spec: KernelSpec):
    """The kernel's scratch indexing and its world's barrier and lane: ``hrow``, ``own_from``,
    ``own_all``, ``block_sync`` (the world's lanes' barrier), ``lane_index`` (the lane in its world)."""
    N, LANES, RL, lanes = spec.N, spec.LANES, spec.RL, spec.lanes
    h_row = spec.staged()["h_row"]
    # a world's barrier and lane: the block's, or its own lanes' of a warp shared with other worlds
    block_sync, lane_index = world_funcs(LANES, spec.WPB)  # noqa: F811 (the world's, shadowing the module's)

    @wp.func
    def hrow(i: int):
        """Where row i of H starts in a scratch column (solver_kernels.h_row: square, packed or the band)."""
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

    return SimpleNamespace(hrow=hrow, own_from=own_from, own_all=own_all, block_sync=block_sync, lane_index=lane_index)
