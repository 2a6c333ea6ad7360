"""The energy-gain test of a step in a conservative world (docs/design.md §4.1).

A world is conservative in a step when nothing does positive work on it: gravity is a potential,
joints, limits and the orthogonality penalty are potentials, damping (a passive term's, a velocity
drive's at target 0) only removes energy, and no drive pushes: every drive's control is 0 in that
step.  A scene qualifies at build (``conservative``) when its drives are effort or velocity drives
(at control 0 an effort drive exerts nothing and a velocity drive is a damper); a position drive's
clipped spring has an energy that ``energies()`` does not report, so a scene with one is not checked.

Its total mechanical energy E is the sum of ``Simulator.energies()`` (kinetic, the armature's
included; gravity; orthogonality; joints; limits; drives).  A step that ended OK gains too much when

    E_after − E_before > tol·S + A_before + A_after,
    S = max over the steps since the state was set of E_before − min(V_low, V_g,after),

with V_low the lowest gravity potential the world has reached: S is the largest swing energy the
world has had (its kinetic plus elastic energy at its lowest point), which does not exceed the
swing energy of the whole run while no step gains, so the test is at least as strict as a gain of
tol of the run's swing energy.  The allowance A of a state is what its energy cannot resolve, the
rounding of the quantities it is computed from, scaled by the world's own magnitudes: the sums'
(``floor``, 1000 eps of the dtype, times Σ|E_c|) and, per column, the energy R_c its quantity has at
its rounding (q̇ = Δq/ĥ from q's, 2 eps‖q‖/h; the orthogonality residual AAᵀ − I, a point
joint's offset and a prismatic joint's four residuals from q's), which moves E_c by at most
2√(E_c R_c) + R_c (``total``); a limit's cubic, from its coordinate's rounding, the R that
2√(E R) + R turns into the cubic's change; the armature's ½aẋ², from ẋ's rounding.  A world at rest
in float32 (R ~ 1e-10 J for 0.1 kg bodies at dt 0.01) moves by that much with no gain at all.
E is the robustness report's total (joints and limits counted as their physical energies,
Solver.report_scale), so the test holds a step to the report's criterion.  It leaves no room
for the joints' stretch: every step keeps the joints' stiffness (constitutions/_joint_step.py),
so a retry's substeps do not release the stretch a step made.

``State.energy`` (W, 4) keeps, after each step, E, V_low, S and A as the next step's "before"; it
is computed anew before a step only where a door set the state (``fresh`` SET) or a parameter
changed it (E NaN: Simulator's setters).
"""
import functools
import math
from types import SimpleNamespace

import numpy as np
import warp as wp

from ..constitutions import (_point_joint, affine_body, drive, fixed_joint, passive, prismatic_joint, prismatic_limit,
                             revolute_joint, revolute_limit)
from ..core.angles import angle_ops
from ..core.warp_ops import ops
from ..sim.status import OK
from .kernels import RESET, RESTART, SET, next_attempt

# the energy's own rounding allowed in a step, in units of eps·Σ|E_c|: a column's sum, each of its
# terms a chain of a few dozen operations added in a world's own order, errs by at most γ_n|E_c|,
# γ_n ≈ n·eps, and n stays below 1000 for the scenes a world holds
FLOOR_EPS = 1000.0
# a point joint's offset C_p = (p_a + A_a x̄_a) − (p_b + A_b x̄_b) errs, in units of eps·ρ‖q‖ per body
# (ρ = √(1 + ‖x̄‖²) ≥ ‖[I, x̄ᵀ ⊗ I]‖₂): q's own rounding (u = eps/2) and the point's 4-term sums (4u)
JOINT_ROUNDING = 2.5
# a cross product d × T errs, in units of eps·‖d‖‖T‖, by its own products and differences (2u) and d's
# difference of two points (u)
CROSS_ROUNDING = 1.5
# a dot product T·d errs, in units of eps·‖d‖‖T‖, by its products and sums (3u) and d's difference (u)
DOT_ROUNDING = 2.0
# an angle atan2(s', c') with s', c' products of (c, s) and the step's reference, summed with θ0: its
# own and the products' rounding (2u each) and θ0 + δ's (u|x|), in units of eps (1 + |x|)
ANGLE_ROUNDING = 2.0
# a coordinate's rate (3x^{n+1} − 4xⁿ + x^{n−1})/(2h) errs, per unit of each x's rounding δx, by 8/(2h)
COORDINATE_RATE_ROUNDING = 4.0
# q̇ = (3Δq − (qⁿ − qⁿ⁻¹))/(2h) (BDF2; implicit Euler's Δq/h is less) errs, from q's rounding, by
# (3·2u + 2u)/(2h) = 2 eps/h per unit of |q|
VELOCITY_ROUNDING = 2.0
# fresh == SET as the bytes of an int32: a host-side test without a ufunc (fresh's values, 0 to
# SET, are one low byte and three zero bytes, so the pattern can match only at a value's start)
SET_BYTES = np.int32(SET).tobytes()


def conservative(model) -> bool:
    """Whether the scene's worlds can be checked: no position drive (module docstring)."""
    return not model.num_drives or not (model.drive_mode.numpy() == drive.POSITION).any()


# the point joints (constitution name: (joint kind, points)), whose energy measure takes without
# the 12 × 12 Hessian blocks their own kernel builds (zeroed) at every evaluation
POINT_JOINTS = {c.NAME: (c.KIND, c.NUM_POINTS) for c in (revolute_joint, fixed_joint)}


