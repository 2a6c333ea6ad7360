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

``scratch="tiled"``: one CUDA block per world instead of one thread.  Every lane runs the same scalar code
(the evaluators compute whole 12 × 12 blocks); the Hessian and gradient live in shared memory,
added one entry per lane per ``wp.tile_scatter_add``, and the block factors and solves with
``wp.tile_cholesky_inplace`` / ``wp.tile_cholesky_solve_inplace``.  Measured on an H100
(``results/bench_h100_tiled.md``) it is faster only where there are few worlds and cheap terms
(1,024 double pendulums: 1.4x); with the evaluators repeated on all 32 lanes a block issues as
many instructions as 32 per-thread worlds, so it saturates near 1.8 M world-steps/s.
"""
import functools
from typing import Any

import numpy as np
import warp as wp

from . import solver_kernels
from .constitutions import _point_joint, affine_body, drive, prismatic_joint, prismatic_limit, revolute_limit
from .warp_ops import ENERGY, GRADIENT, HESSIAN, ops

OK, FAILED = 0, 1


@functools.lru_cache(maxsize=None)
def fused_kernel(dtype, has_rev, has_fix, has_pri, has_rlim, has_plim, has_drive, scratch="global", n=0,
                 max_registers=0, smem_spilling=False, envelope=False, retract=True):  # fmt: skip
    """The Newton kernel for a scene with the given constitutions and ``n`` unknowns per world.

    ``scratch``: "global": a thread per world, its g, H, Δq in global arrays (one column per thread);
    "tiled": a CUDA block per world, H and g in shared memory, assembled together and factored by
    ``wp.tile_cholesky``.  (A third layout, g, H and Δq in each thread's local memory, measured
    slower than "global" at every batch size on an H100 and was removed; see results/.)
    ``max_registers`` (0: the compiler's choice) caps registers per thread on CUDA, trading spills
    for occupancy; ``smem_spilling`` lets the compiler spill registers to shared memory."""
    # loops stay loops: unrolling the 12×12 block loops of every inlined evaluator multiplies the
    # code size, and with it NVRTC's compile time (minutes); on an H100 unrolling the 3-loops
    # (max_unroll 3) made the cart-pole step 15% slower, max_unroll 4 compiled for minutes for 5%
    options = dict(module="unique", module_options={"max_unroll": 1})
    if max_registers:
        options["cuda_max_registers"] = int(max_registers)
    if smem_spilling:
        options["enable_cuda_smem_spilling"] = True
    tiled = n if scratch == "tiled" else 0
    N = n  # unknowns per world (12 per free body), a constant of the kernel
    o = ops(dtype)
    vec3, vec12, mat33, mat12, mat44 = o.vec3, o.vec12, o.mat33, o.mat12, o.mat44
    body_eval = affine_body.kernels(dtype).body_eval
    hessian_parts, a_block = affine_body.kernels(dtype).hessian_parts, affine_body.kernels(dtype).a_block
    retract_body = affine_body.kernels(dtype).retract
    point_eval_kron = _point_joint.kernel(dtype).eval_kron
    kron3, kron_index = o.kron3, o.kron_index
    prismatic_eval = prismatic_joint.kernel(dtype).eval
    rlim_eval = revolute_limit.kernel(dtype).eval
    plim_eval = prismatic_limit.kernel(dtype).eval
    drive_eval = drive.kernel(dtype).eval
    staged = solver_kernels.kernels(dtype, envelope and scratch != "tiled")
    cholesky_solve, factored_solve = staged["cholesky_solve"], staged["factored_solve"]
    noise_floor, energy_noise = staged["noise_floor"], staged["energy_noise"]
    zero, one, half = dtype(0.0), dtype(1.0), dtype(0.5)
    EPS = dtype(float(np.finfo(np.float32 if dtype == wp.float32 else np.float64).eps))

    if tiled:

        @wp.func
        def put_grad(g: Any, s: int, B: int, o: int, v: vec12):
            """g[o:o+12] += v, lanes s, s+B, … of the block adding one entry each."""
            if o >= 0:
                for base in range(0, 12, B):
                    r = wp.min(base + s, 11)
                    wp.tile_scatter_add(g, o + r, v[r], base + s < 12, False)

        @wp.func
        def put_block(H: Any, s: int, B: int, oa: int, ob: int, m: mat12):
            """Block (oa, ob) and its transpose into the lower triangle of the shared H (all the
            Cholesky reads), one entry per lane per call."""
            if oa >= 0 and ob >= 0:
                for base in range(0, 144, B):
                    e = base + s
                    r = wp.min(e // 12, 11)
                    c = wp.min(e - r * 12, 11)  # lanes past the block's end write nothing
                    i = oa + r
                    j = ob + c
                    keep = e < 144 and (oa != ob or i >= j)
                    if i < j:
                        t = i
                        i = j
                        j = t
                    wp.tile_scatter_add(H, i, j, m[r, c], keep, False)

    else:

        # the thread's scratch column s of the flat g, H (solver_kernels: entry (i, j) of H at
        # (i·N + j)·T + s, entry i of g at i·T + s); B is T, the scratch width

        @wp.func
        def put_grad(g: Any, s: int, B: int, o: int, v: vec12):
            if o >= 0:
                p = o * B + s
                for r in range(12):
                    g[p] = g[p] + v[r]
                    p += B

        @wp.func
        def put_block(H: Any, s: int, B: int, oa: int, ob: int, m: mat12):
            """Add block (oa, ob) and its transpose, lower triangle only (all the Cholesky reads):
            a diagonal block's lower half; (oa, ob) below the diagonal as it is, above it transposed."""
            if oa >= 0 and ob >= 0:
                if oa == ob:
                    for r in range(12):
                        p = ((oa + r) * N + ob) * B + s
                        for c in range(r + 1):
                            H[p] = H[p] + m[r, c]
                            p += B
                elif oa > ob:
                    for r in range(12):
                        p = ((oa + r) * N + ob) * B + s
                        for c in range(12):
                            H[p] = H[p] + m[r, c]
                            p += B
                else:
                    for c in range(12):
                        p = ((ob + c) * N + oa) * B + s
                        for r in range(12):
                            H[p] = H[p] + m[r, c]
                            p += B

        @wp.func
        def put_body(H: Any, s: int, B: int, o: int, qb: vec12, m: dtype, c: vec3, S: mat33, ks: dtype):
            """Body o's Hessian (affine_body.body_eval's h) added to the lower triangle from its parts,
            without building the 12 × 12 matrix in the thread's local memory: m on the translation
            diagonal, the first moments c below it, and the A rows' 3 × 3 blocks (a_block), 57
            entries where the dense block's lower triangle has 78."""
            if o >= 0:
                Rp, ata = hessian_parts(qb)
                for r in range(3):
                    p = ((o + r) * N + o + r) * B + s
                    H[p] = H[p] + m
                    for a in range(3):
                        p = ((o + 3 + 3 * r + a) * N + o + r) * B + s
                        H[p] = H[p] + c[a]
                for kk in range(3):
                    for ll in range(kk + 1):
                        blk = a_block(qb, kk, ll, Rp, ata, ks, S)
                        for a in range(3):
                            p = ((o + 3 + 3 * kk + a) * N + o + 3 + 3 * ll) * B + s
                            for bb in range(3):
                                if kk != ll or bb <= a:
                                    H[p] = H[p] + blk[a, bb]
                                p += B

    if tiled:

        @wp.func
        def put_kron(H: Any, s: int, B: int, oa: int, ob: int, U: mat44):
            put_block(H, s, B, oa, ob, kron3(U))

    else:

        @wp.func
        def put_kron(H: Any, s: int, B: int, oa: int, ob: int, U: mat44):
            """Block (oa, ob) = U ⊗ I₃ (see warp_ops.kron3): its 48 non-zero entries only."""
            if oa >= 0 and ob >= 0:
                for m in range(3):
                    for c in range(4):
                        a = kron_index(m, c)
                        for d in range(4):
                            b = kron_index(m, d)
                            if oa > ob or (oa == ob and a >= b):
                                p = ((oa + a) * N + ob + b) * B + s
                                H[p] = H[p] + U[c, d]
                            elif oa < ob:
                                p = ((ob + b) * N + oa + a) * B + s
                                H[p] = H[p] + U[c, d]

    @wp.func
    def trial(q: wp.array2d(dtype=vec12), q_trial: wp.array2d(dtype=vec12), t: Any, step: Any, w: int, row: int,
              s: int, T: int, alpha: dtype):  # fmt: skip
        """q_trial[row] = q[w] + α Δq along the retraction's path (affine_body.retract): Δq in
        scratch column s of the flat ``step`` (T columns), or (tiled) −y with y = H⁻¹g in the
        block's shared tile ``step``."""
        for b in range(q.shape[1]):
            qb = q[w, b]
            ob = t.dof[b]
            if ob >= 0:
                d = vec12()
                for r in range(12):
                    if wp.static(tiled):
                        d[r] = -wp.tile_extract(step, ob + r)
                    else:
                        d[r] = step[(ob + r) * T + s]
                if wp.static(retract):
                    qb = retract_body(qb, d, alpha, t.mass[w, b], t.mc[w, b], 0)
                else:
                    qb = qb + alpha * d
            q_trial[row, b] = qb

    @wp.func
    def put_kron_pair(g: Any, H: Any, s: int, B: int, derivs: int, oi: int, oj: int, gi: vec12, gj: vec12,
                      uii: mat44, uij: mat44, ujj: mat44):  # fmt: skip
        put_grad(g, s, B, oi, gi)
        put_grad(g, s, B, oj, gj)
        if derivs == HESSIAN:
            put_kron(H, s, B, oi, oi, uii)
            put_kron(H, s, B, oi, oj, uij)
            put_kron(H, s, B, oj, oj, ujj)

    @wp.func
    def put_pair(g: Any, H: Any, s: int, B: int, derivs: int, oi: int, oj: int, gi: vec12, gj: vec12, hii: mat12,
                 hij: mat12, hjj: mat12):  # fmt: skip
        put_grad(g, s, B, oi, gi)
        put_grad(g, s, B, oj, gj)
        if derivs == HESSIAN:
            put_block(H, s, B, oi, oi, hii)
            put_block(H, s, B, oi, oj, hij)
            put_block(H, s, B, oj, oj, hjj)

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
        drive_mode: wp.array(dtype=wp.int32)
        kp: wp.array2d(dtype=dtype)
        kd: wp.array2d(dtype=dtype)
        fmax: wp.array2d(dtype=dtype)
        control: wp.array2d(dtype=dtype)
        unwrapped: wp.array2d(dtype=dtype)
        x_anchor: wp.array2d(dtype=dtype)

    @wp.func
    def assemble(q: wp.array2d(dtype=vec12), qr: int, w: int, s: int, B: int, derivs: int, t: Terms, g: Any, H: Any):
        """Total incremental potential of world w at q[qr]; derivs GRADIENT adds its g, HESSIAN its g
        and H (to scratch column s; tiled: to the block's shared g and H, s the lane, B the block size)."""
        e = zero
        hw = t.h_step[w]
        h2 = hw * hw
        for k in range(t.free.shape[0]):
            b = t.free[k]
            qb = q[qr, b]
            ks = t.kv[w, b] * h2
            d_body = derivs
            if wp.static(not tiled) and derivs == HESSIAN:
                d_body = GRADIENT  # the Hessian goes straight into H (put_body)
            e_in, e_or, f, hb = body_eval(qb, t.q_tilde[w, b], t.mass[w, b], t.mc[w, b], t.S[w, b], ks, d_body)
            e += e_in + e_or
            if derivs != 0:
                put_grad(g, s, B, t.dof[b], f)
                if derivs == HESSIAN:
                    if wp.static(tiled):
                        put_block(H, s, B, t.dof[b], t.dof[b], hb)
                    else:
                        put_body(H, s, B, t.dof[b], qb, t.mass[w, b], t.mc[w, b], t.S[w, b], ks)
        if wp.static(has_rev):
            for k in range(t.rev_ids.shape[0]):
                j = t.rev_ids[k]
                ej, gi, gj, uii, uij, ujj = point_eval_kron(q[qr, t.body_a[j]], q[qr, t.body_b[j]], t.pts_a, t.pts_b, w, j, 2,
                                                            t.K[w, j], derivs)  # fmt: skip
                e += ej
                if derivs != 0:
                    put_kron_pair(g, H, s, B, derivs, t.dof[t.body_a[j]], t.dof[t.body_b[j]], gi, gj, uii, uij, ujj)
        if wp.static(has_fix):
            for k in range(t.fix_ids.shape[0]):
                j = t.fix_ids[k]
                ej, gi, gj, uii, uij, ujj = point_eval_kron(q[qr, t.body_a[j]], q[qr, t.body_b[j]], t.pts_a, t.pts_b, w, j, 4,
                                                            t.K[w, j], derivs)  # fmt: skip
                e += ej
                if derivs != 0:
                    put_kron_pair(g, H, s, B, derivs, t.dof[t.body_a[j]], t.dof[t.body_b[j]], gi, gj, uii, uij, ujj)
        if wp.static(has_pri):
            for k in range(t.pri_ids.shape[0]):
                j = t.pri_ids[k]
                ej, gi, gj, hii, hij, hjj = prismatic_eval(q[qr, t.body_a[j]], q[qr, t.body_b[j]], t.c_a[w, j], t.c_b[w, j],
                                                           t.t_a[w, j], t.t_b[w, j], t.n_a[w, j], t.n_b[w, j], t.b_a[w, j],
                                                           t.b_b[w, j], t.K[w, j], derivs,
                                                           wp.where(t.dof[t.body_a[j]] >= 0, 1, 0),
                                                           wp.where(t.dof[t.body_b[j]] >= 0, 1, 0))  # fmt: skip
                e += ej
                if derivs != 0:
                    put_pair(g, H, s, B, derivs, t.dof[t.body_a[j]], t.dof[t.body_b[j]], gi, gj, hii, hij, hjj)
        if wp.static(has_rlim):
            for k in range(t.rlim_ids.shape[0]):
                j = t.rlim_ids[k]
                ej, gi, gj, hii, hij, hjj = rlim_eval(q[qr, t.body_a[j]], q[qr, t.body_b[j]], t.n_a[w, j], t.b_a[w, j], t.n_b[w, j],
                                                      t.b_b[w, j], t.theta0[w, j], t.c_prev[w, j], t.s_prev[w, j], t.rlim_lo[w, k],
                                                      t.rlim_up[w, k], t.rlim_s[w, k], derivs)  # fmt: skip
                e += ej
                if derivs != 0 and ej != zero:
                    put_pair(g, H, s, B, derivs, t.dof[t.body_a[j]], t.dof[t.body_b[j]], gi, gj, hii, hij, hjj)
        if wp.static(has_plim):
            for k in range(t.plim_ids.shape[0]):
                j = t.plim_ids[k]
                ej, gi, gj, hii, hij, hjj = plim_eval(q[qr, t.body_a[j]], q[qr, t.body_b[j]], t.c_a[w, j], t.c_b[w, j], t.t_a[w, j],
                                                      t.plim_lo[w, k], t.plim_up[w, k], t.plim_s[w, k], derivs)  # fmt: skip
                e += ej
                if derivs != 0 and ej != zero:
                    put_pair(g, H, s, B, derivs, t.dof[t.body_a[j]], t.dof[t.body_b[j]], gi, gj, hii, hij, hjj)
        if wp.static(has_drive):
            for k in range(t.drive_joint.shape[0]):
                j = t.drive_joint[k]
                ej, gi, gj, hii, hij, hjj = drive_eval(q[qr, t.body_a[j]], q[qr, t.body_b[j]], w, k, t.drive_joint, t.joint_kind,
                                                       t.c_a, t.c_b, t.t_a, t.n_a, t.b_a, t.n_b, t.b_b, t.c_prev, t.s_prev, t.drive_mode, t.kp,
                                                       t.kd, t.fmax, t.control, t.unwrapped, t.x_anchor, hw, h2, 0, derivs)  # fmt: skip
                e += ej
                if derivs != 0 and t.drive_mode[k] == 0:  # an effort drive is linear: gradient only
                    put_grad(g, s, B, t.dof[t.body_a[j]], gi)
                    put_grad(g, s, B, t.dof[t.body_b[j]], gj)
                elif derivs != 0:
                    put_pair(g, H, s, B, derivs, t.dof[t.body_a[j]], t.dof[t.body_b[j]], gi, gj, hii, hij, hjj)
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
               max_line_search: int):  # fmt: skip
        """(accepted, stalled, α) for the step: taken whole when ``skip`` (whole_step); a reused
        factor's step tried at α = 1 only; else Armijo backtracking on the world's own energy.  The
        trial points go to row ``row`` of q_trial; s, B as in assemble."""
        trial(q, q_trial, t, step, w, row, s, B, one)
        alpha = one
        accepted = int(0)
        stalled = int(0)
        if skip != 0:
            accepted = 1
            stalled = done
        elif chord > 0:
            accepted, stalled = armijo(e0, assemble(q_trial, row, w, s, B, ENERGY, t, g, H), one, gdq)
        else:
            for ls in range(max_line_search):
                if ls > 0:
                    trial(q, q_trial, t, step, w, row, s, B, alpha)
                accepted, stalled = armijo(e0, assemble(q_trial, row, w, s, B, ENERGY, t, g, H), alpha, gdq)
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
        tolerance, where Newton's leaves it far below)."""
        if chord > 0:
            if accepted == 0:
                return 1, -1
            return 0, wp.where(dmax <= dtype(0.125) * d_prev, 1, 0)
        if chord < 0:
            return 0, -1
        return 0, wp.where(accepted != 0 and alpha == one, reuse, 0)

    @wp.func
    def end_iteration(q: wp.array2d(dtype=vec12), q_trial: wp.array2d(dtype=vec12), w: int, row: int, accepted: int,
                      stalled: int, dmax: dtype, floor: dtype, converged: wp.array(dtype=wp.int32)):  # fmt: skip
        """Take the accepted trial point (row of q_trial) as world w's q; 1 when its solve is over.
        A search that ran out takes no step: converged if the step was already near the tolerance.
        (Steps within 10x the noise floor are taken whole, see whole_step.)"""
        if accepted == 0:
            if dmax < dtype(1000.0) * floor:
                converged[w] = 1
            return 1
        for b in range(q.shape[1]):
            q[w, b] = q_trial[row, b]
        if dmax < floor or stalled != 0:
            converged[w] = 1
            return 1
        return 0

    @wp.func
    def take_step(q: wp.array2d(dtype=vec12), q_trial: wp.array2d(dtype=vec12), t: Terms, step: Any, g: Any, H: Any,
                  w: int, row: int, s: int, B: int, e0: dtype, gdq: dtype, dmax: dtype, g_abs: dtype, threshold: dtype, chord: int,
                  reuse: int, d_prev: dtype, max_line_search: int, converged: wp.array(dtype=wp.int32)):  # fmt: skip
        """Everything after a Newton direction (both layouts): the stop test, the line search, the
        choice to reuse the factor next, and the update of q.  Returns (1 when the solve is over,
        chord for the next iteration)."""
        floor, rounding = noise_floor(q, w, threshold)
        skip, done = whole_step(e0, gdq, dmax, floor, energy_noise(rounding, g_abs), chord)
        accepted, stalled, alpha = search(q, q_trial, t, step, g, H, w, row, s, B, e0, gdq, skip, done, chord,
                                          max_line_search)  # fmt: skip
        retry, chord_next = chord_step(chord, reuse, accepted, alpha, dmax, d_prev)
        stop = int(0)
        if retry == 0:
            stop = end_iteration(q, q_trial, w, row, accepted, stalled, dmax, floor, converged)
        return stop, chord_next

    @wp.func
    def solve_world(q: wp.array2d(dtype=vec12), q_trial: wp.array2d(dtype=vec12), t: Terms, g: wp.array(dtype=dtype),
                    H: wp.array(dtype=dtype), dq: wp.array(dtype=dtype), w: int, s: int, T: int, row: int, threshold: dtype,
                    max_iterations: int, max_line_search: int, reuse: int, status: wp.array(dtype=wp.int32),
                    iterations: wp.array(dtype=wp.int32), factorizations: wp.array(dtype=wp.int32),
                    converged: wp.array(dtype=wp.int32)):  # fmt: skip
        """World w's whole Newton solve, in scratch column s (of T) of the flat g, H, dq and row
        ``row`` of q_trial.

        With ``reuse``, an iteration after a full step (α = 1) keeps the Cholesky factor it left in H
        and solves only the new gradient against it (a simplified-Newton step; see ``chord_step``)."""
        iterations[w] = 0
        factorizations[w] = 0
        converged[w] = 0
        if status[w] != OK:
            return 0
        chord = int(0)  # 1: H holds the factor of an earlier iteration, reused for this one (chord_step)
        d_prev = zero
        for it in range(max_iterations):
            for i in range(N):
                g[i * T + s] = zero
                if chord <= 0:
                    j0 = int(0)
                    if wp.static(envelope):
                        j0 = t.first[i]
                    p = (i * N + j0) * T + s
                    for j in range(j0, i + 1):
                        H[p] = zero
                        p += T
            e0 = zero
            ok = int(0)
            gdq = zero
            dmax = zero
            g_abs = zero
            if chord > 0:
                e0 = assemble(q, w, w, s, T, GRADIENT, t, g, H)
                ok, gdq, dmax, g_abs = factored_solve(H, g, dq, s, N, T, t.first)
            else:
                e0 = assemble(q, w, w, s, T, HESSIAN, t, g, H)
                ok, gdq, dmax, g_abs = cholesky_solve(H, g, dq, s, N, T, t.first)
                factorizations[w] = factorizations[w] + 1
            if ok == 0:
                status[w] = FAILED
                return 0
            iterations[w] = it + 1
            stop, chord = take_step(q, q_trial, t, dq, g, H, w, row, s, T, e0, gdq, dmax, g_abs, threshold, chord, reuse,
                                    d_prev, max_line_search, converged)  # fmt: skip
            if stop != 0:
                return 0
            d_prev = dmax
        return 0

    @wp.kernel(**options)
    def newton(
        q: wp.array2d(dtype=vec12), q_trial: wp.array2d(dtype=vec12), t: Terms,
        g: wp.array(dtype=dtype), H: wp.array(dtype=dtype), dq: wp.array(dtype=dtype),
        s0: int, Tw: int, wa: int, wb: int, threshold: dtype, max_iterations: int, max_line_search: int, reuse: int,
        status: wp.array(dtype=wp.int32), iterations: wp.array(dtype=wp.int32),
        factorizations: wp.array(dtype=wp.int32), converged: wp.array(dtype=wp.int32),
    ):  # fmt: skip
        """The launch's Tw threads solve worlds wa … wb − 1, thread c the worlds wa + c, wa + c + Tw,
        …: a thread's scratch is reused world after world, so it stays in cache however many worlds
        there are.  On a GPU one launch runs every world; on the CPU ranges of threads and worlds run
        as concurrent launches, each with its own scratch (g, H, dq: Tw columns) and its own run of
        worlds, so they share no cache lines; s0 + c is the thread's row of q_trial."""
        c = wp.tid()
        s = c + s0
        for w in range(wa + c, wb, Tw):
            solve_world(q, q_trial, t, g, H, dq, w, c, Tw, s, threshold, max_iterations, max_line_search,
                        reuse, status, iterations, factorizations, converged)  # fmt: skip

    @wp.kernel(**options)
    def assemble_system(q: wp.array2d(dtype=vec12), t: Terms, derivs: int, g: wp.array(dtype=dtype),
                        H: wp.array(dtype=dtype), E: wp.array(dtype=dtype)):  # fmt: skip
        """The incremental potential of world w and, per ``derivs``, its gradient and Hessian (lower
        triangle) as the fused step assembles them, into scratch column w of the zeroed flat g, H
        (one column per world): for checking the fused assembly against the staged one."""
        w = wp.tid()
        E[w] = assemble(q, w, w, w, q.shape[0], derivs, t, g, H)

    if scratch == "global":
        return newton, Terms, assemble_system

    @wp.func
    def solve_world_tiled(q: wp.array2d(dtype=vec12), q_trial: wp.array2d(dtype=vec12), t: Terms, H: Any, g: Any,
                          y: Any, Hz: Any, gz: Any, w: int, lane: int, B: int, threshold: dtype, max_iterations: int,
                          max_line_search: int, reuse: int, status: wp.array(dtype=wp.int32),
                          iterations: wp.array(dtype=wp.int32), factorizations: wp.array(dtype=wp.int32),
                          converged: wp.array(dtype=wp.int32)):  # fmt: skip
        """World w's Newton solve by the B lanes of one block: every lane runs the same scalar code
        (so every branch is uniform and the lanes' global writes agree), H and g live in shared
        memory, assembled one entry per lane, and the block factors H together (kept for the next
        iteration as in ``solve_world``)."""
        iterations[w] = 0
        factorizations[w] = 0
        converged[w] = 0
        if status[w] != OK:
            return 0
        chord = int(0)
        d_prev = zero
        for it in range(max_iterations):
            wp.tile_assign(g, gz, offset=(0,))
            e0 = zero
            if chord > 0:
                e0 = assemble(q, w, w, lane, B, GRADIENT, t, g, H)
                wp.tile_assign(y, g, offset=(0,))
            else:
                wp.tile_assign(H, Hz, offset=(0, 0))
                e0 = assemble(q, w, w, lane, B, HESSIAN, t, g, H)
                wp.tile_assign(y, g, offset=(0,))
                wp.tile_cholesky_inplace(H)
                factorizations[w] = factorizations[w] + 1
            wp.tile_cholesky_solve_inplace(H, y)
            gdq = zero
            dmax = zero
            g_abs = zero
            for i in range(N):
                yi = wp.tile_extract(y, i)
                gi = wp.tile_extract(g, i)
                gdq -= gi * yi
                dmax = wp.max(dmax, wp.abs(yi))
                g_abs += wp.abs(gi)
            if not (wp.isfinite(gdq) and wp.isfinite(dmax)):  # H not positive definite
                status[w] = FAILED
                return 0
            iterations[w] = it + 1
            stop, chord = take_step(q, q_trial, t, y, g, H, w, w, lane, B, e0, gdq, dmax, g_abs, threshold, chord, reuse,
                                    d_prev, max_line_search, converged)  # fmt: skip
            if stop != 0:
                return 0
            d_prev = dmax
        return 0

    @wp.kernel(**options)
    def newton_tiled(
        q: wp.array2d(dtype=vec12), q_trial: wp.array2d(dtype=vec12), t: Terms, threshold: dtype,
        max_iterations: int, max_line_search: int, reuse: int, status: wp.array(dtype=wp.int32),
        iterations: wp.array(dtype=wp.int32), factorizations: wp.array(dtype=wp.int32),
        converged: wp.array(dtype=wp.int32),
    ):  # fmt: skip
        """Block w solves world w (launched with ``wp.launch_tiled``, one block per world)."""
        w, lane = wp.tid()
        B = wp.block_dim()
        H = wp.tile_zeros(shape=(N, N), dtype=dtype, storage="shared")
        g = wp.tile_zeros(shape=(N,), dtype=dtype, storage="shared")
        y = wp.tile_zeros(shape=(N,), dtype=dtype, storage="shared")
        Hz = wp.tile_zeros(shape=(N, N), dtype=dtype, storage="shared")
        gz = wp.tile_zeros(shape=(N,), dtype=dtype, storage="shared")
        solve_world_tiled(q, q_trial, t, H, g, y, Hz, gz, w, lane, B, threshold, max_iterations, max_line_search,
                          reuse, status, iterations, factorizations, converged)  # fmt: skip

    return newton_tiled, Terms, None

