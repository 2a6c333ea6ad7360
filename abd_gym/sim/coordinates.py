"""Kernels that bracket a step: joint-angle history before it, coordinates and velocities after.

Per revolute joint the state keeps ``θ0 = ΔΘ(q^{t−1}, q_ref)`` and ``(cos, sin)θ(q^{t−1})`` for
the limit (seed 670), and a multi-turn angle that accumulates each step's ``δ``.
"""

import functools

import warp as wp

from ..core.angles import angle_ops
from ..solver.kernels import RESTART
from ..core.warp_ops import ops

REVOLUTE_CODE, PRISMATIC_CODE, FIXED_CODE = 0, 1, 2


@functools.lru_cache(maxsize=None)
def kernels(dtype, passive=False):
    """(begin_step, coordinates): the kernels; funcs(dtype): their per-joint functions.  ``passive``:
    they keep the passive terms' rate history and predicted rate (State.coord_vel_hist, v_anchor)."""
    return _begin(dtype, bool(passive))[1], _coordinates(dtype, bool(passive))[1]


@functools.lru_cache(maxsize=None)
def funcs(dtype, passive=False):
    """(begin_joint, joint_coordinates, close_joint): one joint of one world each (for the fused
    step); ``passive`` as for kernels."""
    begin_joint, _ = _begin(dtype, bool(passive))
    joint_coordinates, _ = _coordinates(dtype, bool(passive))
    return begin_joint, joint_coordinates, _close_joint(dtype, bool(passive))


@functools.lru_cache(maxsize=None)
def restart_funcs(dtype):
    """(limit_engaged, restart_engaged): a BDF2 world's history restarts where a limit is engaged
    (solver.kernels.open_body)."""
    return _restart(dtype)


@functools.lru_cache(maxsize=None)
def _anchors(dtype):
    """(anchor, rate_anchor, step_rate): a joint's anchor coordinate and predicted rate at the start
    of a step, and its rate at the end."""

    @wp.func
    def anchor(unwrapped: wp.array2d(dtype=dtype), x_hist: wp.array2d(dtype=dtype), bdf2_step: bool, w: int, j: int):
        """The drives' anchor coordinate of a step: xⁿ, or x̂ = (4xⁿ − xⁿ⁻¹)/3 = xⁿ + (xⁿ − xⁿ⁻¹)/3 for
        a BDF2 step (the difference first: its rounding is the increment's)."""
        if bdf2_step:
            return unwrapped[w, j] + (unwrapped[w, j] - x_hist[w, j]) / dtype(3.0)
        return unwrapped[w, j]

    @wp.func
    def rate_anchor(velocity: wp.array2d(dtype=dtype), velocity_hist: wp.array2d(dtype=dtype),
                    v_anchor: wp.array2d(dtype=dtype), bdf2_step: bool, w: int, j: int):  # fmt: skip
        """The passive terms' predicted rate v̂ of a step [rad/s or m/s]: ẋⁿ, or (4ẋⁿ − ẋⁿ⁻¹)/3 =
        ẋⁿ + (ẋⁿ − ẋⁿ⁻¹)/3 for a BDF2 step (the bodies' v̂, solver.kernels.predict_body)."""
        v = velocity[w, j]
        if bdf2_step:
            v = v + (v - velocity_hist[w, j]) / dtype(3.0)
        v_anchor[w, j] = v

    @wp.func
    def step_rate(d: dtype, unwrapped: wp.array2d(dtype=dtype), x_hist: wp.array2d(dtype=dtype), h: dtype,
                  h_step: wp.array(dtype=dtype), w: int, j: int):  # fmt: skip
        """A coordinate's rate at the end of a step [rad/s or m/s] from its increment d = xⁿ⁺¹ − xⁿ:
        d/h after an implicit Euler step; after a BDF2 step (h_step = 2h/3 < h) BDF2's own
        (3xⁿ⁺¹ − 4xⁿ + xⁿ⁻¹)/(2h) = (3d − (xⁿ − xⁿ⁻¹))/(2h) (xⁿ, xⁿ⁻¹: unwrapped, x_hist before the
        step's update), as the bodies' q̇ is: the quotient d/h is the step's mean rate, half a step
        behind (under a constant force, 5/6 of the rate after the second step).  The history is
        read only after a BDF2 step."""
        if h_step[w] < h:
            return (dtype(3.0) * d - (unwrapped[w, j] - x_hist[w, j])) / (dtype(2.0) * h)
        return d / h

    return anchor, rate_anchor, step_rate