@functools.lru_cache(maxsize=None)
def point_energy(dtype):
    """The point joints' energies alone: each joint's term of _point_joint's kernel (its energy
    from the same point_eval_kron, added in the same order), without its derivatives."""
    vec3, vec12 = ops(dtype).vec3, ops(dtype).vec12
    evaluate, add_energy = _point_joint.kernel(dtype).eval_kron, ops(dtype).add_energy

    @wp.kernel(module="unique")
    def point_energy(q: wp.array2d(dtype=vec12), ids: wp.array(dtype=wp.int32), body_a: wp.array(dtype=wp.int32),
                     body_b: wp.array(dtype=wp.int32), pts_a: wp.array3d(dtype=vec3), pts_b: wp.array3d(dtype=vec3),
                     npts: int, K: wp.array2d(dtype=dtype), active: wp.array(dtype=wp.int32), col: int,
                     rcol: int, eps: dtype, E: wp.array2d(dtype=dtype)):  # fmt: skip
        w, k = wp.tid()
        if active[w] == 0:
            return
        j = ids[k]
        qa, qb = q[w, body_a[j]], q[w, body_b[j]]
        e, gi, gj, uii, uij, ujj = evaluate(qa, qb, pts_a, pts_b, w, j, npts, K[w, j], 0)
        add_energy(E, w, col, e)
        # the joint's energy at its points' rounding (JOINT_ROUNDING): δC_p ≤ 5 eps (ρ_a‖q_a‖ + ρ_b‖q_b‖)
        r = dtype(0.0)
        na, nb = wp.length(qa), wp.length(qb)
        for p in range(npts):
            xa, xb = pts_a[w, j, p], pts_b[w, j, p]
            rho_a, rho_b = wp.sqrt(dtype(1.0) + wp.dot(xa, xa)), wp.sqrt(dtype(1.0) + wp.dot(xb, xb))
            dc = dtype(JOINT_ROUNDING) * eps * (rho_a * na + rho_b * nb)
            r += dtype(0.5) * K[w, j] * dc * dc
        add_energy(E, w, rcol, r)

    return point_energy


@functools.lru_cache(maxsize=None)
def prismatic_energy(dtype):
    """The prismatic joints' energies alone (prismatic_joint's prismatic_grad without its
    gradient: the same energy, added in the same order) and their energies at q's rounding."""
    o = ops(dtype)
    vec3, vec12, point, direction = o.vec3, o.vec12, o.point, o.direction
    energy, add_energy = prismatic_joint.kernel(dtype).grad, o.add_energy

    @wp.kernel(module="unique")
    def prismatic_energy(q: wp.array2d(dtype=vec12), ids: wp.array(dtype=wp.int32), body_a: wp.array(dtype=wp.int32),
                         body_b: wp.array(dtype=wp.int32), c_a: wp.array2d(dtype=vec3), c_b: wp.array2d(dtype=vec3),
                         t_a: wp.array2d(dtype=vec3), t_b: wp.array2d(dtype=vec3), n_a: wp.array2d(dtype=vec3),
                         n_b: wp.array2d(dtype=vec3), b_a: wp.array2d(dtype=vec3), b_b: wp.array2d(dtype=vec3),
                         K: wp.array2d(dtype=dtype), active: wp.array(dtype=wp.int32), col: int, rcol: int,
                         eps: dtype, E: wp.array2d(dtype=dtype)):  # fmt: skip
        w, k = wp.tid()
        if active[w] == 0:
            return
        j = ids[k]
        qa, qb = q[w, body_a[j]], q[w, body_b[j]]
        ca, cb, ta, tb = c_a[w, j], c_b[w, j], t_a[w, j], t_b[w, j]
        e, gi, gj = energy(qa, qb, ca, cb, ta, tb, n_a[w, j], n_b[w, j], b_a[w, j], b_b[w, j], K[w, j], 0)
        add_energy(E, w, col, e)
        # the energy at q's rounding (JOINT_ROUNDING, CROSS_ROUNDING): δd ≤ 2.5 eps (ρ_a‖q_a‖ + ρ_b‖q_b‖) of
        # d = c_b − c_a, δT ≤ 2.5 eps ‖t̄‖‖q‖ of a direction T = A t̄; δ(d × T) ≤ δd‖T‖ + ‖d‖δT + 1.5 eps ‖d‖‖T‖
        na, nb = wp.length(qa), wp.length(qb)
        one, r = dtype(1.0), dtype(JOINT_ROUNDING) * eps
        d = point(qb, cb) - point(qa, ca)
        Ta, Tb = direction(qa, ta), direction(qb, tb)
        dd = r * (wp.sqrt(one + wp.dot(ca, ca)) * na + wp.sqrt(one + wp.dot(cb, cb)) * nb)
        ld, lta, ltb = wp.length(d), wp.length(Ta), wp.length(Tb)
        cross = dtype(CROSS_ROUNDING) * eps * ld
        d0 = dd * lta + ld * r * wp.length(ta) * na + cross * lta
        d1 = dd * ltb + ld * r * wp.length(tb) * nb + cross * ltb
        d2 = r * (wp.length(n_a[w, j]) * na + wp.length(n_b[w, j]) * nb)
        d3 = r * (wp.length(b_a[w, j]) * na + wp.length(b_b[w, j]) * nb)
        add_energy(E, w, rcol, dtype(0.5) * K[w, j] * (d0 * d0 + d1 * d1 + d2 * d2 + d3 * d3))

    return prismatic_energy


