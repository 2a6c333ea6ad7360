"""Opening and closing a world's step inside the fused kernel (``bracket``): ``open_world`` runs
``Solver.open_step``'s kernels (the finite check, the joints' references, the prediction q̃ and the
initial guess), ``close_world`` ``Solver.close_step``'s (velocities, histories, joint coordinates),
a body or a joint per lane; ``step_world`` composes them around the solve, ``held`` says which
worlds a step leaves alone."""
import functools
from types import SimpleNamespace

import warp as wp

from ...sim import coordinates
from ..kernels import RESTART, keep_restart
from ...sim.status import OK
from ...core.warp_ops import ops
from .clock import (PHASE_OPEN, PHASE_CLOSE, PHASE_OPEN_BODIES, PHASE_OPEN_JOINTS, PHASE_OPEN_PREDICT,
                     PHASE_CLOSE_FINALIZE, PHASE_CLOSE_JOINTS, clock)  # fmt: skip
from .layout import KernelSpec, indexing
from .newton import newton
from .structs import structs


@functools.lru_cache(maxsize=None)
def world_bracket(spec: KernelSpec):
    """``open_world`` and ``close_world``: Solver.open_step's and close_step's kernels for one
    world, inside the fused kernel (``spec.bracket``)."""
    dtype, LANES, lanes = spec.dtype, spec.LANES, spec.lanes
    vec12 = ops(dtype).vec12
    Terms, Bracket = structs(dtype).Terms, structs(dtype).Bracket
    staged = spec.staged()
    open_body, predict_body, finalize_body = staged["open_body"], staged["predict_body"], staged["finalize_body"]
    # the passive terms' predicted rate, kept only where a scene has them
    has_passive = any(f[0] == "passive" for f in spec.folds)
    begin_joint, _, close_joint = coordinates.funcs(dtype, has_passive)
    limit_engaged = coordinates.restart_funcs(dtype)[0]
    limit_reach = staged["limit_reach"]
    # the scene's limits, by kind: a term of their own or folded into their joint's
    has_rlim, has_plim = spec.models("revolute_limit"), spec.models("prismatic_limit")
    block_sync = indexing(spec).block_sync
    clock_now, tick = clock(spec).clock_now, clock(spec).tick

    @wp.func
    def open_world(q: wp.array2d(dtype=vec12), t: Terms, k: Bracket, status: wp.array(dtype=wp.int32), w: int,
                   lane: int):  # fmt: skip
        """Solver.open_step's kernels for world w (bracket=True): open_step, begin_step and predict, a body
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
        c = tick(t, w, lane, PHASE_OPEN_BODIES, c)
        if fresh != 0:
            for j in range(lane, t.joint_kind.shape[0], LANES):
                begin_joint(q, t.body_a, t.body_b, t.joint_kind, t.n_a, t.b_a, t.n_b, t.b_b, k.c_ref, k.s_ref, t.theta0,
                            t.c_prev, t.s_prev, t.unwrapped, k.x_hist, t.h_step, k.h, t.x_anchor, k.velocity,
                            k.velocity_hist, t.v_anchor, w, j)  # fmt: skip
            if wp.static(lanes):
                block_sync()
        c = tick(t, w, lane, PHASE_OPEN_JOINTS, c)
        beta = dtype(1.0)  # the fraction of its extrapolated step the guess takes (predict_body)
        if wp.static(has_rlim):
            beta = limit_reach(k.coord, k.velocity, t.rlim_ids, t.rlim_lo, t.rlim_up, t.rlim_ids.shape[0], k.h, w, beta)
        if wp.static(has_plim):
            beta = limit_reach(k.coord, k.velocity, t.plim_ids, t.plim_lo, t.plim_up, t.plim_ids.shape[0], k.h, w, beta)
        for b in range(lane, nb, LANES):
            predict_body(q, k.qd, k.q_prev, k.q_hist, k.qd_hist, k.qd_hist2, k.order3, k.calm, t.q_tilde, t.dof, t.mass,
                         t.mc, k.gravity, k.h, t.h_step, status, beta, w, b)  # fmt: skip
        if wp.static(lanes):
            block_sync()
        tick(t, w, lane, PHASE_OPEN_PREDICT, c)

    @wp.func
    def close_world(q: wp.array2d(dtype=vec12), t: Terms, k: Bracket, status: wp.array(dtype=wp.int32), w: int,
                    lane: int):  # fmt: skip
        """Solver.close_step's kernels for world w (bracket=True): finalize a body per lane, then, once
        the world's q is final, its joints' coordinates (a healthy world's only); under BDF2, a world
        with a limit engaged restarts its history (coordinates.restart_engaged)."""
        if wp.static(lanes):
            block_sync()
        c = clock_now()
        for b in range(lane, q.shape[1], LANES):
            finalize_body(q, k.q_prev, k.qd, k.q_hist, k.qd_hist, k.qd_hist2, k.order3, t.dof, k.h, t.h_step, status, w,
                          b)  # fmt: skip
        if lane == 0:
            keep_restart(k.fresh, w)  # (fresh is read by this step's open only, before its first barrier)
        if wp.static(lanes):
            block_sync()
        c = tick(t, w, lane, PHASE_CLOSE_FINALIZE, c)
        if status[w] == OK:
            for j in range(lane, t.joint_kind.shape[0], LANES):
                close_joint(q, k.q_prev, t.body_a, t.body_b, t.joint_kind, t.c_a, t.c_b, t.t_a, t.n_a, t.b_a, t.n_b,
                            t.b_b, t.theta0, t.c_prev, t.s_prev, k.c_ref, k.s_ref, k.h, t.h_step, k.bdf2, k.coord, k.velocity,
                            t.unwrapped, k.x_hist, t.x_anchor, k.velocity_hist, t.v_anchor, w, j)  # fmt: skip
        if wp.static(has_rlim or has_plim):
            if k.bdf2 != 0 and status[w] == OK:
                if wp.static(lanes):
                    block_sync()  # the coordinates, by other lanes
                if lane == 0:
                    engaged = int(0)
                    if wp.static(has_rlim):
                        engaged += limit_engaged(k.coord, t.rlim_ids, t.rlim_lo, t.rlim_up, t.rlim_ids.shape[0], w)
                    if wp.static(has_plim):
                        engaged += limit_engaged(k.coord, t.plim_ids, t.plim_lo, t.plim_up, t.plim_ids.shape[0], w)
                    if engaged != 0:
                        k.fresh[w] = RESTART  # (solver.kernels.open_body)
        tick(t, w, lane, PHASE_CLOSE_JOINTS, c)  # (lane 0's joints: no barrier follows them)

    return SimpleNamespace(open_world=open_world, close_world=close_world)


@functools.lru_cache(maxsize=None)
def world_step(spec: KernelSpec):
    """``step_world``: a world's step, its solve opened and closed here with ``bracket``
    (``world_bracket``)."""
    dtype, bracket, hold = spec.dtype, spec.bracket, spec.hold
    vec12 = ops(dtype).vec12
    Terms, Bracket = structs(dtype).Terms, structs(dtype).Bracket
    open_world, close_world = world_bracket(spec).open_world, world_bracket(spec).close_world
    clock_now, tick = clock(spec).clock_now, clock(spec).tick
    solve_world = newton(spec).solve_world

    @wp.func
    def held(k: Bracket, w: int):
        """1 where world w is not stepped: built with ``hold`` (and bracket), a world held
        (k.hold[w] != 0) or a batch refused (k.go[0] == 0); else 0."""
        if wp.static(bracket and hold):
            if k.go[0] == 0 or k.hold[w] != 0:
                return 1
        return 0

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
        if held(k, w) != 0:
            return
        if wp.static(bracket):
            c = clock_now()
            open_world(q, t, k, status, w, lane)
            tick(t, w, lane, PHASE_OPEN, c)
        solve_world(q, q_trial, t, g, H, dq, w, s, T, row, threshold, max_iterations, max_line_search, reuse, status,
                    iterations, factorizations, converged, lane)  # fmt: skip
        if wp.static(bracket):
            c = clock_now()
            close_world(q, t, k, status, w, lane)
            tick(t, w, lane, PHASE_CLOSE, c)

    return SimpleNamespace(step_world=step_world, held=held, open_world=open_world, close_world=close_world)
