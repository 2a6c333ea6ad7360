"""Per-world Newton kernels: prediction, dense Cholesky solve, line search, step finalisation.

One thread per world owns that world's small dense system (12 × free bodies unknowns), so no
world waits on another and a failing world touches only its own rows.
"""

import functools

import numpy as np
import warp as wp

from ..constitutions import affine_body
from ..sim.status import BREAKDOWN, NONFINITE, OK, UNCONVERGED
from ..core.warp_ops import ops

# State.fresh: 0, the world's next step is a BDF2 step (under BDF2); RESET, its state was set (it has
# no past) or a limit was engaged at the end of the step before its last; RESTART, a limit was
# engaged at the end of its last step (coordinates.restart_engaged).  Either makes the next step an
# implicit Euler one (open_body).
RESET, RESTART = 1, 2
# State.fresh of a world whose state a door just wrote (rows.restart_q, kinematics' restart): a
# RESET to the step; the energy test (energy_gain) also takes its energy anew before that step
SET = 3


@wp.func
def next_attempt(status: wp.array(dtype=wp.int32), fresh: wp.array(dtype=wp.int32),
                 substeps: wp.array(dtype=wp.int32), idle: wp.array(dtype=wp.int32), w: int, n: int, next_n: int):  # fmt: skip
    """A retried world whose attempt of ``n`` substeps did not come through (solver.retry): it tries
    ``next_n`` substeps from the state before the step (an implicit Euler start: RESTART), or, with
    next_n 0, idles with its status kept (returns 1 then: its retry is over)."""
    if next_n > 0:
        status[w] = OK
        fresh[w] = RESTART
        substeps[w] = next_n
        return 0
    idle[w] = 1
    substeps[w] = n
    return 1


@wp.func
def keep_restart(fresh: wp.array(dtype=wp.int32), w: int):
    """World w's step has begun: RESTART becomes RESET (one more implicit Euler step after the last
    step that ends with a limit engaged), RESET becomes 0."""
    fresh[w] = wp.where(fresh[w] == RESTART, RESET, 0)


# the names kernels() returns
_PUBLIC = (
    "predict", "start", "newton_direction", "h_row", "row_first", "column_end", "cholesky_solve", "factored_solve",
    "reductions", "noise_floor", "energy_noise", "trial", "accept", "commit", "converge", "finalize", "open_step",
    "open_body", "predict_body", "finalize_body", "limit_reach",
)  # fmt: skip


@functools.lru_cache(maxsize=None)
def _scalars(dtype):
    """(vec3, vec12, 0, 1, machine epsilon) of ``dtype``."""
    o = ops(dtype)
    EPS = dtype(float(np.finfo(np.float32 if dtype == wp.float32 else np.float64).eps))
    return o.vec3, o.vec12, dtype(0.0), dtype(1.0), EPS


# H's block band, packed ("band": a scene whose joints couple each free body to the one before it at
# most, Model.banded): rows of body b ≥ 1 from column 12(b − 1), so a body's 12 rows hold
# BAND_BODY words (13 … 24 each) after the first body's triangle of BAND_FIRST
BAND_FIRST, BAND_BODY = 78, 222