@functools.lru_cache(maxsize=None)
def rounding(dtype):
    """wp.funcs of a joint coordinate's rounding from q's and of the R it gives a limit's cubic:
    ``displacement_error`` (a prismatic joint's x = T·d), ``angle_error`` (a revolute joint's x
    = θ0 + ΔΘ) and ``cubic_r``."""
    o, a = ops(dtype), angle_ops(dtype)
    vec3, vec12, point, direction, cos_sin = o.vec3, o.vec12, o.point, o.direction, a.cos_sin
    one, half = dtype(1.0), dtype(0.5)

    @wp.func
    def displacement_error(qa: vec12, qb: vec12, ca: vec3, cb: vec3, ta: vec3, eps: dtype):
        """δx of x = T·d (T = A_a t̄, d = c_b − c_a): δd‖T‖ + ‖d‖δT + 2 eps ‖d‖‖T‖ (JOINT_ROUNDING for
        δd and δT, DOT_ROUNDING for the dot)."""
        r = dtype(JOINT_ROUNDING) * eps
        na, nb = wp.length(qa), wp.length(qb)
        d = point(qb, cb) - point(qa, ca)
        ld, lt = wp.length(d), wp.length(direction(qa, ta))
        dd = r * (wp.sqrt(one + wp.dot(ca, ca)) * na + wp.sqrt(one + wp.dot(cb, cb)) * nb)
        return dd * lt + ld * r * wp.length(ta) * na + dtype(DOT_ROUNDING) * eps * ld * lt

    @wp.func
    def angle_error(qa: vec12, qb: vec12, na: vec3, ba: vec3, nb: vec3, bb: vec3, x: dtype, eps: dtype):
        """δx of x = θ0 + atan2 of (c, s) = ½(B_a·B_b + N_a·N_b, N_a·B_b − B_a·N_b), each direction
        U = A ū within JOINT_ROUNDING eps ‖ū‖‖q‖ and each dot within DOT_ROUNDING: (δc + δs)/√(c² + s²),
        and ANGLE_ROUNDING eps (1 + |x|) for atan2, its products and θ0 + δ."""
        r = dtype(JOINT_ROUNDING) * eps
        la, lb = wp.length(qa), wp.length(qb)
        Na, Ba, Nb, Bb = direction(qa, na), direction(qa, ba), direction(qb, nb), direction(qb, bb)
        lNa, lBa, lNb, lBb = wp.length(Na), wp.length(Ba), wp.length(Nb), wp.length(Bb)
        dNa, dBa = r * wp.length(na) * la, r * wp.length(ba) * la
        dNb, dBb = r * wp.length(nb) * lb, r * wp.length(bb) * lb
        dot = dtype(DOT_ROUNDING) * eps
        dc = half * (dBa * lBb + lBa * dBb + dNa * lNb + lNa * dNb + dot * (lBa * lBb + lNa * lNb))
        ds = half * (dNa * lBb + lNa * dBb + dBa * lNb + lBa * dNb + dot * (lNa * lBb + lBa * lNb))
        c, s = cos_sin(qa, qb, na, ba, nb, bb)
        return (dc + ds) / wp.max(wp.sqrt(c * c + s * s), eps) + dtype(ANGLE_ROUNDING) * eps * (one + wp.abs(x))

    @wp.func
    def cubic_r(e: dtype, p: dtype, dx: dtype, st: dtype):
        """The R of a cubic st·p³ at penetration p (energy e) whose coordinate moves by dx: its
        change Δ = st((p + dx)³ − p³) as (√(e + Δ) − √e)², which total's 2√(e R) + R turns back
        into Δ (a column's sum of them still bounds its limits' sum: Cauchy–Schwarz)."""
        change = st * ((p + dx) * (p + dx) * (p + dx) - p * p * p)
        root = wp.sqrt(e + change) + wp.sqrt(e)
        out = dtype(0.0)
        if root > dtype(0.0):
            out = change * change / (root * root)
        return out

    return SimpleNamespace(displacement_error=displacement_error, angle_error=angle_error, cubic_r=cubic_r)


@functools.lru_cache(maxsize=None)
def prismatic_limit_energy(dtype):
    """The prismatic limits' energies alone (prismatic_limit's parts without their gradient: the
    same energy, added in the same order) and, per limit, the R of its cubic s(p/w)³ at its
    displacement's rounding (rounding)."""
    o, rnd = ops(dtype), rounding(dtype)
    vec3, vec12, point, direction = o.vec3, o.vec12, o.point, o.direction
    parts, add_energy = prismatic_limit.kernel(dtype).parts, o.add_energy

    @wp.kernel(module="unique")
    def prismatic_limit_energy(q: wp.array2d(dtype=vec12), ids: wp.array(dtype=wp.int32),
                               body_a: wp.array(dtype=wp.int32), body_b: wp.array(dtype=wp.int32),
                               c_a: wp.array2d(dtype=vec3), c_b: wp.array2d(dtype=vec3), t_a: wp.array2d(dtype=vec3),
                               lower: wp.array2d(dtype=dtype), upper: wp.array2d(dtype=dtype),
                               strength: wp.array2d(dtype=dtype), active: wp.array(dtype=wp.int32), col: int,
                               rcol: int, eps: dtype, E: wp.array2d(dtype=dtype)):  # fmt: skip
        w, k = wp.tid()
        if active[w] == 0:
            return
        j = ids[k]
        qa, qb = q[w, body_a[j]], q[w, body_b[j]]
        ca, cb, ta = c_a[w, j], c_b[w, j], t_a[w, j]
        lo, up, st = lower[w, k], upper[w, k], strength[w, k]
        e, de, dde, gi, gj = parts(qa, qb, ca, cb, ta, lo, up, st, 0)
        add_energy(E, w, col, e)
        x = wp.dot(direction(qa, ta), point(qb, cb) - point(qa, ca))
        inv = dtype(1.0)
        if up > lo:
            inv = dtype(1.0) / (up - lo)
        p = wp.max(wp.max(x - up, lo - x), dtype(0.0))
        add_energy(E, w, rcol, rnd.cubic_r(e, p, rnd.displacement_error(qa, qb, ca, cb, ta, eps), st * inv * inv * inv))

    return prismatic_limit_energy


