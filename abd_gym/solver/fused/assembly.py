"""A world's system: the incremental potential E(q) = Σ terms [J] of world w at q[qr] and, per
``derivs`` (ENERGY, GRADIENT, HESSIAN), its gradient g and Hessian H (lower triangle) added to
scratch column s (of B), per layout:

- one thread per world: every term in turn, in the staged kernels' order (bodies, revolute,
  fixed, prismatic joints, limits, angle terms, drives);
- lanes: every lane evaluates every joint term (the same energy, in the same order, on each) and
  adds its own rows; the bodies by rows (``lane_bodies``), their energies summed in body order;
- lane groups: each group its share of the terms (``Terms.work``) into its own copy of g and H,
  the copies then summed in group order (``assemble_groups``)."""
import functools
from types import SimpleNamespace
from typing import Any

import warp as wp

from ...constitutions import affine_body
from ...sim.scene import REVOLUTE
from ...core.warp_ops import HESSIAN, body_dofs, ops
from .clock import (PHASE_ASSEMBLE_BODIES, PHASE_ASSEMBLE_REVOLUTE, PHASE_ASSEMBLE_FIXED, PHASE_ASSEMBLE_PRISMATIC,
                     PHASE_ASSEMBLE_LIMITS, PHASE_ASSEMBLE_DRIVES, clock)  # fmt: skip
from .layout import KernelSpec, indexing
from .puts import puts
from .structs import (WORK_ANGLE, WORK_DRIVE, WORK_FIXED, WORK_PRISMATIC, WORK_PRISMATIC_LIMIT, WORK_REVOLUTE,
                      WORK_REVOLUTE_LIMIT, structs)  # fmt: skip
from .terms import coordinate_terms, terms


@functools.lru_cache(maxsize=None)
def padding(spec: KernelSpec):
    """``pad_rows(H, s, B, first, stride)``: 1 on the diagonal of the system's padding rows (KernelSpec.NR
    ≤ i < N: a planar scene's rows to a multiple of 4) that are this thread's, i ≡ first (mod stride)."""
    dtype, N, NR = spec.dtype, spec.N, spec.NR
    hrow = indexing(spec).hrow

    @wp.func
    def pad_rows(H: Any, s: int, B: int, first: int, stride: int):
        for i in range(NR + (first - NR % stride + stride) % stride, N, stride):
            H[(hrow(i) + i) * B + s] = H[(hrow(i) + i) * B + s] + dtype(1.0)

    return pad_rows


@functools.lru_cache(maxsize=None)
def lane_body_rows(spec: KernelSpec):
    """The lanes' body terms by rows: ``body_rows`` (a lane's rows of the bodies) and
    ``lane_bodies`` (every lane's rows, then the bodies' energies summed in body order)."""
    dtype, N, NF, LANES = spec.dtype, spec.N, spec.NF, spec.LANES
    D, NR = spec.D, spec.NR
    vec12 = ops(dtype).vec12
    sel = body_dofs(spec.axis).sel
    Terms = structs(dtype).Terms
    body_grad, hessian_parts = affine_body.kernels(dtype).body_grad, affine_body.kernels(dtype).hessian_parts
    at = indexing(spec)
    block_sync, lane_index = at.block_sync, at.lane_index
    body_row, pad_rows = puts(spec).body_row, padding(spec)
    zero = dtype(0.0)

    @wp.func
    def body_rows(q: wp.array2d(dtype=vec12), qr: int, w: int, s: int, B: int, derivs: int, t: Terms, g: Any,
                  H: Any, h2: dtype, first: int, stride: int):  # fmt: skip
        """The bodies' terms by rows: the lane evaluates the body of each of its rows ρ = first,
        first + stride, … and adds that row only; body k's energy to slot N + k of g (past the
        gradient) from the lane of its first row.  A padding row past the bodies' (NR ≤ ρ < N) gets
        1 on its diagonal."""
        if wp.static(NR < N):
            if derivs == HESSIAN:
                pad_rows(H, s, B, first, stride)
        for rho in range(first, NR, stride):
            k = rho // D
            b = t.free[k]
            r = rho - D * k
            qb = q[qr, b]
            ks = t.kv[w, b] * h2
            e_in, e_or, f = body_grad(qb, t.q_tilde[w, b], t.mass[w, b], t.mc[w, b], t.S[w, b], ks, derivs)
            if derivs != 0:
                g[rho * B + s] = g[rho * B + s] + f[sel(r)]
                if derivs == HESSIAN:
                    exact = int(0)
                    if wp.static(spec.exact):
                        exact = t.exact[w]
                    Rp, ata = hessian_parts(qb, exact)
                    body_row(H, s, B, D * k, r, qb, t.mass[w, b], t.mc[w, b], t.S[w, b], ks, Rp, ata)
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

    return SimpleNamespace(body_rows=body_rows, lane_bodies=lane_bodies)