@functools.lru_cache(maxsize=None)
def _joint_math(dtype):
    """(vec3, vec12, cos_sin, delta_theta, displacement, theta_grad, displacement_grad): the vector
    types and the joint-coordinate functions (core.angles) the factories below build on."""
    o, a = ops(dtype), angle_ops(dtype)
    return o.vec3, o.vec12, a.cos_sin, a.delta_theta, a.displacement, a.theta_grad, a.displacement_grad


@functools.lru_cache(maxsize=None)
def _begin(dtype, passive):
    """(begin_joint, begin_step): a joint's references and anchors before a step."""
    vec3, vec12, cos_sin, delta_theta, *_ = _joint_math(dtype)
    anchor, rate_anchor, _ = _anchors(dtype)

    @wp.func
    def begin_joint(
        q: wp.array2d(dtype=vec12), body_a: wp.array(dtype=wp.int32), body_b: wp.array(dtype=wp.int32),
        kind: wp.array(dtype=wp.int32),
        n_a: wp.array2d(dtype=vec3), b_a: wp.array2d(dtype=vec3), n_b: wp.array2d(dtype=vec3), b_b: wp.array2d(dtype=vec3),
        c_ref: wp.array2d(dtype=dtype), s_ref: wp.array2d(dtype=dtype),
        theta0: wp.array2d(dtype=dtype), c_prev: wp.array2d(dtype=dtype), s_prev: wp.array2d(dtype=dtype),
        unwrapped: wp.array2d(dtype=dtype), x_hist: wp.array2d(dtype=dtype),
        h_step: wp.array(dtype=dtype), h: dtype, x_anchor: wp.array2d(dtype=dtype), velocity: wp.array2d(dtype=dtype),
        velocity_hist: wp.array2d(dtype=dtype), v_anchor: wp.array2d(dtype=dtype), w: int, j: int,
    ):  # fmt: skip
        """θ0 and cos/sin θ of q^{t−1} (the state at the start of the step), and the drives' anchor
        coordinate: xⁿ, or x̂ = (4xⁿ − xⁿ⁻¹)/3 for a BDF2 step (h_step[w] = 2h/3 < h), with passive
        terms their predicted rate (rate_anchor); joint j of world w."""
        x_anchor[w, j] = anchor(unwrapped, x_hist, h_step[w] < h, w, j)
        if wp.static(passive):
            rate_anchor(velocity, velocity_hist, v_anchor, h_step[w] < h, w, j)
        if kind[j] != REVOLUTE_CODE:
            return
        c, s = cos_sin(q[w, body_a[j]], q[w, body_b[j]], n_a[w, j], b_a[w, j], n_b[w, j], b_b[w, j])
        c_prev[w, j] = c
        s_prev[w, j] = s
        theta0[w, j] = delta_theta(c, s, c_ref[w, j], s_ref[w, j])

    @wp.kernel(module="unique")
    def begin_step(
        q: wp.array2d(dtype=vec12), body_a: wp.array(dtype=wp.int32), body_b: wp.array(dtype=wp.int32),
        kind: wp.array(dtype=wp.int32),
        n_a: wp.array2d(dtype=vec3), b_a: wp.array2d(dtype=vec3), n_b: wp.array2d(dtype=vec3), b_b: wp.array2d(dtype=vec3),
        c_ref: wp.array2d(dtype=dtype), s_ref: wp.array2d(dtype=dtype),
        theta0: wp.array2d(dtype=dtype), c_prev: wp.array2d(dtype=dtype), s_prev: wp.array2d(dtype=dtype),
        mask: wp.array(dtype=wp.int32), unwrapped: wp.array2d(dtype=dtype), x_hist: wp.array2d(dtype=dtype),
        h_step: wp.array(dtype=dtype), h: dtype, x_anchor: wp.array2d(dtype=dtype), velocity: wp.array2d(dtype=dtype),
        velocity_hist: wp.array2d(dtype=dtype), v_anchor: wp.array2d(dtype=dtype),
    ):  # fmt: skip
        """begin_joint of joint j of each world w in mask."""
        w, j = wp.tid()
        if mask[w] == 0:
            return
        begin_joint(q, body_a, body_b, kind, n_a, b_a, n_b, b_b, c_ref, s_ref, theta0, c_prev, s_prev, unwrapped, x_hist,
                    h_step, h, x_anchor, velocity, velocity_hist, v_anchor, w, j)  # fmt: skip

    return begin_joint, begin_step