@functools.lru_cache(maxsize=None)
def revolute_limit_energy(dtype):
    """The revolute limits' energies alone (revolute_limit's parts without their gradient) and,
    per limit, the R of its cubic s p³ at its angle's rounding (rounding)."""
    o, a, rnd = ops(dtype), angle_ops(dtype), rounding(dtype)
    vec3, vec12, cos_sin, delta_theta = o.vec3, o.vec12, a.cos_sin, a.delta_theta
    parts, add_energy = revolute_limit.kernel(dtype).parts, o.add_energy

    @wp.kernel(module="unique")
    def revolute_limit_energy(q: wp.array2d(dtype=vec12), ids: wp.array(dtype=wp.int32),
                              body_a: wp.array(dtype=wp.int32), body_b: wp.array(dtype=wp.int32),
                              n_a: wp.array2d(dtype=vec3), b_a: wp.array2d(dtype=vec3), n_b: wp.array2d(dtype=vec3),
                              b_b: wp.array2d(dtype=vec3), theta0: wp.array2d(dtype=dtype),
                              c_prev: wp.array2d(dtype=dtype), s_prev: wp.array2d(dtype=dtype),
                              lower: wp.array2d(dtype=dtype), upper: wp.array2d(dtype=dtype),
                              strength: wp.array2d(dtype=dtype), active: wp.array(dtype=wp.int32), col: int,
                              rcol: int, eps: dtype, E: wp.array2d(dtype=dtype)):  # fmt: skip
        w, k = wp.tid()
        if active[w] == 0:
            return
        j = ids[k]
        qa, qb = q[w, body_a[j]], q[w, body_b[j]]
        na, ba, nb, bb = n_a[w, j], b_a[w, j], n_b[w, j], b_b[w, j]
        lo, up, st = lower[w, k], upper[w, k], strength[w, k]
        e, de, dde, gi, gj = parts(qa, qb, na, ba, nb, bb, theta0[w, j], c_prev[w, j], s_prev[w, j], lo, up, st, 0)
        add_energy(E, w, col, e)
        c, s = cos_sin(qa, qb, na, ba, nb, bb)
        x = theta0[w, j] + delta_theta(c, s, c_prev[w, j], s_prev[w, j])
        p = wp.max(wp.max(x - up, lo - x), dtype(0.0))
        add_energy(E, w, rcol, rnd.cubic_r(e, p, rnd.angle_error(qa, qb, na, ba, nb, bb, x, eps), st))

    return revolute_limit_energy


@functools.lru_cache(maxsize=None)
def armature_energy(dtype):
    """The joints' armature energies ½aẋ² alone (passive's physical part: the same energy, added
    in the same order, to the kinetic column) and their energies at ẋ's rounding: ẋ from three
    coordinates (BDF2's difference; implicit Euler's is less) errs by COORDINATE_RATE_ROUNDING δx/h,
    δx a coordinate's rounding (rounding) and its own, eps |x|."""
    o, rnd = ops(dtype), rounding(dtype)
    vec3, vec12 = o.vec3, o.vec12
    add_energy, half = o.add_energy, dtype(0.5)

    @wp.kernel(module="unique")
    def armature_energy(q: wp.array2d(dtype=vec12), joint: wp.array(dtype=wp.int32),
                        joint_kind: wp.array(dtype=wp.int32), body_a: wp.array(dtype=wp.int32),
                        body_b: wp.array(dtype=wp.int32), c_a: wp.array2d(dtype=vec3), c_b: wp.array2d(dtype=vec3),
                        t_a: wp.array2d(dtype=vec3), n_a: wp.array2d(dtype=vec3), b_a: wp.array2d(dtype=vec3),
                        n_b: wp.array2d(dtype=vec3), b_b: wp.array2d(dtype=vec3), armature: wp.array2d(dtype=dtype),
                        unwrapped: wp.array2d(dtype=dtype), velocity: wp.array2d(dtype=dtype),
                        active: wp.array(dtype=wp.int32), col: int, rcol: int, eps: dtype, rate: dtype,
                        E: wp.array2d(dtype=dtype)):  # fmt: skip
        w, k = wp.tid()
        if active[w] == 0:
            return
        j = joint[k]
        v = velocity[w, j]
        add_energy(E, w, col, half * armature[w, k] * v * v)
        qa, qb = q[w, body_a[j]], q[w, body_b[j]]
        x = unwrapped[w, j]
        dx = eps * wp.abs(x)
        if joint_kind[j] == 0:  # revolute
            dx += rnd.angle_error(qa, qb, n_a[w, j], b_a[w, j], n_b[w, j], b_b[w, j], x, eps)
        else:
            dx += rnd.displacement_error(qa, qb, c_a[w, j], c_b[w, j], t_a[w, j], eps)
        dv = rate * dx
        add_energy(E, w, rcol, half * armature[w, k] * dv * dv)

    return armature_energy