@functools.lru_cache(maxsize=None)
def lane_assembly(spec: KernelSpec):
    """The lanes' assembly: ``lane_bodies`` (the bodies by rows, ``lane_body_rows``) and
    ``assemble_groups`` (lane groups, each its share of the terms in its own copy of g and H)."""
    dtype, N, NF, TRI, LANES, G, RL = spec.dtype, spec.N, spec.NF, spec.TRI, spec.LANES, spec.G, spec.RL
    has_rev, has_fix, has_pri = spec.has("revolute_joint"), spec.has("fixed_joint"), spec.has("prismatic_joint")
    has_rlim, has_plim, has_drive = spec.has("revolute_limit"), spec.has("prismatic_limit"), spec.has("drive")
    rev_angles = len(spec.folded(REVOLUTE)) > 0
    vec12 = ops(dtype).vec12
    Terms = structs(dtype).Terms
    at = indexing(spec)
    block_sync, lane_index = at.block_sync, at.lane_index
    body_rows = lane_body_rows(spec).body_rows
    point_term, prismatic_term = terms(spec).point_term, terms(spec).prismatic_term
    ct = coordinate_terms(spec)
    angle_term, rlim_term, plim_term, drive_term = ct.angle_term, ct.rlim_term, ct.plim_term, ct.drive_term
    clock_now, tick = clock(spec).clock_now, clock(spec).tick
    zero = dtype(0.0)

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
            ck = tick(t, w, lane, PHASE_ASSEMBLE_BODIES, ck)
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

    return SimpleNamespace(lane_bodies=lane_body_rows(spec).lane_bodies, assemble_groups=assemble_groups)


@functools.lru_cache(maxsize=None)
def assembly(spec: KernelSpec):
    """``assemble(q, qr, w, s, B, derivs, t, g, H)``: the incremental potential of world w at
    q[qr] and, per ``derivs``, its gradient and Hessian added to scratch column s (of B)."""
    dtype, G, lanes, N, NR = spec.dtype, spec.G, spec.lanes, spec.N, spec.NR
    pad_rows = padding(spec)
    has_rev, has_fix, has_pri = spec.has("revolute_joint"), spec.has("fixed_joint"), spec.has("prismatic_joint")
    has_rlim, has_plim, has_drive = spec.has("revolute_limit"), spec.has("prismatic_limit"), spec.has("drive")
    rev_angles = len(spec.folded(REVOLUTE)) > 0
    vec12 = ops(dtype).vec12
    Terms = structs(dtype).Terms
    lane_bodies, assemble_groups = lane_assembly(spec).lane_bodies, lane_assembly(spec).assemble_groups
    tm = terms(spec)
    body_term, point_term, prismatic_term = tm.body_term, tm.point_term, tm.prismatic_term
    ct = coordinate_terms(spec)
    angle_term, rlim_term, plim_term, drive_term = ct.angle_term, ct.rlim_term, ct.plim_term, ct.drive_term
    clock_now, tick = clock(spec).clock_now, clock(spec).tick
    zero = dtype(0.0)

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
            if wp.static(NR < N):
                if derivs == HESSIAN:
                    pad_rows(H, s, B, 0, 1)
        ck = tick(t, w, 0, PHASE_ASSEMBLE_BODIES, ck)
        if wp.static(has_rev):
            for k in range(t.rev_ids.shape[0]):
                e += point_term(q, qr, w, s, B, derivs, t, g, H, t.rev_ids[k], 2)
            ck = tick(t, w, 0, PHASE_ASSEMBLE_REVOLUTE, ck)
        if wp.static(has_fix):
            for k in range(t.fix_ids.shape[0]):
                e += point_term(q, qr, w, s, B, derivs, t, g, H, t.fix_ids[k], 4)
            ck = tick(t, w, 0, PHASE_ASSEMBLE_FIXED, ck)
        if wp.static(has_pri):
            for k in range(t.pri_ids.shape[0]):
                e += prismatic_term(q, qr, w, s, B, derivs, t, g, H, k)
            ck = tick(t, w, 0, PHASE_ASSEMBLE_PRISMATIC, ck)
        if wp.static(has_rlim):
            for k in range(t.rlim_ids.shape[0]):
                e += rlim_term(q, qr, w, s, B, derivs, t, g, H, k)
        if wp.static(has_plim):
            for k in range(t.plim_ids.shape[0]):
                e += plim_term(q, qr, w, s, B, derivs, t, g, H, k)
        if wp.static(rev_angles):
            for k in range(t.ang_joint.shape[0]):
                e += angle_term(q, qr, w, s, B, derivs, t, g, H, k, hw)
        ck = tick(t, w, 0, PHASE_ASSEMBLE_LIMITS, ck)
        if wp.static(has_drive):
            for k in range(t.drive_rest.shape[0]):
                e += drive_term(q, qr, w, s, B, derivs, t, g, H, t.drive_rest[k], hw, h2)
            ck = tick(t, w, 0, PHASE_ASSEMBLE_DRIVES, ck)
        return e

    return SimpleNamespace(assemble=assemble)