@functools.lru_cache(maxsize=None)
def _coordinates(dtype, passive):
    """(joint_coordinates, coordinates): a joint's coordinate and rate after a step."""
    vec3, vec12, cos_sin, delta_theta, displacement, theta_grad, displacement_grad = _joint_math(dtype)
    step_rate = _anchors(dtype)[2]

    @wp.func
    def joint_coordinates(
        q: wp.array2d(dtype=vec12), q_prev: wp.array2d(dtype=vec12), qd: wp.array2d(dtype=vec12),
        body_a: wp.array(dtype=wp.int32), body_b: wp.array(dtype=wp.int32), kind: wp.array(dtype=wp.int32),
        c_a: wp.array2d(dtype=vec3), c_b: wp.array2d(dtype=vec3), t_a: wp.array2d(dtype=vec3),
        n_a: wp.array2d(dtype=vec3), b_a: wp.array2d(dtype=vec3), n_b: wp.array2d(dtype=vec3), b_b: wp.array2d(dtype=vec3),
        theta0: wp.array2d(dtype=dtype), c_prev: wp.array2d(dtype=dtype), s_prev: wp.array2d(dtype=dtype),
        h: dtype, h_step: wp.array(dtype=dtype), accumulate: int, rate_from_qd: int,
        coord: wp.array2d(dtype=dtype), velocity: wp.array2d(dtype=dtype), unwrapped: wp.array2d(dtype=dtype),
        x_hist: wp.array2d(dtype=dtype), velocity_hist: wp.array2d(dtype=dtype),
        w: int, j: int,
    ):  # fmt: skip
        """x = θ0 + ΔΘ(q, q^{t−1}) (seed), its rate (step_rate), and the multi-turn angle; displacement.

        ``rate_from_qd``: after a state is set there is no step to take a rate over, so the rate is
        the instantaneous ∇x·q̇ (with passive terms, its history too: no past).  With passive terms
        and ``accumulate``, the rate's history shifts (ẋⁿ⁻¹ ← ẋⁿ).
        """
        if wp.static(passive):
            if accumulate != 0:
                velocity_hist[w, j] = velocity[w, j]
        qi = q[w, body_a[j]]
        qj = q[w, body_b[j]]
        if kind[j] == REVOLUTE_CODE:
            c, s = cos_sin(qi, qj, n_a[w, j], b_a[w, j], n_b[w, j], b_b[w, j])
            d = delta_theta(c, s, c_prev[w, j], s_prev[w, j])
            coord[w, j] = theta0[w, j] + d
            velocity[w, j] = step_rate(d, unwrapped, x_hist, h, h_step, w, j)
            if rate_from_qd != 0:
                gi, gj = theta_grad(qi, qj, n_a[w, j], b_a[w, j], n_b[w, j], b_b[w, j], c, s)
                velocity[w, j] = wp.dot(gi, qd[w, body_a[j]]) + wp.dot(gj, qd[w, body_b[j]])
            if accumulate != 0:
                x_hist[w, j] = unwrapped[w, j]
                unwrapped[w, j] = unwrapped[w, j] + d
        elif kind[j] == PRISMATIC_CODE:
            x = displacement(qi, qj, c_a[w, j], c_b[w, j], t_a[w, j])
            xp = displacement(q_prev[w, body_a[j]], q_prev[w, body_b[j]], c_a[w, j], c_b[w, j], t_a[w, j])
            coord[w, j] = x
            velocity[w, j] = step_rate(x - xp, unwrapped, x_hist, h, h_step, w, j)
            if rate_from_qd != 0:
                gi, gj = displacement_grad(qi, qj, c_a[w, j], c_b[w, j], t_a[w, j])
                velocity[w, j] = wp.dot(gi, qd[w, body_a[j]]) + wp.dot(gj, qd[w, body_b[j]])
            if accumulate != 0:
                x_hist[w, j] = unwrapped[w, j]
                unwrapped[w, j] = x
        if wp.static(passive):
            if rate_from_qd != 0:
                velocity_hist[w, j] = velocity[w, j]

    @wp.kernel(module="unique")
    def coordinates(
        q: wp.array2d(dtype=vec12), q_prev: wp.array2d(dtype=vec12), qd: wp.array2d(dtype=vec12),
        body_a: wp.array(dtype=wp.int32), body_b: wp.array(dtype=wp.int32), kind: wp.array(dtype=wp.int32),
        c_a: wp.array2d(dtype=vec3), c_b: wp.array2d(dtype=vec3), t_a: wp.array2d(dtype=vec3),
        n_a: wp.array2d(dtype=vec3), b_a: wp.array2d(dtype=vec3), n_b: wp.array2d(dtype=vec3), b_b: wp.array2d(dtype=vec3),
        theta0: wp.array2d(dtype=dtype), c_prev: wp.array2d(dtype=dtype), s_prev: wp.array2d(dtype=dtype),
        h: dtype, h_step: wp.array(dtype=dtype), status: wp.array(dtype=wp.int32), mask: wp.array(dtype=wp.int32),
        accumulate: int, rate_from_qd: int,
        coord: wp.array2d(dtype=dtype), velocity: wp.array2d(dtype=dtype), unwrapped: wp.array2d(dtype=dtype),
        x_hist: wp.array2d(dtype=dtype), velocity_hist: wp.array2d(dtype=dtype),
    ):  # fmt: skip
        """joint_coordinates of joint j of each healthy world w in mask."""
        w, j = wp.tid()
        if status[w] != 0 or mask[w] == 0:
            return
        joint_coordinates(q, q_prev, qd, body_a, body_b, kind, c_a, c_b, t_a, n_a, b_a, n_b, b_b, theta0, c_prev, s_prev, h,
                          h_step, accumulate, rate_from_qd, coord, velocity, unwrapped, x_hist, velocity_hist, w, j)  # fmt: skip

    return joint_coordinates, coordinates