@functools.lru_cache(maxsize=None)
def body_energy(dtype):
    """The bodies' energies in one launch: kinetic and gravity (affine_body's report_terms, as its
    body_report adds them) and orthogonality (its body_terms in physical form: the same
    body_grad, added in the same order, without the 12 × 12 Hessian or the inertia term), with
    the kinetic and orthogonality energies at q's rounding (EnergyCheck.measure's columns)."""
    o = ops(dtype)
    vec3, vec12, mat33 = o.vec3, o.vec12, o.mat33
    body_grad, add_energy = affine_body.body_funcs(dtype).body_grad, o.add_energy
    report_terms = affine_body.kernels(dtype).report_terms

    @wp.kernel(module="unique")
    def body_energy(q: wp.array2d(dtype=vec12), qd: wp.array2d(dtype=vec12), q_tilde: wp.array2d(dtype=vec12),
                    free: wp.array(dtype=wp.int32), mass: wp.array2d(dtype=dtype), mc: wp.array2d(dtype=vec3),
                    S: wp.array2d(dtype=mat33), kv: wp.array2d(dtype=dtype), gravity: vec3,
                    active: wp.array(dtype=wp.int32), kcol: int, gcol: int, col: int, roff: int, eps: dtype,
                    dv: dtype, E: wp.array2d(dtype=dtype)):  # fmt: skip
        w, k = wp.tid()
        if active[w] == 0:
            return
        b = free[k]
        qb = q[w, b]
        m, s = mass[w, b], S[w, b]
        ke, ge = report_terms(qd[w, b], qb, m, mc[w, b], s, gravity)
        wp.atomic_add(E, w, kcol, ke)
        wp.atomic_add(E, w, gcol, ge)
        e_inertia, e_ortho, f = body_grad(qb, q_tilde[w, b], m, mc[w, b], s, kv[w, b], 0)
        add_energy(E, w, col, e_ortho)
        # the energies at q's rounding: orthogonality ks‖δR‖², ‖δR‖_F ≤ eps (3‖A‖_F² + √3/2); kinetic
        # ½ λmax(M) ‖δq̇‖² with λmax(M) ≤ m + tr S and ‖δq̇‖ ≤ dv ‖q‖ (VELOCITY_ROUNDING)
        a2 = wp.dot(qb, qb) - (qb[0] * qb[0] + qb[1] * qb[1] + qb[2] * qb[2])
        dr = eps * (dtype(3.0) * a2 + dtype(0.8660254037844386))
        add_energy(E, w, roff + col, kv[w, b] * dr * dr)
        dq = dv * wp.length(qb)
        add_energy(E, w, roff + kcol, dtype(0.5) * (m + s[0, 0] + s[1, 1] + s[2, 2]) * dq * dq)

    return body_energy


