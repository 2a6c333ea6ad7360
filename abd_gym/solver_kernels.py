"""Per-world Newton kernels: prediction, dense Cholesky solve, line search, step finalisation.

One thread per world owns that world's small dense system (12 × free bodies unknowns), so no
world waits on another and a failing world touches only its own rows.
"""

import functools

import numpy as np
import warp as wp

from .constitutions import affine_body
from .warp_ops import ops

# world status codes
OK, FAILED = 0, 1


@functools.lru_cache(maxsize=None)
def kernels(dtype, envelope=False):
    """The per-world Newton kernels for ``dtype``; ``envelope``: the Cholesky factor and solves skip
    the columns left of each row's first non-zero (``Model.first``), for block-banded scenes."""
    o = ops(dtype)
    vec3, vec12 = o.vec3, o.vec12
    zero, one = dtype(0.0), dtype(1.0)
    EPS = dtype(float(np.finfo(np.float32 if dtype == wp.float32 else np.float64).eps))
    retract = affine_body.kernels(dtype).retract

    @wp.func
    def noise_floor(q: wp.array2d(dtype=vec12), w: int, threshold: dtype):
        """(max(h·tol, 4·eps·(1 + ‖q‖∞)), eps·(1 + ‖q‖∞)): the Newton stop, since a step below the
        rounding of q itself cannot shrink further, and the rounding of q, from which the energy's
        noise follows (energy_noise)."""
        m = zero
        for b in range(q.shape[1]):
            for r in range(12):
                m = wp.max(m, wp.abs(q[w, b][r]))
        rounding = EPS * (one + m)
        return wp.max(threshold, dtype(4.0) * rounding), rounding

    @wp.func
    def energy_noise(rounding: dtype, g_abs: dtype):
        """eps·(1 + ‖q‖∞)·‖g‖₁: how much the energy can change when q moves by its own rounding (a
        first-order bound).  The rounding of E's own sum (eps·|E|) is far smaller where q − q̃ and
        the joints' offsets are differences of nearly equal numbers: a predicted decrease −gᵀΔq under
        this is noise, and a line search on it only halves the step (measured: float32 double
        pendulums at dt 0.002 and 0.005 spent up to 15 iterations at α = 1/32 on such steps)."""
        return rounding * g_abs

    @wp.kernel(module="unique")
    def predict(
        q: wp.array2d(dtype=vec12), qd: wp.array2d(dtype=vec12), q_prev: wp.array2d(dtype=vec12),
        q_hist: wp.array2d(dtype=vec12), qd_hist: wp.array2d(dtype=vec12),
        q_tilde: wp.array2d(dtype=vec12), dof: wp.array(dtype=wp.int32), mass: wp.array2d(dtype=dtype),
        mc: wp.array2d(dtype=vec3), gravity: vec3, h: dtype, h_step: wp.array(dtype=dtype),
        status: wp.array(dtype=wp.int32), bend: int,
    ):  # fmt: skip
        """Implicit Euler: q̃ = qⁿ + h q̇ⁿ + h² (g, 0)  (M⁻¹f_g = (g, 0) exactly: gravity moves p only).
        BDF2 (ĥ = h_step[w] = 2h/3): q̃ = q̂ + ĥ v̂ + ĥ² (g, 0), q̂ = (4qⁿ − qⁿ⁻¹)/3, v̂ = (4q̇ⁿ − q̇ⁿ⁻¹)/3.

        Newton starts from qⁿ + h q̇ⁿ + h (q̇ⁿ − q̇ⁿ⁻¹), the last step's motion extrapolated to second
        order, not from q̃: q̃ lets a jointed body fall freely by h²g, which the joints then undo
        (a first Newton step of ~1e-3 m at dt 0.01, against ~1e-5 m from the extrapolation; float32
        cart-poles and double pendulums converge in 2.0 iterations instead of 2.7–2.9).  After a
        reset q̇ⁿ⁻¹ = q̇ⁿ, so the first guess is qⁿ + h q̇ⁿ."""
        w, b = wp.tid()
        qb = q[w, b]
        q_prev[w, b] = qb
        if dof[b] < 0 or status[w] != OK:
            q_tilde[w, b] = qb
            return
        he = h_step[w]
        qt = qb + h * qd[w, b]
        if he < h:
            # q̂ = qⁿ + (qⁿ − qⁿ⁻¹)/3, not (4qⁿ − qⁿ⁻¹)/3: the rounding is then that of the
            # increment, not of q (in float32, 4qⁿ/3 rounds by ~1e-7·|q| a step, always the same
            # way).  The divisions stay in dtype: a literal quotient such as 1.0/3.0 in a Warp
            # kernel is a float32 operation even inside dtype(...).
            q_hat = qb + (qb - q_hist[w, b]) / dtype(3.0)
            v_hat = qd[w, b] + (qd[w, b] - qd_hist[w, b]) / dtype(3.0)
            qt = q_hat + he * v_hat
        for r in range(3):
            qt[r] = qt[r] + he * he * gravity[r]
        q_tilde[w, b] = qt
        # Newton's initial guess, A turned by Cayley's rotation of its extrapolated step (retract,
        # rigid); with the bent trial steps, CartPole-v0's scene at dt 0.02 under random forces takes
        # 3.14 Newton iterations a step instead of 4.54 (float64, tests/test_hard_cases.py)
        d = h * (dtype(2.0) * qd[w, b] - qd_hist[w, b])
        q[w, b] = wp.where(bend != 0, retract(qb, d, one, mass[w, b], mc[w, b], 1), qb + d)

    @wp.func
    def cholesky(H: wp.array3d(dtype=dtype), w: int, n: int, first: wp.array(dtype=wp.int32)):
        """H = L Lᵀ in place on H's lower triangle (column w of the world-minor arrays); 0 when H is
        not positive definite.  With ``envelope``, row i starts at column first[i]: L has H's
        envelope (Cholesky fills nothing left of a row's first non-zero), so the skipped products
        are exact zeros and the result is the dense one."""
        for j in range(n):
            fj = int(0)
            if wp.static(envelope):
                fj = first[j]
            s = H[j, j, w]
            for k in range(fj, j):
                s -= H[j, k, w] * H[j, k, w]
            if not (s > zero) or not wp.isfinite(s):
                return 0
            d = wp.sqrt(s)
            H[j, j, w] = d
            for i in range(j + 1, n):
                fi = int(0)
                if wp.static(envelope):
                    fi = first[i]
                if fi <= j:
                    t = H[i, j, w]
                    for k in range(wp.max(fi, fj), j):
                        t -= H[i, k, w] * H[j, k, w]
                    H[i, j, w] = t / d
        return 1

    @wp.func
    def factored_solve(L: wp.array3d(dtype=dtype), g: wp.array2d(dtype=dtype), dq: wp.array2d(dtype=dtype), w: int,
                       n: int, first: wp.array(dtype=wp.int32)):  # fmt: skip
        """dq = −(L Lᵀ)⁻¹g by two triangular solves (n² multiply-adds, against n³/6 for the factor).

        Returns (ok, gᵀdq, ‖dq‖∞, ‖g‖₁); ok = 0 when the result is not finite.
        """
        for i in range(n):  # L y = −g
            fi = int(0)
            if wp.static(envelope):
                fi = first[i]
            t = -g[i, w]
            for k in range(fi, i):
                t -= L[i, k, w] * dq[k, w]
            dq[i, w] = t / L[i, i, w]
        gdq = zero
        dmax = zero
        g_abs = zero
        if wp.static(envelope):
            for ii in range(n):  # Lᵀ x = y by columns of Lᵀ (rows of L: their envelope)
                i = n - 1 - ii
                xi = dq[i, w] / L[i, i, w]
                dq[i, w] = xi
                for k in range(first[i], i):
                    dq[k, w] = dq[k, w] - L[i, k, w] * xi
            for i in range(n):
                gdq += g[i, w] * dq[i, w]
                dmax = wp.max(dmax, wp.abs(dq[i, w]))
                g_abs += wp.abs(g[i, w])
        else:
            for ii in range(n):  # Lᵀ x = y
                i = n - 1 - ii
                t = dq[i, w]
                for k in range(i + 1, n):
                    t -= L[k, i, w] * dq[k, w]
                dq[i, w] = t / L[i, i, w]
                gdq += g[i, w] * dq[i, w]
                dmax = wp.max(dmax, wp.abs(dq[i, w]))
                g_abs += wp.abs(g[i, w])
        if not wp.isfinite(gdq):
            return 0, zero, zero, zero
        return 1, gdq, dmax, g_abs

    @wp.func
    def cholesky_solve(H: wp.array3d(dtype=dtype), g: wp.array2d(dtype=dtype), dq: wp.array2d(dtype=dtype), w: int,
                       n: int, first: wp.array(dtype=wp.int32)):  # fmt: skip
        """dq = −H⁻¹g for world w by Cholesky, in place on H's lower triangle (world-minor arrays).

        Returns (ok, gᵀdq, ‖dq‖∞, ‖g‖₁); ok = 0 when H is not positive definite or the result not finite.
        """
        if cholesky(H, w, n, first) == 0:
            return 0, zero, zero, zero
        return factored_solve(H, g, dq, w, n, first)

    @wp.kernel(module="unique")
    def newton_direction(
        H: wp.array3d(dtype=dtype), L: wp.array3d(dtype=dtype), g: wp.array2d(dtype=dtype), n: int,
        first: wp.array(dtype=wp.int32), active: wp.array(dtype=wp.int32), chord: wp.array(dtype=wp.int32),
        dq: wp.array2d(dtype=dtype), gdq: wp.array(dtype=dtype), dq_max: wp.array(dtype=dtype),
        g_abs: wp.array(dtype=dtype), status: wp.array(dtype=wp.int32), factorizations: wp.array(dtype=wp.int32),
    ):  # fmt: skip
        """Newton direction of every active world, from H's Cholesky factor (kept in L) or, for a
        world whose iteration reuses the last factor (chord), from L as it is; a world whose
        system is bad is flagged."""
        w = wp.tid()
        if active[w] == 0:
            return
        ok = int(1)
        if chord[w] == 0:
            factorizations[w] = factorizations[w] + 1
            ok = cholesky(H, w, n, first)
            for i in range(n):
                for j in range(i + 1):
                    L[i, j, w] = H[i, j, w]
        s = zero
        m = zero
        ga = zero
        if ok != 0:
            ok, s, m, ga = factored_solve(L, g, dq, w, n, first)
        if ok == 0:
            status[w] = FAILED
            active[w] = 0
            return
        gdq[w] = s
        dq_max[w] = m
        g_abs[w] = ga

    @wp.kernel(module="unique")
    def trial(
        q: wp.array2d(dtype=vec12), dq: wp.array2d(dtype=dtype), dof: wp.array(dtype=wp.int32),
        mass: wp.array2d(dtype=dtype), mc: wp.array2d(dtype=vec3), alpha: wp.array(dtype=dtype),
        searching: wp.array(dtype=wp.int32), q_trial: wp.array2d(dtype=vec12), bend: int,
    ):  # fmt: skip
        """The trial point q + αΔq along the retraction's path (affine_body.retract; ``bend`` 0:
        the straight line)."""
        w, b = wp.tid()
        if searching[w] == 0:
            return  # keeps an accepted trial point until it is committed
        o = dof[b]
        qb = q[w, b]
        if o >= 0:
            d = vec12()
            for r in range(12):
                d[r] = dq[o + r, w]
            if bend != 0:
                qb = retract(qb, d, alpha[w], mass[w, b], mc[w, b], 0)
            else:
                qb = qb + alpha[w] * d
        q_trial[w, b] = qb

    @wp.kernel(module="unique")
    def accept(
        q: wp.array2d(dtype=vec12), E0: wp.array2d(dtype=dtype), E1: wp.array2d(dtype=dtype), nterms: int,
        gdq: wp.array(dtype=dtype), g_abs: wp.array(dtype=dtype),
        dq_max: wp.array(dtype=dtype), threshold: dtype, min_alpha: dtype,
        alpha: wp.array(dtype=dtype), searching: wp.array(dtype=wp.int32), take: wp.array(dtype=wp.int32),
        chord: wp.array(dtype=wp.int32), active: wp.array(dtype=wp.int32), converged: wp.array(dtype=wp.int32),
        remaining: wp.array(dtype=wp.int32),
    ):  # fmt: skip
        """Armijo test on the world's own energy; halve α on failure (a step under the tolerance, or
        one whose predicted decrease the energy's rounding cannot show, is accepted without it).

        Energies equal to within rounding count as no increase (the float32 noise floor); a world
        whose search runs out takes no step and stops: converged if its Newton step was already
        within 1000× the tolerance, else reported as not converged.  A step from a reused factor
        (chord) is tried at α = 1 only and ends the solve only under the tolerance; rejected, it is
        not taken (take 0) and the next iteration refactors.
        """
        w = wp.tid()
        if searching[w] == 0:
            return
        e0 = zero
        e1 = zero
        mag = zero
        for t in range(nterms):
            e0 += E0[w, t]
            e1 += E1[w, t]
            mag += wp.abs(E0[w, t]) + wp.abs(E1[w, t])
        floor, rounding = noise_floor(q, w, threshold)
        unresolved = -gdq[w] <= dtype(1600.0) * EPS * wp.abs(e0) or -gdq[w] <= energy_noise(rounding, g_abs[w])
        if dq_max[w] < dtype(10.0) * floor or unresolved:
            # taken whole (α = 1, the first trial), as the fused step (fused.whole_step): within 10×
            # the noise floor, or a predicted decrease below the energy's rounding, which the test
            # could only halve on noise; the solve ends here if the step is under the tolerance, or
            # unresolved and within 1000× it (take 2)
            searching[w] = 0
            done = dq_max[w] < floor or (unresolved and dq_max[w] < dtype(1000.0) * floor)
            take[w] = wp.where(done, 2, 1)
            if chord[w] != 0 and dq_max[w] >= floor:
                take[w] = 1
            return
        a = alpha[w]
        noise = dtype(16.0) * EPS * mag
        if e1 <= e0 + dtype(1.0e-4) * a * gdq[w] + noise and wp.isfinite(e1):
            searching[w] = 0
            take[w] = 1
            if e0 - e1 <= noise:
                take[w] = 2  # no decrease the precision can resolve: this is as converged as it gets
        elif chord[w] != 0:
            searching[w] = 0
            take[w] = 0
        elif a <= min_alpha:
            searching[w] = 0
            take[w] = 0
            active[w] = 0
            if dq_max[w] < dtype(1000.0) * floor:
                converged[w] = 1
        else:
            alpha[w] = a * dtype(0.5)
            wp.atomic_add(remaining, 0, 1)

    @wp.kernel(module="unique")
    def commit(
        q: wp.array2d(dtype=vec12), q_trial: wp.array2d(dtype=vec12), take: wp.array(dtype=wp.int32),
    ):  # fmt: skip
        w, b = wp.tid()
        if take[w] != 0:
            q[w, b] = q_trial[w, b]

    @wp.kernel(module="unique")
    def converge(
        q: wp.array2d(dtype=vec12), take: wp.array(dtype=wp.int32), dq_max: wp.array(dtype=dtype), threshold: dtype,
        alpha: wp.array(dtype=dtype), reuse: int, chord: wp.array(dtype=wp.int32), d_prev: wp.array(dtype=dtype),
        active: wp.array(dtype=wp.int32), converged: wp.array(dtype=wp.int32), iterations: wp.array(dtype=wp.int32),
        max_iterations: int, remaining: wp.array(dtype=wp.int32),
    ):  # fmt: skip
        """‖Δq‖∞ below h·tol (or q's rounding), or a step whose energy change is below rounding:
        the step just taken was the last one needed.  At the iteration cap a world stops unconverged.
        The next iteration reuses the factor after a full step taken whole (with ``reuse``), and
        keeps reusing it while the steps shrink 8× an iteration (fused.chord_step)."""
        w = wp.tid()
        if active[w] == 0:
            return
        iterations[w] = iterations[w] + 1
        taken = take[w]
        stalled = taken == 2
        take[w] = 0
        was_chord = chord[w]
        retry = was_chord != 0 and taken == 0
        if was_chord != 0:
            chord[w] = wp.where(taken != 0 and dq_max[w] <= dtype(0.125) * d_prev[w], 1, 0)
        else:
            chord[w] = wp.where(taken != 0 and alpha[w] == one, reuse, 0)
        d_prev[w] = dq_max[w]
        floor, rounding = noise_floor(q, w, threshold)
        if retry:
            if iterations[w] >= max_iterations:
                active[w] = 0
            else:
                wp.atomic_add(remaining, 0, 1)
        elif dq_max[w] < floor or stalled:
            converged[w] = 1
            active[w] = 0
        elif iterations[w] >= max_iterations:
            active[w] = 0
        else:
            wp.atomic_add(remaining, 0, 1)

    @wp.kernel(module="unique")
    def start(
        status: wp.array(dtype=wp.int32), active: wp.array(dtype=wp.int32), iterations: wp.array(dtype=wp.int32),
        converged: wp.array(dtype=wp.int32), take: wp.array(dtype=wp.int32), chord: wp.array(dtype=wp.int32),
        factorizations: wp.array(dtype=wp.int32),
    ):  # fmt: skip
        """A world takes part in the solve while healthy."""
        w = wp.tid()
        factorizations[w] = 0
        active[w] = wp.where(status[w] == OK, 1, 0)
        iterations[w] = 0
        converged[w] = 0
        take[w] = 0
        chord[w] = 0

    @wp.kernel(module="unique")
    def finalize(
        q: wp.array2d(dtype=vec12), q_prev: wp.array2d(dtype=vec12), qd: wp.array2d(dtype=vec12),
        q_hist: wp.array2d(dtype=vec12), qd_hist: wp.array2d(dtype=vec12),
        dof: wp.array(dtype=wp.int32), h: dtype, h_step: wp.array(dtype=dtype), status: wp.array(dtype=wp.int32),
    ):  # fmt: skip
        """q̇ⁿ⁺¹ = (qⁿ⁺¹ − qⁿ)/h, or (3qⁿ⁺¹ − 4qⁿ + qⁿ⁻¹)/(2h) for a BDF2 step; the history shifts.
        A failed world keeps its last good state."""
        w, b = wp.tid()
        if status[w] != OK:
            q[w, b] = q_prev[w, b]
            return
        if dof[b] >= 0:
            v = (q[w, b] - q_prev[w, b]) / h
            if h_step[w] < h:
                # the differences first: 3qⁿ⁺¹ − 4qⁿ + qⁿ⁻¹ cancels to ~eps·|q| in float32
                v = (dtype(3.0) * (q[w, b] - q_prev[w, b]) - (q_prev[w, b] - q_hist[w, b])) / (dtype(2.0) * h)
            qd_hist[w, b] = qd[w, b]
            qd[w, b] = v
        q_hist[w, b] = q_prev[w, b]

    @wp.kernel(module="unique")
    def open_step(
        q: wp.array2d(dtype=vec12), qd: wp.array2d(dtype=vec12), status: wp.array(dtype=wp.int32),
        fresh: wp.array(dtype=wp.int32), h: dtype, bdf2: int, h_step: wp.array(dtype=dtype),
    ):  # fmt: skip
        """A world with a non-finite q or q̇ fails; each world's effective step: ĥ = 2h/3 for BDF2,
        but h (an implicit Euler step) for a world without a past step (``fresh``).  BDF2 started
        from a past invented as "the velocity was constant" takes a first velocity of (2/3)h·a for
        h·a, an O(h) error it never loses (measured: first-order global error); an implicit Euler
        first step is O(h²) accurate, which keeps BDF2 second order."""
        w, b = wp.tid()
        if b == 0:
            he = h
            if bdf2 != 0 and fresh[w] == 0:
                he = dtype(2.0) * h / dtype(3.0)
            h_step[w] = he
            fresh[w] = 0
        for r in range(12):
            if not (wp.isfinite(q[w, b][r]) and wp.isfinite(qd[w, b][r])):
                status[w] = FAILED

    return dict(
        predict=predict, start=start, newton_direction=newton_direction, cholesky_solve=cholesky_solve,
        factored_solve=factored_solve,
        noise_floor=noise_floor, energy_noise=energy_noise, trial=trial, accept=accept, commit=commit,
        converge=converge, finalize=finalize, open_step=open_step,
    )  # fmt: skip