@functools.lru_cache(maxsize=None)
def _close_joint(dtype, passive):
    """close_joint: the fused step's close of a joint, which also opens its next step."""
    vec3, vec12, cos_sin, delta_theta, displacement, *_ = _joint_math(dtype)
    anchor, rate_anchor, step_rate = _anchors(dtype)

    @wp.func
    def close_joint(
        q: wp.array2d(dtype=vec12), q_prev: wp.array2d(dtype=vec12), body_a: wp.array(dtype=wp.int32),
        body_b: wp.array(dtype=wp.int32), kind: wp.array(dtype=wp.int32),
        c_a: wp.array2d(dtype=vec3), c_b: wp.array2d(dtype=vec3), t_a: wp.array2d(dtype=vec3),
        n_a: wp.array2d(dtype=vec3), b_a: wp.array2d(dtype=vec3), n_b: wp.array2d(dtype=vec3), b_b: wp.array2d(dtype=vec3),
        theta0: wp.array2d(dtype=dtype), c_prev: wp.array2d(dtype=dtype), s_prev: wp.array2d(dtype=dtype),
        c_ref: wp.array2d(dtype=dtype), s_ref: wp.array2d(dtype=dtype), h: dtype, h_step: wp.array(dtype=dtype), bdf2: int,
        coord: wp.array2d(dtype=dtype), velocity: wp.array2d(dtype=dtype), unwrapped: wp.array2d(dtype=dtype),
        x_hist: wp.array2d(dtype=dtype), x_anchor: wp.array2d(dtype=dtype), velocity_hist: wp.array2d(dtype=dtype),
        v_anchor: wp.array2d(dtype=dtype), w: int, j: int,
    ):  # fmt: skip
        """The fused step's close of joint j of world w: joint_coordinates (accumulating the
        multi-turn angle), then what begin_joint would compute from the same q as the next step
        opens, from the cos/sin just computed: θ0 = ΔΘ(q, q_ref), (cos, sin)θ and the drives'
        anchor (x, or x̂ = x + (x − x_prev)/3 for BDF2, whose next step is not a fresh one) and, with
        passive terms, the rate's history and predicted rate (rate_anchor).  The
        same values, one cos_sin a step fewer; a world set between steps (fresh) opens with
        begin_joint.  (joint_coordinates' arithmetic written out, not called: calling it and then
        storing its cos/sin builds a larger kernel with a larger stack frame, and where a world's
        step is a latency-bound chain its time follows its code size.)"""
        if wp.static(passive):
            velocity_hist[w, j] = velocity[w, j]
        qi = q[w, body_a[j]]
        qj = q[w, body_b[j]]
        if kind[j] == REVOLUTE_CODE:
            c, s = cos_sin(qi, qj, n_a[w, j], b_a[w, j], n_b[w, j], b_b[w, j])
            d = delta_theta(c, s, c_prev[w, j], s_prev[w, j])
            coord[w, j] = theta0[w, j] + d
            velocity[w, j] = step_rate(d, unwrapped, x_hist, h, h_step, w, j)
            x_hist[w, j] = unwrapped[w, j]
            unwrapped[w, j] = unwrapped[w, j] + d
            c_prev[w, j] = c
            s_prev[w, j] = s
            theta0[w, j] = delta_theta(c, s, c_ref[w, j], s_ref[w, j])
        elif kind[j] == PRISMATIC_CODE:
            x = displacement(qi, qj, c_a[w, j], c_b[w, j], t_a[w, j])
            xp = displacement(q_prev[w, body_a[j]], q_prev[w, body_b[j]], c_a[w, j], c_b[w, j], t_a[w, j])
            coord[w, j] = x
            velocity[w, j] = step_rate(x - xp, unwrapped, x_hist, h, h_step, w, j)
            x_hist[w, j] = unwrapped[w, j]
            unwrapped[w, j] = x
        x_anchor[w, j] = anchor(unwrapped, x_hist, bdf2 != 0, w, j)
        if wp.static(passive):
            rate_anchor(velocity, velocity_hist, v_anchor, bdf2 != 0, w, j)

    return close_joint