@functools.lru_cache(maxsize=None)
def kernels(dtype):
    """The test's kernels for a scalar dtype."""

    @wp.func
    def total(E: wp.array2d(dtype=dtype), scale: wp.array(dtype=dtype), w: int, ncols: int, floor: dtype,
              roff: int):
        """(Σ E_c, the energy's rounding A) of world w's first ncols columns, each column c its
        physical energy E_c = scale[c]·E[w, c] (Solver.report_scale) and R_c = scale[c]·E[w, roff + c]
        the energy of its quantities' rounding: A = Σ floor·|E_c| + 2√(|E_c| R_c) + R_c, the
        rounding of the sums and the most a quadratic energy changes when its quantity moves by
        its rounding (½k(x + δ)² − ½kx² ≤ 2√(½kx²·½kδ²) + ½kδ²)."""
        e = dtype(0.0)
        allow = dtype(0.0)
        for c in range(ncols):
            ec = scale[c] * E[w, c]
            rc = scale[c] * E[w, roff + c]
            e += ec
            allow += floor * wp.abs(ec) + dtype(2.0) * wp.sqrt(wp.abs(ec) * rc) + rc
        return e, allow

    @wp.func
    def swing_of(mem: wp.array2d(dtype=dtype), w: int, g: dtype):
        """S: the largest swing energy world w has had since its state was set, its energy before
        the step above the lowest gravity potential it has reached (g, after the step, included)."""
        return wp.max(mem[w, 2], mem[w, 0] - wp.min(mem[w, 1], g))

    @wp.func
    def gains(mem: wp.array2d(dtype=dtype), w: int, e: dtype, allow: dtype, g: dtype, tol: dtype):
        """Whether world w's step to energy ``e`` (gravity potential g; ``allow`` its allowance)
        gains more than tol of S plus the rounding of before and after (the most a difference of
        two rounded values errs by)."""
        return e - mem[w, 0] > tol * swing_of(mem, w, g) + allow + mem[w, 3]

    @wp.func
    def keep(mem: wp.array2d(dtype=dtype), w: int, e: dtype, allow: dtype, g: dtype):
        """World w's step is kept: its energy, allowance and swing as the next step's before."""
        mem[w, 2] = swing_of(mem, w, g)
        mem[w, 1] = wp.min(mem[w, 1], g)
        mem[w, 0] = e
        mem[w, 3] = allow

    @wp.func
    def pushed(control: wp.array2d(dtype=dtype), w: int, nd: int):
        """Whether a drive of world w has a nonzero control (the world is not conservative)."""
        out = int(0)
        for d in range(nd):
            if control[w, d] != dtype(0.0):
                out = 1
        return out

    @wp.kernel
    def unknown(status: wp.array(dtype=wp.int32), fresh: wp.array(dtype=wp.int32), mem: wp.array2d(dtype=dtype),
                hold: wp.array(dtype=wp.int32), go: wp.array(dtype=wp.int32), need: wp.array(dtype=wp.int32)):  # fmt: skip
        """need[w] = 1 where world w's energy before its step is to be computed: its state was set
        (fresh SET) or a parameter changed it (energy NaN); not a world the step holds (hold, go)."""
        w = wp.tid()
        need[w] = 0
        if go[0] != 0 and hold[w] == 0 and status[w] == OK and (fresh[w] == SET or not wp.isfinite(mem[w, 0])):
            need[w] = 1

    @wp.kernel
    def remember(E: wp.array2d(dtype=dtype), scale: wp.array(dtype=dtype), ncols: int, gcol: int, floor: dtype,
                 roff: int, need: wp.array(dtype=wp.int32), mem: wp.array2d(dtype=dtype)):  # fmt: skip
        """The energy, gravity potential, swing and allowance of the worlds ``need`` marks, as of
        before their step."""
        w = wp.tid()
        if need[w] != 0:
            e, allow = total(E, scale, w, ncols, floor, roff)
            g = E[w, gcol]
            mem[w, 0] = e
            mem[w, 1] = g
            mem[w, 2] = e - g
            mem[w, 3] = allow

    @wp.kernel
    def judge(E: wp.array2d(dtype=dtype), scale: wp.array(dtype=dtype), ncols: int, gcol: int, floor: dtype,
              roff: int, control: wp.array2d(dtype=dtype), nd: int,
              status: wp.array(dtype=wp.int32), hold: wp.array(dtype=wp.int32), go: wp.array(dtype=wp.int32),
              tol: dtype, mem: wp.array2d(dtype=dtype),
              fresh: wp.array(dtype=wp.int32), substeps: wp.array(dtype=wp.int32), gained: wp.array(dtype=wp.int32),
              idle: wp.array(dtype=wp.int32), busy: wp.array(dtype=wp.int32), flag: wp.array(dtype=wp.int32)):  # fmt: skip
        """After a step and retry.mark: a world it stepped OK whose energy gained too much (and no
        drive pushed) is to be retried as retry.mark does for a failed one (idle 0, an implicit
        Euler start, 2 substeps; flag[0] = 1); any other world it stepped OK keeps its energy as the
        next step's E_before.  busy[w] = 1 for every world to be retried (the energy's mask)."""
        w = wp.tid()
        busy[w] = 0
        if go[0] == 0 or hold[w] != 0:
            return
        gained[w] = 0
        if idle[w] == 0:  # a failed step marked for its retry
            busy[w] = 1
            return
        if status[w] != OK:
            return
        e, allow = total(E, scale, w, ncols, floor, roff)
        g = E[w, gcol]
        if pushed(control, w, nd) == 0 and gains(mem, w, e, allow, g, tol):
            idle[w] = 0
            busy[w] = 1
            fresh[w] = RESTART
            substeps[w] = 2
            flag[0] = 1
            return
        keep(mem, w, e, allow, g)

    @wp.kernel
    def settle(E: wp.array2d(dtype=dtype), scale: wp.array(dtype=dtype), ncols: int, gcol: int, floor: dtype,
               roff: int, control: wp.array2d(dtype=dtype), nd: int,
               status: wp.array(dtype=wp.int32), tol: dtype, mem: wp.array2d(dtype=dtype),
               fresh: wp.array(dtype=wp.int32), substeps: wp.array(dtype=wp.int32),
               gained: wp.array(dtype=wp.int32), idle: wp.array(dtype=wp.int32), busy: wp.array(dtype=wp.int32),
               back: wp.array(dtype=wp.int32), n: int, next_n: int):  # fmt: skip
        """retry.settle with the energy test: after an attempt of ``n`` substeps, a retried world
        that came through without gaining too much idles from now on (its energy kept); one that
        failed, or gained with ``next_n`` > 0, goes back to the state before the step (back 1) and
        tries ``next_n`` substeps; at next_n 0 one that failed is rejected (status kept) and one
        that gained keeps its step and is flagged (gained 1)."""
        w = wp.tid()
        back[w] = 0
        if idle[w] != 0:
            return
        if status[w] == OK:
            e, allow = total(E, scale, w, ncols, floor, roff)
            g = E[w, gcol]
            bad = pushed(control, w, nd) == 0 and gains(mem, w, e, allow, g, tol)
            if not bad or next_n == 0:
                idle[w] = 1
                busy[w] = 0
                fresh[w] = RESET
                gained[w] = wp.where(bad, 1, 0)
                keep(mem, w, e, allow, g)
                return
        back[w] = 1
        if next_attempt(status, fresh, substeps, idle, w, n, next_n) != 0:
            busy[w] = 0

    @wp.kernel(module="unique")
    def allowance(E: wp.array2d(dtype=dtype), scale: wp.array(dtype=dtype), ncols: int, floor: dtype, roff: int,
                  out: wp.array(dtype=dtype)):  # fmt: skip
        """out[w]: the allowance A of world w's energy (total), as the test allows it."""
        w = wp.tid()
        e, allow = total(E, scale, w, ncols, floor, roff)
        out[w] = allow

    return {"unknown": unknown, "remember": remember, "judge": judge, "settle": settle, "allowance": allowance}