def h_words(n: int, packed: bool = False, band: bool = False) -> int:
    """Words of H in a scratch column: n² square, n(n+1)/2 packed, the block band's
    78 + 222(n/12 − 1) (``band``, n a multiple of 12; the packed triangle up to 24 unknowns)."""
    if band and n > 24:
        return BAND_FIRST + BAND_BODY * (n // 12 - 1)
    return n * (n + 1) // 2 if packed or band else n * n


def h_row_starts(n: int, packed: bool = False, band: bool = False) -> np.ndarray:
    """(n,) where row i starts: entry (i, j) of a scratch column at h_row_starts[i] + j (h_row, on the
    host: for reading a scratch back; row i holds columns h_row_first(n)[i] … i)."""
    i = np.arange(n)
    if not (packed or band):
        return i * n
    rows = i * (i + 1) // 2
    if band:
        b, k = i // 12, i % 12
        rows = np.where(i >= 24, BAND_FIRST + (BAND_BODY - 12) * (b - 1) + 13 * k + k * (k - 1) // 2, rows)
    return rows


def h_row_first(n: int, band: bool = False) -> np.ndarray:
    """(n,) the first column each row of H stores: 12(b − 1) for body b ≥ 1 in the block band, else 0."""
    i = np.arange(n)
    return np.maximum(i // 12 - 1, 0) * 12 if band else np.zeros(n, dtype=int)


@functools.lru_cache(maxsize=None)
def _rows(packed, band=False):
    """(h_row, row_first, column_end): where a row of H starts in a scratch column (square,
    ``packed`` or the packed block ``band``), the first column a row stores, and the end of the rows
    that store a column."""

    @wp.func
    def h_row(i: int, n: int):
        """Where row i of H starts in a scratch column (entry (i, j) at (h_row(i, n) + j)·T + w): i·n
        square, i(i+1)/2 packed; in the band, past the first two bodies (where it is the packed
        triangle), 78 + 210(b − 1) + 13k + k(k − 1)/2 for row k of body b (h_row_starts)."""
        if wp.static(band):
            if i >= 24:
                b = i // 12
                k = i - 12 * b
                return BAND_FIRST + (BAND_BODY - 12) * (b - 1) + 13 * k + ((k * (k - 1)) >> 1)
        if wp.static(packed or band):
            return (i * (i + 1)) >> 1
        return i * n

    @wp.func
    def row_first(i: int):
        """The first column row i stores: 12(b − 1) for body b ≥ 1 in the band, else 0."""
        if wp.static(band):
            return wp.max(i // 12 - 1, 0) * 12
        return 0

    @wp.func
    def column_end(j: int, n: int):
        """One past the last row that stores column j: the next body's in the band, else n."""
        if wp.static(band):
            return wp.min(n, (j // 12 + 2) * 12)
        return n

    return h_row, row_first, column_end


@functools.lru_cache(maxsize=None)
def _noise_funcs(dtype):
    """The Newton stop and the energy's noise, from the rounding of q."""
    vec3, vec12, zero, one, EPS = _scalars(dtype)

    @wp.func
    def noise_floor(q: wp.array2d(dtype=vec12), w: int, threshold: dtype):
        """(max(h·tol, 4·eps·(1 + ‖q‖∞)), eps·(1 + ‖q‖∞)): the Newton stop, since a step below the
        rounding of q itself cannot shrink further, and the rounding of q, from which the energy's
        noise follows (energy_noise)."""
        m = zero
        for b in range(q.shape[1]):
            # a body's 12 values loaded at once and reduced in registers (an element at a time in
            # a loop, each waits on its own load: the fused step's chain, every iteration)
            m = wp.max(m, wp.max(wp.abs(q[w, b])))
        rounding = EPS * (one + m)
        return wp.max(threshold, dtype(4.0) * rounding), rounding

    @wp.func
    def energy_noise(rounding: dtype, g_abs: dtype):
        """eps·(1 + ‖q‖∞)·‖g‖₁: how much the energy can change when q moves by its own rounding (a
        first-order bound).  The rounding of E's own sum (eps·|E|) is far smaller where q − q̃ and
        the joints' offsets are differences of nearly equal numbers: a predicted decrease −gᵀΔq under
        this is noise, and a line search on it only halves the step, iteration after iteration."""
        return rounding * g_abs

    return dict(noise_floor=noise_floor, energy_noise=energy_noise)


@functools.lru_cache(maxsize=None)
def _reach_func(dtype):
    """limit_reach: the fraction of the extrapolated step a world's limits leave its guess."""

    @wp.func
    def limit_reach(coord: wp.array2d(dtype=dtype), rate: wp.array2d(dtype=dtype), lim_ids: wp.array(dtype=wp.int32),
                    lo: wp.array2d(dtype=dtype), up: wp.array2d(dtype=dtype), count: int, h: dtype, w: int,
                    beta: dtype):  # fmt: skip
        """min(β, β_k) over world w's ``count`` limits (joint lim_ids[k], coordinate x = coord[w, j],
        rate ẋ = rate[w, j], bounds l = lo[w, k] ≤ x ≤ u = up[w, k], step h [s]), with hẋ the
        coordinate's last step: past a bound by e > 0 (the limit acts), β_k = 0 (the guess is qⁿ)
        unless the coordinate rests (|hẋ| ≤ e/16: the extrapolation is kept); inside [l, u], β_k =
        (u − x)/(hẋ) where x + hẋ > u and (l − x)/(hẋ) where x + hẋ < l (the guess stops at the
        bound, to first order); else 1.

        Why: on the one-sided cubic E = s e³, Newton from an overrun e₀ far past the solution's e*
        converges at rate 1/2 (e ← e/2 + e*²/2e), ~log₂(e₀/e*) iterations: an extrapolation through
        the bound at an impact, or one that carries the motion of before an impact on after it,
        starts it there.  Only the guess moves: the step's solution is the same."""
        b = beta
        for k in range(count):
            j = lim_ids[k]
            x = coord[w, j]
            step = h * rate[w, j]
            move = wp.abs(step)
            # the overrun; inside [l, u], minus the distance to the nearer bound
            e = wp.max(x - up[w, k], lo[w, k] - x)
            if e > dtype(0.0):
                if dtype(16.0) * move > e:
                    b = dtype(0.0)
            else:
                reach = wp.where(step > dtype(0.0), up[w, k] - x, x - lo[w, k])  # the bound ahead
                if move > reach:
                    b = wp.min(b, reach / move)
        return b

    return limit_reach


@functools.lru_cache(maxsize=None)
def _predict_funcs(dtype):
    """A step's prediction and initial guess (predict_body, predict; limit_reach from
    ``_reach_func``); its opening (open_body, open_step) from ``_open_funcs``."""
    vec3, vec12, zero, one, EPS = _scalars(dtype)
    retract = affine_body.kernels(dtype).retract
    limit_reach = _reach_func(dtype)

    @wp.func
    def predict_body(
        q: wp.array2d(dtype=vec12), qd: wp.array2d(dtype=vec12), q_prev: wp.array2d(dtype=vec12),
        q_hist: wp.array2d(dtype=vec12), qd_hist: wp.array2d(dtype=vec12), qd_hist2: wp.array2d(dtype=vec12),
        order3: wp.array2d(dtype=wp.int32), calm: wp.array(dtype=wp.int32), q_tilde: wp.array2d(dtype=vec12),
        dof: wp.array(dtype=wp.int32), mass: wp.array2d(dtype=dtype),
        mc: wp.array2d(dtype=vec3), gravity: vec3, h: dtype, h_step: wp.array(dtype=dtype),
        status: wp.array(dtype=wp.int32), beta: dtype, w: int, b: int,
    ):  # fmt: skip
        """Implicit Euler: q̃ = qⁿ + h q̇ⁿ + h² (g, 0)  (M⁻¹f_g = (g, 0) exactly: gravity moves p only).
        BDF2 (ĥ = h_step[w] = 2h/3): q̃ = q̂ + ĥ v̂ + ĥ² (g, 0), q̂ = (4qⁿ − qⁿ⁻¹)/3, v̂ = (4q̇ⁿ − q̇ⁿ⁻¹)/3.

        Newton starts from the last steps' motion extrapolated to second order: before an implicit
        Euler step from qⁿ + h q̇ⁿ + h (q̇ⁿ − q̇ⁿ⁻¹), exact on quadratic motion where q̇ⁿ = (qⁿ − qⁿ⁻¹)/h;
        before a BDF2 step from qⁿ + (qⁿ − qⁿ⁻¹) + h (q̇ⁿ − q̇ⁿ⁻¹), exact on quadratic motion for that q̇
        and for BDF2's, the slope at tⁿ of the quadratic through qⁿ⁻², qⁿ⁻¹, qⁿ (with which the first
        form overshoots by h²q̈/2, as far as q̃ is off).  Not from q̃: q̃ lets a jointed body fall
        freely by h²g, which the joints then undo: a first Newton step far longer than the
        extrapolation's error, and more iterations.  Where the third-order extrapolation
        qⁿ + h(3q̇ⁿ − 3q̇ⁿ⁻¹ + q̇ⁿ⁻²) would have guessed the body's last step better (``order3``, set
        by finalize_body) and the world's controls are those of its last two steps (``calm``,
        open_body), it is used instead: smooth motion then starts closer (before a BDF2 step
        qⁿ + (qⁿ − qⁿ⁻¹) + h(3q̇ⁿ − 4q̇ⁿ⁻¹ + q̇ⁿ⁻²)/2, exact on cubic motion); across a change of
        control its jerk is the change's, and it guesses worse than second order.  After a reset
        q̇ⁿ⁻² = q̇ⁿ⁻¹ = q̇ⁿ, so the first guess is qⁿ + h q̇ⁿ.  A world whose limits act or are in
        reach takes the fraction ``beta`` of that step (limit_reach; 1 elsewhere).  A retry
        from a fresh factor starts from q̃ instead (fused.solve_world, converge)."""
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
        # rigid): a straight step in A would leave the rotations by ~½θ², which the stiff
        # orthogonality energy then pulls back over several iterations (docs/design.md §4)
        if he < h:
            # a BDF2 step's q̇ⁿ is the slope at tⁿ of the quadratic through qⁿ⁻², qⁿ⁻¹, qⁿ, not the
            # mean slope (qⁿ − qⁿ⁻¹)/h of the last step: h(2q̇ⁿ − q̇ⁿ⁻¹) would overshoot by h²q̈/2
            step = qb - q_hist[w, b]
            d = step + h * (qd[w, b] - qd_hist[w, b])
            if order3[w, b] != 0 and calm[w] >= 2:
                d = step + h * (dtype(1.5) * qd[w, b] - dtype(2.0) * qd_hist[w, b] + dtype(0.5) * qd_hist2[w, b])
            d = beta * d
        else:
            hb = h * beta  # (h exactly where β = 1)
            d = hb * (dtype(2.0) * qd[w, b] - qd_hist[w, b])
            if order3[w, b] != 0 and calm[w] >= 2:
                d = hb * (dtype(3.0) * (qd[w, b] - qd_hist[w, b]) + qd_hist2[w, b])
        q[w, b] = retract(qb, d, one, mass[w, b], mc[w, b], 1)

    @wp.kernel(module="unique")
    def predict(
        q: wp.array2d(dtype=vec12), qd: wp.array2d(dtype=vec12), q_prev: wp.array2d(dtype=vec12),
        q_hist: wp.array2d(dtype=vec12), qd_hist: wp.array2d(dtype=vec12), qd_hist2: wp.array2d(dtype=vec12),
        order3: wp.array2d(dtype=wp.int32), calm: wp.array(dtype=wp.int32), q_tilde: wp.array2d(dtype=vec12),
        dof: wp.array(dtype=wp.int32), mass: wp.array2d(dtype=dtype), mc: wp.array2d(dtype=vec3), gravity: vec3, h: dtype,
        h_step: wp.array(dtype=dtype), status: wp.array(dtype=wp.int32), coord: wp.array2d(dtype=dtype),
        rate: wp.array2d(dtype=dtype), rlim_ids: wp.array(dtype=wp.int32), rlim_lo: wp.array2d(dtype=dtype),
        rlim_up: wp.array2d(dtype=dtype), num_rlim: int, plim_ids: wp.array(dtype=wp.int32),
        plim_lo: wp.array2d(dtype=dtype), plim_up: wp.array2d(dtype=dtype), num_plim: int,
    ):  # fmt: skip
        """predict_body of body b of world w, its step's fraction from the world's limits
        (limit_reach)."""
        w, b = wp.tid()
        beta = limit_reach(coord, rate, rlim_ids, rlim_lo, rlim_up, num_rlim, h, w, one)
        beta = limit_reach(coord, rate, plim_ids, plim_lo, plim_up, num_plim, h, w, beta)
        predict_body(q, qd, q_prev, q_hist, qd_hist, qd_hist2, order3, calm, q_tilde, dof, mass, mc, gravity, h, h_step,
                     status, beta, w, b)  # fmt: skip

    return dict(predict_body=predict_body, predict=predict, limit_reach=limit_reach, **_open_funcs(dtype))


@functools.lru_cache(maxsize=None)
def _open_funcs(dtype):
    """A step's opening: the finite check, the effective step ĥ and the controls' calm count
    (open_body, open_step)."""
    vec12 = _scalars(dtype)[1]

    @wp.func
    def open_body(
        q: wp.array2d(dtype=vec12), qd: wp.array2d(dtype=vec12), status: wp.array(dtype=wp.int32),
        fresh: wp.array(dtype=wp.int32), h: dtype, bdf2: int, h_step: wp.array(dtype=dtype),
        control: wp.array2d(dtype=dtype), control_prev: wp.array2d(dtype=dtype), calm: wp.array(dtype=wp.int32),
        w: int, b: int, clear: int,
    ):  # fmt: skip
        """A world with a non-finite q or q̇ fails; each world's effective step: ĥ = 2h/3 for BDF2,
        but h (an implicit Euler step) for a world whose history restarts (``fresh`` nonzero):
        - its state was set, so it has no past.  BDF2 started from a past invented as "the velocity
          was constant" takes a first velocity of (2/3)h·a for h·a, an O(h) error it never loses
          (its global error would be first order); an implicit Euler first step is O(h²) accurate,
          which keeps BDF2 second order.
        - a limit was engaged at the end of one of its last two steps (coordinates.restart_engaged).
          A stiff limit's impulse acts within a step or two; BDF2's two-step history would span it,
          and its velocity q̇ⁿ⁺¹ = (3qⁿ⁺¹ − 4qⁿ + qⁿ⁻¹)/(2h) then keeps changing after the impulse with
          no force acting (free motion carries q̇ⁿ⁺¹ − q̇ⁿ = (q̇ⁿ − q̇ⁿ⁻¹)/3 on, adding half of the last
          step's change), so a world leaves a limit faster than it arrived.  Implicit Euler steps
          while a limit acts and one step after it releases leave a history of free motion.
        (Body 0 sets the world's.)  ``calm``: the steps in a row, up to 2, whose controls are the
        last step's (predict_body extrapolates the last accelerations to third order only across
        steps of one control).  ``clear``: the world's step has begun (keep_restart; else the
        step's close does it: the fused step)."""
        if b == 0:
            same = int(1)
            for d in range(control.shape[1]):
                if control[w, d] != control_prev[w, d]:
                    same = 0
                control_prev[w, d] = control[w, d]
            calm[w] = wp.where(same != 0 and fresh[w] == 0, wp.min(calm[w] + 1, 2), 0)
            he = h
            if bdf2 != 0 and fresh[w] == 0:
                he = dtype(2.0) * h / dtype(3.0)
            h_step[w] = he
            if clear != 0:
                keep_restart(fresh, w)
        if not (wp.isfinite(q[w, b]) and wp.isfinite(qd[w, b])):
            status[w] = NONFINITE

    @wp.kernel(module="unique")
    def open_step(
        q: wp.array2d(dtype=vec12), qd: wp.array2d(dtype=vec12), status: wp.array(dtype=wp.int32),
        fresh: wp.array(dtype=wp.int32), h: dtype, bdf2: int, h_step: wp.array(dtype=dtype),
        control: wp.array2d(dtype=dtype), control_prev: wp.array2d(dtype=dtype), calm: wp.array(dtype=wp.int32),
    ):  # fmt: skip
        """open_body of body b of world w."""
        w, b = wp.tid()
        open_body(q, qd, status, fresh, h, bdf2, h_step, control, control_prev, calm, w, b, 1)

    return dict(open_body=open_body, open_step=open_step)


@functools.lru_cache(maxsize=None)
def _finalize_funcs(dtype):
    """A step's close: velocities and history (finalize_body, finalize)."""
    vec3, vec12, zero, one, EPS = _scalars(dtype)

    @wp.func
    def finalize_body(
        q: wp.array2d(dtype=vec12), q_prev: wp.array2d(dtype=vec12), qd: wp.array2d(dtype=vec12),
        q_hist: wp.array2d(dtype=vec12), qd_hist: wp.array2d(dtype=vec12), qd_hist2: wp.array2d(dtype=vec12),
        order3: wp.array2d(dtype=wp.int32), dof: wp.array(dtype=wp.int32), h: dtype, h_step: wp.array(dtype=dtype),
        status: wp.array(dtype=wp.int32), w: int, b: int,
    ):  # fmt: skip
        """q̇ⁿ⁺¹ = (qⁿ⁺¹ − qⁿ)/h, or (3qⁿ⁺¹ − 4qⁿ + qⁿ⁻¹)/(2h) for a BDF2 step; the history shifts.
        ``order3``: whether the third-order extrapolation of the velocity (predict_body) would have
        guessed q̇ⁿ⁺¹ better than the second-order one (its third difference smaller than the
        second).  A failed world keeps its last good state."""
        if status[w] != OK:
            q[w, b] = q_prev[w, b]
            return
        if dof[b] >= 0:
            # one division, not twelve (a vector over a scalar divides each entry: ~150 instructions
            # of the fused step's code, run once a step)
            dx = q[w, b] - q_prev[w, b]
            v = dx * (one / h)
            if h_step[w] < h:
                # the differences first: 3qⁿ⁺¹ − 4qⁿ + qⁿ⁻¹ cancels to ~eps·|q| in float32
                v = (dtype(3.0) * dx - (q_prev[w, b] - q_hist[w, b])) * (one / (dtype(2.0) * h))
            v0 = qd[w, b]
            v1 = qd_hist[w, b]
            d2 = v - dtype(2.0) * v0 + v1
            d3 = d2 - (v0 - dtype(2.0) * v1 + qd_hist2[w, b])
            order3[w, b] = wp.where(wp.max(wp.abs(d3)) < wp.max(wp.abs(d2)), 1, 0)
            qd_hist2[w, b] = v1
            qd_hist[w, b] = v0
            qd[w, b] = v
        q_hist[w, b] = q_prev[w, b]

    @wp.kernel(module="unique")
    def finalize(
        q: wp.array2d(dtype=vec12), q_prev: wp.array2d(dtype=vec12), qd: wp.array2d(dtype=vec12),
        q_hist: wp.array2d(dtype=vec12), qd_hist: wp.array2d(dtype=vec12), qd_hist2: wp.array2d(dtype=vec12),
        order3: wp.array2d(dtype=wp.int32), dof: wp.array(dtype=wp.int32), h: dtype, h_step: wp.array(dtype=dtype),
        status: wp.array(dtype=wp.int32),
    ):  # fmt: skip
        """finalize_body of body b of world w."""
        w, b = wp.tid()
        finalize_body(q, q_prev, qd, q_hist, qd_hist, qd_hist2, order3, dof, h, h_step, status, w, b)

    return dict(finalize_body=finalize_body, finalize=finalize)


# The Newton scratch of a world (or of a fused thread) is column w of n × n and n × 1 arrays with
# one column per world or thread, stored flat: H's entry (i, j) at (i·n + j)·T + w, g's entry i
# at i·T + w (T columns; neighbouring threads read neighbouring words).  Flat 1-D indices, kept
# as running offsets in the loops: 3-D indexing would cost every access of the Newton system
# three multiplies and three negative-index tests.


@functools.lru_cache(maxsize=None)
def _tile_row(dtype):
    """tile_row: a row of a tile below the diagonal solved against the diagonal tile's factor."""

    @wp.func
    def tile_row(H: wp.array(dtype=dtype), r: int, c: int, T: int, t0: dtype, t1: dtype, t2: dtype, t3: dtype,
                 i0: dtype, i1: dtype, i2: dtype, i3: dtype, l10: dtype, l20: dtype, l21: dtype, l30: dtype,
                 l31: dtype, l32: dtype):  # fmt: skip
        """Row (t0 … t3) of a tile below the diagonal solved against the diagonal tile's factor
        (x L_JJᵀ = t: l_ab its entries below the diagonal, i_a the reciprocals of its diagonal),
        stored from H[r + c] on."""
        x0 = t0 * i0
        x1 = (t1 - x0 * l10) * i1
        x2 = (t2 - x0 * l20 - x1 * l21) * i2
        H[r + c] = x0
        H[r + c + T] = x1
        H[r + c + 2 * T] = x2
        H[r + c + 3 * T] = (t3 - x0 * l30 - x1 * l31 - x2 * l32) * i3

    return tile_row


@functools.lru_cache(maxsize=None)
def _cholesky_dense(dtype, packed, band=False):
    """cholesky_dense: the dense factor by 4 × 4 tiles (square, ``packed`` or ``band`` scratch)."""
    vec3, vec12, zero, one, EPS = _scalars(dtype)
    h_row, row_first, column_end = _rows(packed, band)
    tile_row = _tile_row(dtype)

    @wp.func
    def cholesky_dense(H: wp.array(dtype=dtype), w: int, n: int, T: int):
        """H = L Lᵀ in place on H's lower triangle (flat, column w of T); 0 when H is not positive
        definite.  Left-looking by 4 × 4 tiles (n a multiple of 4: 12 per body): each tile of L is
        its H tile less Σ_k L[I, k] L[J, k]ᵀ, sixteen sums in registers from eight loads per k (one
        row at a time loads five values for four products), then divided by the diagonal tile's
        factor, formed in registers; reciprocals of the diagonal, so a column's n − j divisions are
        one division and multiplies (a GPU's IEEE division is a call of ~20 instructions).  In the
        block band the sums start at a row's first stored column and the tiles stop at the next
        body's rows: L keeps H's band (Cholesky fills nothing left of a row's first non-zero), so
        the products skipped are exact zeros and L is the dense factor's, bit for bit."""
        J = int(0)
        while J < n:
            c = J * T
            j0 = h_row(J, n) * T + w  # rows J … J + 3
            j1 = h_row(J + 1, n) * T + w
            j2 = h_row(J + 2, n) * T + w
            j3 = h_row(J + 3, n) * T + w
            a00 = H[j0 + c]
            a10 = H[j1 + c]
            a11 = H[j1 + c + T]
            a20 = H[j2 + c]
            a21 = H[j2 + c + T]
            a22 = H[j2 + c + 2 * T]
            a30 = H[j3 + c]
            a31 = H[j3 + c + T]
            a32 = H[j3 + c + 2 * T]
            a33 = H[j3 + c + 3 * T]
            lo = row_first(J)
            p = lo * T
            for k in range(lo, J):
                v0 = H[j0 + p]
                v1 = H[j1 + p]
                v2 = H[j2 + p]
                v3 = H[j3 + p]
                a00 -= v0 * v0
                a10 -= v1 * v0
                a11 -= v1 * v1
                a20 -= v2 * v0
                a21 -= v2 * v1
                a22 -= v2 * v2
                a30 -= v3 * v0
                a31 -= v3 * v1
                a32 -= v3 * v2
                a33 -= v3 * v3
                p += T
            # the diagonal tile's factor, in registers
            if not (a00 > zero) or not wp.isfinite(a00):
                return 0
            d0 = wp.sqrt(a00)
            i0 = one / d0
            l10 = a10 * i0
            l20 = a20 * i0
            l30 = a30 * i0
            a11 -= l10 * l10
            if not (a11 > zero) or not wp.isfinite(a11):
                return 0
            d1 = wp.sqrt(a11)
            i1 = one / d1
            l21 = (a21 - l20 * l10) * i1
            l31 = (a31 - l30 * l10) * i1
            a22 -= l20 * l20 + l21 * l21
            if not (a22 > zero) or not wp.isfinite(a22):
                return 0
            d2 = wp.sqrt(a22)
            i2 = one / d2
            l32 = (a32 - l30 * l20 - l31 * l21) * i2
            a33 -= l30 * l30 + l31 * l31 + l32 * l32
            if not (a33 > zero) or not wp.isfinite(a33):
                return 0
            d3 = wp.sqrt(a33)
            i3 = one / d3
            H[j0 + c] = d0
            H[j1 + c] = l10
            H[j1 + c + T] = d1
            H[j2 + c] = l20
            H[j2 + c + T] = l21
            H[j2 + c + 2 * T] = d2
            H[j3 + c] = l30
            H[j3 + c + T] = l31
            H[j3 + c + 2 * T] = l32
            H[j3 + c + 3 * T] = d3
            # the tiles below it: rows I … I + 3, columns J … J + 3
            I = J + 4
            end = column_end(J, n)
            while I < end:
                r0 = h_row(I, n) * T + w
                r1 = h_row(I + 1, n) * T + w
                r2 = h_row(I + 2, n) * T + w
                r3 = h_row(I + 3, n) * T + w
                t00 = H[r0 + c]
                t01 = H[r0 + c + T]
                t02 = H[r0 + c + 2 * T]
                t03 = H[r0 + c + 3 * T]
                t10 = H[r1 + c]
                t11 = H[r1 + c + T]
                t12 = H[r1 + c + 2 * T]
                t13 = H[r1 + c + 3 * T]
                t20 = H[r2 + c]
                t21 = H[r2 + c + T]
                t22 = H[r2 + c + 2 * T]
                t23 = H[r2 + c + 3 * T]
                t30 = H[r3 + c]
                t31 = H[r3 + c + T]
                t32 = H[r3 + c + 2 * T]
                t33 = H[r3 + c + 3 * T]
                lo = row_first(I)
                p = lo * T
                for k in range(lo, J):
                    u0 = H[r0 + p]
                    u1 = H[r1 + p]
                    u2 = H[r2 + p]
                    u3 = H[r3 + p]
                    v0 = H[j0 + p]
                    v1 = H[j1 + p]
                    v2 = H[j2 + p]
                    v3 = H[j3 + p]
                    t00 -= u0 * v0
                    t01 -= u0 * v1
                    t02 -= u0 * v2
                    t03 -= u0 * v3
                    t10 -= u1 * v0
                    t11 -= u1 * v1
                    t12 -= u1 * v2
                    t13 -= u1 * v3
                    t20 -= u2 * v0
                    t21 -= u2 * v1
                    t22 -= u2 * v2
                    t23 -= u2 * v3
                    t30 -= u3 * v0
                    t31 -= u3 * v1
                    t32 -= u3 * v2
                    t33 -= u3 * v3
                    p += T
                # X L_JJᵀ = T, a row of X at a time (forward substitution along the row)
                tile_row(H, r0, c, T, t00, t01, t02, t03, i0, i1, i2, i3, l10, l20, l21, l30, l31, l32)
                tile_row(H, r1, c, T, t10, t11, t12, t13, i0, i1, i2, i3, l10, l20, l21, l30, l31, l32)
                tile_row(H, r2, c, T, t20, t21, t22, t23, i0, i1, i2, i3, l10, l20, l21, l30, l31, l32)
                tile_row(H, r3, c, T, t30, t31, t32, t33, i0, i1, i2, i3, l10, l20, l21, l30, l31, l32)
                I += 4
            J += 4
        return 1

    return cholesky_dense


@functools.lru_cache(maxsize=None)
def _solve_funcs(dtype, envelope, packed):
    """The triangular solves of a factored H and the direction's reductions (``envelope`` and
    ``packed``: the packed block band; the reductions from ``_reduction_funcs``)."""
    vec3, vec12, zero, one, EPS = _scalars(dtype)
    h_row, row_first, column_end = _rows(packed, envelope and packed)
    reductions = _reduction_funcs(dtype)["reductions"]

    @wp.func
    def solve_dense(L: wp.array(dtype=dtype), g: wp.array(dtype=dtype), dq: wp.array(dtype=dtype), w: int, n: int,
                    T: int):  # fmt: skip
        """dq = −(L Lᵀ)⁻¹g, n a multiple of 4 (12 per body): each substitution runs four rows at a
        time (as cholesky_dense, for loads in flight), the known part first, then the 4 × 4
        triangle of the four rows themselves (in the block band, within each row's stored columns:
        four rows of one body share them)."""
        i = int(0)
        while i < n:  # L y = −g
            r0 = h_row(i, n) * T + w
            r1 = h_row(i + 1, n) * T + w
            r2 = h_row(i + 2, n) * T + w
            r3 = h_row(i + 3, n) * T + w
            c = i * T
            # the diagonal's reciprocals first: divisions that wait on nothing, not on the chain y0 → y3
            e0 = one / L[r0 + c]
            e1 = one / L[r1 + c + T]
            e2 = one / L[r2 + c + 2 * T]
            e3 = one / L[r3 + c + 3 * T]
            t0 = -g[i * T + w]
            t1 = -g[(i + 1) * T + w]
            t2 = -g[(i + 2) * T + w]
            t3 = -g[(i + 3) * T + w]
            lo = row_first(i)
            pk = lo * T + w
            for k in range(lo, i):
                y = dq[pk]
                ck = k * T
                t0 -= L[r0 + ck] * y
                t1 -= L[r1 + ck] * y
                t2 -= L[r2 + ck] * y
                t3 -= L[r3 + ck] * y
                pk += T
            y0 = t0 * e0
            y1 = (t1 - L[r1 + c] * y0) * e1
            y2 = (t2 - L[r2 + c] * y0 - L[r2 + c + T] * y1) * e2
            y3 = (t3 - L[r3 + c] * y0 - L[r3 + c + T] * y1 - L[r3 + c + 2 * T] * y2) * e3
            dq[c + w] = y0
            dq[c + T + w] = y1
            dq[c + 2 * T + w] = y2
            dq[c + 3 * T + w] = y3
            i += 4
        i = n - 4
        while i >= 0:  # Lᵀ x = y, rows i + 3 … i
            c = i * T
            t0 = dq[c + w]
            t1 = dq[c + T + w]
            t2 = dq[c + 2 * T + w]
            t3 = dq[c + 3 * T + w]
            pk = h_row(i + 4, n) * T + c + w  # L[k, i], k = i + 4, …
            for k in range(i + 4, column_end(i, n)):
                x = dq[k * T + w]
                t0 -= L[pk] * x
                t1 -= L[pk + T] * x
                t2 -= L[pk + 2 * T] * x
                t3 -= L[pk + 3 * T] * x
                pk += (h_row(k + 1, n) - h_row(k, n)) * T
            r0 = h_row(i, n) * T + c + w  # L[i, i]
            r1 = h_row(i + 1, n) * T + c + w
            r2 = h_row(i + 2, n) * T + c + w
            r3 = h_row(i + 3, n) * T + c + w
            x3 = t3 / L[r3 + 3 * T]
            e2 = one / L[r2 + 2 * T]
            e1 = one / L[r1 + T]
            e0 = one / L[r0]
            x2 = (t2 - L[r3 + 2 * T] * x3) * e2
            x1 = (t1 - L[r2 + T] * x2 - L[r3 + T] * x3) * e1
            x0 = (t0 - L[r1] * x1 - L[r2] * x2 - L[r3] * x3) * e0
            dq[c + w] = x0
            dq[c + T + w] = x1
            dq[c + 2 * T + w] = x2
            dq[c + 3 * T + w] = x3
            i -= 4

    @wp.func
    def substitute(L: wp.array(dtype=dtype), g: wp.array(dtype=dtype), dq: wp.array(dtype=dtype), w: int, n: int,
                   T: int, first: wp.array(dtype=wp.int32)):  # fmt: skip
        """dq = −(L Lᵀ)⁻¹g by two triangular solves (n² multiply-adds, against n³/6 for the factor);
        flat arrays, column w of T."""
        if wp.static(envelope and not packed):
            R = n * T
            for i in range(n):  # L y = −g
                t = -g[i * T + w]
                for k in range(first[i], i):
                    t -= L[i * R + k * T + w] * dq[k * T + w]
                dq[i * T + w] = t / L[i * R + i * T + w]
            for ii in range(n):  # Lᵀ x = y by columns of Lᵀ (rows of L: their envelope)
                i = n - 1 - ii
                xi = dq[i * T + w] / L[i * R + i * T + w]
                dq[i * T + w] = xi
                for k in range(first[i], i):
                    dq[k * T + w] = dq[k * T + w] - L[i * R + k * T + w] * xi
        else:
            solve_dense(L, g, dq, w, n, T)

    @wp.func
    def factored_solve(L: wp.array(dtype=dtype), g: wp.array(dtype=dtype), dq: wp.array(dtype=dtype), w: int,
                       n: int, T: int, first: wp.array(dtype=wp.int32)):  # fmt: skip
        """dq = −(L Lᵀ)⁻¹g (substitute), flat arrays, column w of T.

        Returns (ok, gᵀdq, ‖dq‖∞, ‖g‖₁); ok = 0 when the result is not finite.
        """
        substitute(L, g, dq, w, n, T, first)
        return reductions(g, dq, w, n, T)

    return dict(substitute=substitute, reductions=reductions, factored_solve=factored_solve)


@functools.lru_cache(maxsize=None)
def _reduction_funcs(dtype):
    """``reductions``: a Newton direction's gᵀΔq, ‖Δq‖∞ and ‖g‖₁, and whether it is finite."""
    zero = dtype(0.0)

    @wp.func
    def reductions(g: wp.array(dtype=dtype), dq: wp.array(dtype=dtype), w: int, n: int, T: int):
        """(ok, gᵀdq, ‖dq‖∞, ‖g‖₁) of a Newton direction; ok = 0 when it is not finite."""
        gdq = zero
        dmax = zero
        g_abs = zero
        p = w
        for i in range(n):
            gi = g[p]
            di = dq[p]
            gdq += gi * di
            dmax = wp.max(dmax, wp.abs(di))
            g_abs += wp.abs(gi)
            p += T
        if not wp.isfinite(gdq):
            return 0, zero, zero, zero
        return 1, gdq, dmax, g_abs

    return dict(reductions=reductions)


@functools.lru_cache(maxsize=None)
def _factor_funcs(dtype, envelope, packed):
    """H's Cholesky factor (the ``envelope``'s, the dense one or, both flags, the packed band's by
    the dense loops) and the solve through it."""
    vec3, vec12, zero, one, EPS = _scalars(dtype)
    cholesky_dense = _cholesky_dense(dtype, packed, envelope and packed)
    factored_solve = _solve_funcs(dtype, envelope, packed)["factored_solve"]

    @wp.func
    def cholesky_envelope(H: wp.array(dtype=dtype), w: int, n: int, T: int, first: wp.array(dtype=wp.int32)):
        """H = L Lᵀ in place on H's lower triangle (flat, column w of T); 0 when H is not positive
        definite.  Row i starts at column first[i]: L has H's envelope (Cholesky fills nothing left
        of a row's first non-zero), so the skipped products are exact zeros and the result is the
        dense one."""
        R = n * T
        for j in range(n):
            fj = first[j]
            rj = j * R + w
            s = H[rj + j * T]
            for k in range(fj, j):
                a = H[rj + k * T]
                s -= a * a
            if not (s > zero) or not wp.isfinite(s):
                return 0
            d = wp.sqrt(s)
            H[rj + j * T] = d
            for i in range(j + 1, n):
                fi = first[i]
                if fi <= j:
                    ri = i * R + w
                    t = H[ri + j * T]
                    for k in range(wp.max(fi, fj), j):
                        t -= H[ri + k * T] * H[rj + k * T]
                    H[ri + j * T] = t / d
        return 1

    @wp.func
    def cholesky(H: wp.array(dtype=dtype), w: int, n: int, T: int, first: wp.array(dtype=wp.int32)):
        """H = L Lᵀ in place (flat, column w of T; ``envelope``: within Model.first's envelope); 0
        when H is not positive definite."""
        if wp.static(envelope and not packed):
            return cholesky_envelope(H, w, n, T, first)
        return cholesky_dense(H, w, n, T)

    @wp.func
    def cholesky_solve(H: wp.array(dtype=dtype), g: wp.array(dtype=dtype), dq: wp.array(dtype=dtype), w: int,
                       n: int, T: int, first: wp.array(dtype=wp.int32)):  # fmt: skip
        """dq = −H⁻¹g for world w by Cholesky, in place on H's lower triangle (flat, column w of T).

        Returns (ok, gᵀdq, ‖dq‖∞, ‖g‖₁); ok = 0 when H is not positive definite or the result not finite.
        """
        if cholesky(H, w, n, T, first) == 0:
            return 0, zero, zero, zero
        return factored_solve(H, g, dq, w, n, T, first)

    return dict(cholesky=cholesky, cholesky_solve=cholesky_solve)


@functools.lru_cache(maxsize=None)
def _direction_kernels(dtype, envelope, packed):
    """The staged solve's start and its Newton direction of every active world."""
    vec3, vec12, zero, one, EPS = _scalars(dtype)
    cholesky = _factor_funcs(dtype, envelope, packed)["cholesky"]
    factored_solve = _solve_funcs(dtype, envelope, packed)["factored_solve"]

    @wp.kernel(module="unique")
    def start(
        status: wp.array(dtype=wp.int32), active: wp.array(dtype=wp.int32), iterations: wp.array(dtype=wp.int32),
        converged: wp.array(dtype=wp.int32), take: wp.array(dtype=wp.int32), chord: wp.array(dtype=wp.int32),
        factorizations: wp.array(dtype=wp.int32), cap: wp.array(dtype=wp.int32), max_iterations: int,
        spare: wp.array(dtype=wp.int32), reuse: int, retried: wp.array(dtype=wp.int32),
    ):  # fmt: skip
        """A world takes part in the solve while healthy, with a budget (``cap``) of max_iterations
        and, with ``reuse``, a retry from a fresh factor (``spare``, converge)."""
        w = wp.tid()
        factorizations[w] = 0
        cap[w] = max_iterations
        spare[w] = reuse
        retried[w] = 0
        active[w] = wp.where(status[w] == OK, 1, 0)
        iterations[w] = 0
        converged[w] = 0
        take[w] = 0
        chord[w] = 0

    @wp.kernel(module="unique")
    def newton_direction(
        H: wp.array(dtype=dtype), L: wp.array(dtype=dtype), g: wp.array(dtype=dtype), n: int,
        first: wp.array(dtype=wp.int32), active: wp.array(dtype=wp.int32), chord: wp.array(dtype=wp.int32),
        dq: wp.array(dtype=dtype), gdq: wp.array(dtype=dtype), dq_max: wp.array(dtype=dtype),
        g_abs: wp.array(dtype=dtype), status: wp.array(dtype=wp.int32), factorizations: wp.array(dtype=wp.int32),
        searching: wp.array(dtype=wp.int32), take: wp.array(dtype=wp.int32), spare: wp.array(dtype=wp.int32),
    ):  # fmt: skip
        """Newton direction of every active world, from H's Cholesky factor (kept in L) or, for a
        world whose iteration reuses the last factor (chord), from L as it is; the worlds with a
        direction start their line search (``searching``).  A world whose system breaks down ends
        its budget (take −2: converge retries a solve that reused the factor) or, without a retry
        left, is flagged BREAKDOWN.  Flat scratch, one column per world."""
        w = wp.tid()
        T = active.shape[0]
        searching[w] = 0
        if active[w] == 0:
            return
        ok = int(1)
        if chord[w] <= 0:
            factorizations[w] = factorizations[w] + 1
            ok = cholesky(H, w, n, T, first)
            for i in range(n):
                for j in range(i + 1):
                    L[(i * n + j) * T + w] = H[(i * n + j) * T + w]
        s = zero
        m = zero
        ga = zero
        if ok != 0:
            ok, s, m, ga = factored_solve(L, g, dq, w, n, T, first)
        if ok == 0:
            if spare[w] != 0:
                take[w] = -2
            else:
                status[w] = BREAKDOWN
                active[w] = 0
            return
        searching[w] = 1
        gdq[w] = s
        dq_max[w] = m
        g_abs[w] = ga

    return dict(start=start, newton_direction=newton_direction)


@functools.lru_cache(maxsize=None)
def _search_kernels(dtype):
    """The staged line search: trial point and Armijo test; the commit and the stop test after it
    from ``_converge_kernels``.

    The line search of the staged (reference) step (``fused=False``): each kernel runs over every
    world, a round of them (trial, energies, ``accept``) a halving of α, repeated while any world
    searches.  It is apart from the fused step's (fused/newton.py, ``line_search``), which runs
    inside a world's own thread or lanes, because each kernel here is one phase over all worlds
    and the energies come from the staged terms' columns; it keeps Armijo's test on Newton's
    direction with α halved, without the fused step's model of the limits along the step."""
    vec3, vec12, zero, one, EPS = _scalars(dtype)
    retract = affine_body.kernels(dtype).retract
    noise_floor = _noise_funcs(dtype)["noise_floor"]
    energy_noise = _noise_funcs(dtype)["energy_noise"]

    @wp.kernel(module="unique")
    def trial(
        q: wp.array2d(dtype=vec12), dq: wp.array2d(dtype=dtype), dof: wp.array(dtype=wp.int32),
        mass: wp.array2d(dtype=dtype), mc: wp.array2d(dtype=vec3), alpha: wp.array(dtype=dtype),
        searching: wp.array(dtype=wp.int32), q_trial: wp.array2d(dtype=vec12),
    ):  # fmt: skip
        """The trial point q + αΔq along the retraction's path (affine_body.retract)."""
        w, b = wp.tid()
        if searching[w] == 0:
            return  # keeps an accepted trial point until it is committed
        o = dof[b]
        qb = q[w, b]
        if o >= 0:
            d = vec12()
            for r in range(12):
                d[r] = dq[o + r, w]
            qb = retract(qb, d, alpha[w], mass[w, b], mc[w, b], 0)
        q_trial[w, b] = qb

    @wp.kernel(module="unique")
    def accept(
        q: wp.array2d(dtype=vec12), E0: wp.array2d(dtype=dtype), E1: wp.array2d(dtype=dtype), nterms: int,
        gdq: wp.array(dtype=dtype), g_abs: wp.array(dtype=dtype),
        dq_max: wp.array(dtype=dtype), threshold: dtype, min_alpha: dtype, quadratic: dtype,
        alpha: wp.array(dtype=dtype), searching: wp.array(dtype=wp.int32), take: wp.array(dtype=wp.int32),
        chord: wp.array(dtype=wp.int32), active: wp.array(dtype=wp.int32), converged: wp.array(dtype=wp.int32),
        remaining: wp.array(dtype=wp.int32),
    ):  # fmt: skip
        """Armijo test on the world's own energy; halve α on failure (a step under the tolerance, or
        one whose predicted decrease the energy's rounding cannot show, is accepted without it).

        Energies equal to within rounding count as no increase (the float32 noise floor); a world
        whose search runs out takes no step: it stops converged if its Newton step was already
        within 1000× the tolerance, else its budget ends (take −1, see converge).  A step from a reused factor
        (chord) is tried at α = 1 only and ends the solve only under the tolerance; rejected, it is
        not taken (take 0) and the next iteration refactors.  A Newton step (fresh factor) accepted at
        α = 1 that is under ``quadratic`` × q's rounding floor (4·eps·(1 + ‖q‖∞)) also ends it
        (SolverSettings.quadratic_stop).
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
        # a Newton step this small, accepted at α = 1, leaves an error below q's rounding (quadratic_stop)
        quad = chord[w] <= 0 and dq_max[w] < quadratic * dtype(4.0) * rounding
        if dq_max[w] < dtype(10.0) * floor or unresolved:
            # taken whole (α = 1, the first trial), as the fused step (fused.whole_step): within 10×
            # the noise floor, or a predicted decrease below the energy's rounding, which the test
            # could only halve on noise; the solve ends here if the step is under the tolerance, or
            # unresolved and within 1000× it (take 2)
            searching[w] = 0
            done = dq_max[w] < floor or (unresolved and dq_max[w] < dtype(1000.0) * floor) or quad
            take[w] = wp.where(done, 2, 1)
            if chord[w] > 0 and dq_max[w] >= floor:
                take[w] = 1
            return
        a = alpha[w]
        noise = dtype(16.0) * EPS * mag
        if e1 <= e0 + dtype(1.0e-4) * a * gdq[w] + noise and wp.isfinite(e1):
            searching[w] = 0
            take[w] = 1
            if e0 - e1 <= noise:
                take[w] = 2  # no decrease the precision can resolve: this is as converged as it gets
            if quad and a == one:
                take[w] = 2
        elif chord[w] > 0:
            searching[w] = 0
            take[w] = 0
        elif a <= min_alpha:
            searching[w] = 0
            take[w] = -1
            if dq_max[w] < dtype(1000.0) * floor:
                take[w] = 0
                active[w] = 0
                converged[w] = 1
        else:
            alpha[w] = a * dtype(0.5)
            wp.atomic_add(remaining, 0, 1)

    return dict(trial=trial, accept=accept, **_converge_kernels(dtype))


@functools.lru_cache(maxsize=None)
def _converge_kernels(dtype):
    """The end of a staged iteration: the accepted trial point taken (commit), the stop test, the
    factor's reuse and the retry (converge)."""
    _, vec12, _, one, _ = _scalars(dtype)
    noise_floor = _noise_funcs(dtype)["noise_floor"]

    @wp.kernel(module="unique")
    def commit(
        q: wp.array2d(dtype=vec12), q_trial: wp.array2d(dtype=vec12), take: wp.array(dtype=wp.int32),
    ):  # fmt: skip
        w, b = wp.tid()
        if take[w] > 0:
            q[w, b] = q_trial[w, b]

    @wp.kernel(module="unique")
    def converge(
        q: wp.array2d(dtype=vec12), q_tilde: wp.array2d(dtype=vec12), take: wp.array(dtype=wp.int32),
        dq_max: wp.array(dtype=dtype), threshold: dtype, alpha: wp.array(dtype=dtype), reuse: int,
        chord: wp.array(dtype=wp.int32), d_prev: wp.array(dtype=dtype), active: wp.array(dtype=wp.int32),
        converged: wp.array(dtype=wp.int32), iterations: wp.array(dtype=wp.int32), max_iterations: int,
        dof: wp.array(dtype=wp.int32),
        cap: wp.array(dtype=wp.int32), spare: wp.array(dtype=wp.int32), retried: wp.array(dtype=wp.int32),
        status: wp.array(dtype=wp.int32), remaining: wp.array(dtype=wp.int32),
    ):  # fmt: skip
        """‖Δq‖∞ below h·tol (or q's rounding), or a step whose energy change is below rounding:
        the step just taken was the last one needed.  The next iteration reuses the factor after a
        full step taken whole (with ``reuse``), and keeps reusing it while the steps shrink 8× an
        iteration, and not after a reused factor's step was rejected (fused.chord_step).

        A world's budget ends at ``cap`` iterations, when its line search ran out (take −1) or when
        its system broke down (take −2, newton_direction).  With a retry left (``spare``: the solve
        may reuse the factor) it then starts again from the prediction q̃ with max_iterations more, a
        fresh factor at every one (chord −1).  At the end of that budget, or of a solve without reuse, the world's step is
        rejected (status UNCONVERGED; finalize keeps qⁿ).  The staged twin of fused.solve_world."""
        w = wp.tid()
        if active[w] == 0:
            return
        taken = take[w]
        if taken != -2:  # (a system that broke down took no iteration)
            iterations[w] = iterations[w] + 1
        stalled = taken == 2
        ran_out = taken < 0
        take[w] = 0
        was_chord = chord[w]
        retry = was_chord > 0 and taken == 0
        if retry:
            chord[w] = -1  # a reused factor failed: this step factors every iteration from now
        elif was_chord > 0:
            chord[w] = wp.where(taken != 0 and dq_max[w] <= dtype(0.125) * d_prev[w], 1, -1)
        elif was_chord == 0:
            chord[w] = wp.where(taken != 0 and alpha[w] == one, reuse, 0)
        d_prev[w] = dq_max[w]
        floor, rounding = noise_floor(q, w, threshold)
        if not (retry or ran_out) and (dq_max[w] < floor or stalled):
            converged[w] = 1
            active[w] = 0
        elif ran_out or iterations[w] >= cap[w]:
            if spare[w] != 0:
                spare[w] = 0
                retried[w] = 1
                cap[w] = iterations[w] + max_iterations
                chord[w] = -1
                for b in range(q.shape[1]):
                    if dof[b] >= 0:
                        q[w, b] = q_tilde[w, b]
                wp.atomic_add(remaining, 0, 1)
            else:
                status[w] = UNCONVERGED
                active[w] = 0
        else:
            wp.atomic_add(remaining, 0, 1)

    return dict(commit=commit, converge=converge)


@functools.lru_cache(maxsize=None)
def kernels(dtype, envelope=False, packed=False):
    """The per-world Newton kernels for ``dtype``; ``envelope``: the Cholesky factor and solves skip
    the columns left of each row's first non-zero (``Model.first``), for block-banded scenes;
    ``packed``: H's lower triangle stored packed, row i from i(i+1)/2 (n(n+1)/2 words a column
    instead of n², for a scratch in shared memory); both: only the block band stored, packed
    (h_words, h_row_starts; for a scene with Model.banded), factored by the dense loops within it."""
    h_row, row_first, column_end = _rows(packed, envelope and packed)
    found = {**_noise_funcs(dtype), **_predict_funcs(dtype), **_finalize_funcs(dtype), "h_row": h_row,
             "row_first": row_first, "column_end": column_end}
    found.update(_solve_funcs(dtype, envelope, packed))
    found.update(_factor_funcs(dtype, envelope, packed))
    found.update(_direction_kernels(dtype, envelope, packed))
    found.update(_search_kernels(dtype))
    return {name: found[name] for name in _PUBLIC}