@functools.lru_cache(maxsize=None)
def _restart(dtype):
    """(limit_engaged, restart_engaged): see restart_funcs."""

    @wp.func
    def limit_engaged(coord: wp.array2d(dtype=dtype), lim_ids: wp.array(dtype=wp.int32), lo: wp.array2d(dtype=dtype),
                      up: wp.array2d(dtype=dtype), count: int, w: int):  # fmt: skip
        """1 where one of world w's ``count`` limits (joint lim_ids[k], bounds lo[w, k] ≤ x ≤ up[w, k])
        has its joint's coordinate x = coord[w, j] outside its bounds (its energy not zero), else 0."""
        engaged = int(0)
        for k in range(count):
            x = coord[w, lim_ids[k]]
            if x < lo[w, k] or x > up[w, k]:
                engaged = 1
        return engaged

    @wp.kernel(module="unique")
    def restart_engaged(
        coord: wp.array2d(dtype=dtype), status: wp.array(dtype=wp.int32), fresh: wp.array(dtype=wp.int32),
        rlim_ids: wp.array(dtype=wp.int32), rlim_lo: wp.array2d(dtype=dtype), rlim_up: wp.array2d(dtype=dtype),
        num_rlim: int, plim_ids: wp.array(dtype=wp.int32), plim_lo: wp.array2d(dtype=dtype),
        plim_up: wp.array2d(dtype=dtype), num_plim: int,
    ):  # fmt: skip
        """A healthy world w with a limit engaged at the end of its step restarts its BDF2 history
        (fresh[w] = RESTART; solver.kernels.open_body)."""
        w = wp.tid()
        if status[w] != 0:
            return
        if limit_engaged(coord, rlim_ids, rlim_lo, rlim_up, num_rlim, w) + limit_engaged(
                coord, plim_ids, plim_lo, plim_up, num_plim, w) != 0:  # fmt: skip
            fresh[w] = RESTART

    return limit_engaged, restart_engaged