class EnergyCheck:
    """The energy test of one Solver's worlds (module docstring): the energy arrays and launches."""

    def __init__(self, solver, tol: float):
        self.solver, self.tol = solver, float(tol)
        m = solver.model
        self.k = kernels(m.dtype)
        cols = solver.report_cols
        self.ncols, self.gcol = len(cols) - 1, cols["gravity"]  # (every column but the scratch)
        # the energies, then from column roff on the energies of their quantities' rounding (total)
        self.roff = len(cols)
        self.E = wp.zeros((m.num_worlds, 2 * len(cols)), dtype=m.dtype, device=m.device)
        self.scale = wp.array(solver.report_scale, dtype=m.dtype, device=m.device)  # each column's to J
        self.parts = [c for c in solver.parts if c.name != drive.NAME]  # (measure)
        self.need = wp.zeros(m.num_worlds, dtype=wp.int32, device=m.device)
        self.busy = wp.zeros(m.num_worlds, dtype=wp.int32, device=m.device)
        self.cpu = wp.get_device(m.device).is_cpu
        self._host = None  # CPU: HostViews of the state the views are of
        self.eps = float(np.finfo(m.np_dtype).eps)
        self.floor = FLOOR_EPS * self.eps

    def measure(self, state, mask, h=None):
        """The physical energies of the worlds in mask into self.E (Solver.assemble, physical),
        but for the drives': a conservative scene's (no position drive) are 0, as the zeroed
        column keeps them, so their launch is left out; the bodies', the joints', the limits' and
        the armature's by kernels of their energies alone, with their energies at their
        quantities' rounding (body_energy, point_energy, prismatic_energy, the limits' and
        armature_energy)."""
        h = self.solver.dt if h is None else h  # the step that made the state's q̇ (its rounding)
        s, m = self.solver, self.solver.model
        self.E.zero_()
        for c in self.parts:
            if c.name == affine_body.NAME:  # kinetic, gravity and orthogonality in one launch (body_energy)
                cols = s.report_cols
                wp.launch(body_energy(m.dtype), dim=(m.num_worlds, m.num_free),
                          inputs=[state.q, state.qd, s.q_tilde, m.free, m.mass, m.mc, m.S, m.kv, m.gravity, mask,
                                  cols["kinetic"], cols["gravity"], cols["orthogonality"], self.roff, self.eps,
                                  m.dtype(VELOCITY_ROUNDING * self.eps / h), self.E], device=m.device)  # fmt: skip
            elif c.name in POINT_JOINTS:
                kind, npts = POINT_JOINTS[c.name]
                wp.launch(point_energy(m.dtype), dim=(m.num_worlds, m.joint_count[kind]),
                          inputs=[state.q, m.joint_ids[kind], m.body_a, m.body_b, m.pts_a, m.pts_b, npts, m.K, mask,
                                  s.report_cols[c.name], self.roff + s.report_cols[c.name], self.eps,
                                  self.E], device=m.device)  # fmt: skip
            elif c.name == prismatic_joint.NAME:
                kind, col = prismatic_joint.KIND, s.report_cols[c.name]
                wp.launch(prismatic_energy(m.dtype), dim=(m.num_worlds, m.joint_count[kind]),
                          inputs=[state.q, m.joint_ids[kind], m.body_a, m.body_b, m.c_a, m.c_b, m.t_a, m.t_b, m.n_a,
                                  m.n_b, m.b_a, m.b_b, m.K, mask, col, self.roff + col, self.eps, self.E],
                          device=m.device)  # fmt: skip
            elif c.name == prismatic_limit.NAME:
                kind, col = prismatic_limit.KIND, s.report_cols[c.name]
                wp.launch(prismatic_limit_energy(m.dtype), dim=(m.num_worlds, len(m.limit_joints[kind])),
                          inputs=[state.q, m.limit_joint_ids[kind], m.body_a, m.body_b, m.c_a, m.c_b, m.t_a,
                                  *m.limit_params[kind], mask, col, self.roff + col, self.eps, self.E],
                          device=m.device)  # fmt: skip
            elif c.name == revolute_limit.NAME:
                kind, col = revolute_limit.KIND, s.report_cols[c.name]
                wp.launch(revolute_limit_energy(m.dtype), dim=(m.num_worlds, len(m.limit_joints[kind])),
                          inputs=[state.q, m.limit_joint_ids[kind], m.body_a, m.body_b, m.n_a, m.b_a, m.n_b, m.b_b,
                                  state.theta0, state.c_prev, state.s_prev, *m.limit_params[kind], mask, col,
                                  self.roff + col, self.eps, self.E], device=m.device)  # fmt: skip
            elif c.name == passive.NAME:  # (its physical part: the armature's kinetic energy)
                col = s.report_cols["kinetic"]
                wp.launch(armature_energy(m.dtype), dim=(m.num_worlds, m.num_passive),
                          inputs=[state.q, m.passive_joint, m.joint_kind, m.body_a, m.body_b, m.c_a, m.c_b, m.t_a,
                                  m.n_a, m.b_a, m.n_b, m.b_b, m.passive_armature, state.unwrapped, state.coord_vel,
                                  mask, col, self.roff + col, self.eps, m.dtype(COORDINATE_RATE_ROUNDING / h),
                                  self.E], device=m.device)  # fmt: skip
            else:
                c.launch(m, state, s, state.q, self.E, s.g, s.H, mask, 0, s.report_cols, True)

    def allowance(self, state) -> np.ndarray:
        """(num_worlds,) float64: the allowance A of every world's energy in ``state`` (total: what
        the test allows a state's energy for its rounding), with q̇'s rounding that of a step of
        dt (a world's retried substeps round more)."""
        m = self.solver.model
        self.measure(state, self.solver.all_active, self.solver.dt)
        out = wp.zeros(m.num_worlds, dtype=m.dtype, device=m.device)
        wp.launch(self.k["allowance"], dim=m.num_worlds,
                  inputs=[self.E, self.scale, self.ncols, m.dtype(self.floor), self.roff, out], device=m.device)
        return out.numpy().astype(np.float64)

    def host(self, state) -> "HostViews":
        """CPU: the NumPy views of ``state`` the host-side checks read (made once per state)."""
        if self._host is None or self._host.state is not state:
            self._host = HostViews(state, self.solver.model.num_drives)
        return self._host

    def any_checked(self, state) -> bool:
        """CPU (host memory): whether a world has no drive pushing (else the step is not tested, and
        every world's energy is marked unknown, to be computed before a step that is;
        HostViews.any_checked)."""
        h = self._host
        if h is None or h.state is not state:
            h = self.host(state)
        return h.any_checked()

    def before(self, state, hold, go):
        """Before a step (holding the worlds ``hold``, and every world while go[0] == 0): the energy
        of the worlds whose E_before is not known (module docstring)."""
        m = self.solver.model
        if self.cpu and not self.host(state).unknown():  # host memory: no launch where every energy is known
            return
        wp.launch(self.k["unknown"], dim=m.num_worlds, inputs=[state.status, state.fresh, state.energy, hold, go, self.need],
                  device=m.device)  # fmt: skip
        self.measure(state, self.need, self.solver.dt)
        wp.launch(self.k["remember"], dim=m.num_worlds,
                  inputs=[self.E, self.scale, self.ncols, self.gcol, m.dtype(self.floor), self.roff, self.need,
                          state.energy],
                  device=m.device)  # fmt: skip

    def _common(self, state):
        m = self.solver.model
        return [self.E, self.scale, self.ncols, self.gcol, m.dtype(self.floor), self.roff, state.control,
                m.num_drives]

    def judge(self, state, hold, go, idle, flag):
        """After a step and retry.mark: mark the worlds that gained too much for the retry."""
        m, s = self.solver.model, self.solver
        self.measure(state, s.all_active, s.dt)
        wp.launch(self.k["judge"], dim=m.num_worlds,
                  inputs=self._common(state) + [state.status, hold, go, m.dtype(self.tol), state.energy, state.fresh, state.substeps, state.gained,
                                                idle, self.busy, flag], device=m.device)  # fmt: skip

    def settle(self, state, idle, back, n, next_n):
        """After an attempt of n substeps (retry.settle with the energy test)."""
        m = self.solver.model
        self.measure(state, self.busy, self.solver.dt / n)
        wp.launch(self.k["settle"], dim=m.num_worlds,
                  inputs=self._common(state) + [state.status, m.dtype(self.tol), state.energy,
                                                state.fresh, state.substeps, state.gained, idle, self.busy,
                                                back, n, next_n], device=m.device)  # fmt: skip


class HostViews:
    """CPU: NumPy views of a state's arrays (host memory) for the energy test's host-side checks."""

    def __init__(self, state, num_drives: int):
        self.state = state
        self.status, self.fresh = state.status.numpy(), state.fresh.numpy()
        self.control = state.control.numpy()[:, :num_drives]
        self.energy0 = state.energy.numpy()[:, 0]  # E_before, NaN where unknown
        # one world with one drive: that control alone decides (an item compare, no reduction)
        self.single = self.control.size == 1
        self.one_world = self.energy0.size == 1  # (unknown: items, no reduction)
        self.control_item = self.control.reshape(-1) if self.single else None

    def any_checked(self) -> bool:
        """Whether a world has no drive pushing; where none has, its energy is marked unknown.
        Counting the nonzero controls decides the common cases, every control nonzero (no world
        tested) or none (every world), without a per-world reduction."""
        if self.single:
            if self.control_item[0] == 0:
                return True
            self.energy0[0] = np.nan
            return False
        if not self.control.size:  # no drive
            return True
        pushing = np.count_nonzero(self.control)
        if pushing == 0:
            return True
        if pushing < self.control.size and (np.count_nonzero(self.control, axis=1) == 0).any():
            return True
        self.energy0.fill(np.nan)
        return False

    def unknown(self) -> bool:
        """Whether a world OK has no known energy before its step: its state set (fresh SET) or a
        parameter changed (E NaN).  The energies' dot product with themselves is NaN where one is
        NaN (and only there: squares are never NaN, their sum only where inf meets -inf, which
        squares are not), a cheaper reduction than a sum or isnan's; of one world, its items."""
        if self.one_world:
            return self.status.item(0) == OK and (self.fresh.item(0) == SET or math.isnan(self.energy0.item(0)))
        if not math.isnan(self.energy0.dot(self.energy0)) and SET_BYTES not in self.fresh.tobytes():
            return False
        return bool(((self.status == OK) & ((self.fresh == SET) | np.isnan(self.energy0))).any())
