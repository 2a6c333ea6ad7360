"""Forward kinematics of tree mechanisms: joint coordinates and rates to body states, on the device.

``Simulator.set_joint_state`` places each body from its parent, joint by joint, in an order fixed
by the scene's topology (``tree_plan``, built once): a revolute child turns by x about the joint
axis through its anchor, a prismatic child slides by x along the axis, a fixed child keeps its
scene pose relative to its parent; rates add ω = ẋ t (revolute) or v = ẋ t (prismatic) to the
parent's rigid motion.  Bodies no tree joint reaches keep their scene pose at rest; a joint between
two placed bodies closes a loop and is not placed: the coordinates given must close it (a task's
reset computes them from its loop's kinematics), or its gap holds the joint's penalty.  One
kernel does every listed world and writes q, q̇, the restart history (``rows.restart_q``) and the
joints' coordinates and angle history, so a reset costs one launch, not a host computation and a
transfer of every body's state (nor, on a GPU, the launches of a step's bracketing kernels: the vector env's autoreset runs it
in each step).
"""

import functools
from dataclasses import dataclass

import numpy as np
import warp as wp

from . import loops
from .coordinates import PRISMATIC_CODE, REVOLUTE_CODE
from .coordinates import funcs as coordinate_funcs
from ..core.rows import world_of
from ..core.warp_ops import ops
from ..solver.kernels import SET


@dataclass
class TreePlan:
    """Placement order on the device: per tree joint (in order) its joint index, parent, child, kind,
    sign (−1 when the joint's first body is the child) and, in the parent's frame, the child's
    rest rotation and position, the joint axis and anchor; per body its scene pose."""

    steps: wp.array  # (S, 4) int32: joint, parent, child, kind
    sign: wp.array  # (S,)
    R_rel0: wp.array  # (S,) mat33
    p_rel0: wp.array  # (S,) vec3
    t_loc: wp.array  # (S,) vec3
    c_loc: wp.array  # (S,) vec3
    R0: wp.array  # (bodies,) mat33
    p0: wp.array  # (bodies,) vec3


def tree_plan(scene, model) -> TreePlan:
    """The order forward kinematics places bodies in (fixed bodies first, then free roots)."""
    bodies = scene.bodies
    rows = []
    for k, par, ch, sign in loops.tree_order(scene)[0]:
        j, Bp, Bc = scene.joints[k], bodies[par], bodies[ch]
        rows.append(((k, par, ch, model.joint_kind_np[k]), sign, Bp.rotation.T @ Bc.rotation,
                     Bp.rotation.T @ (Bc.position - Bp.position), Bp.to_local_dir(j.frame[0]),
                     Bp.to_local_point(j.anchor)))  # fmt: skip
    dev, npd = model.device, model.np_dtype

    def arr(values, dtype, shape):
        return wp.array(np.asarray(values, dtype=npd).reshape(shape), dtype=dtype, device=dev)

    S = len(rows)
    return TreePlan(
        steps=wp.array(np.array([r[0] for r in rows], dtype=np.int32).reshape(S, 4), dtype=wp.int32, device=dev),
        sign=arr([r[1] for r in rows], model.dtype, (S,)),
        R_rel0=arr([r[2] for r in rows], model.mat33, (S, 3, 3)),
        p_rel0=arr([r[3] for r in rows], model.vec3, (S, 3)),
        t_loc=arr([r[4] for r in rows], model.vec3, (S, 3)),
        c_loc=arr([r[5] for r in rows], model.vec3, (S, 3)),
        R0=arr([b.rotation for b in bodies], model.mat33, (len(bodies), 3, 3)),
        p0=arr([b.position for b in bodies], model.vec3, (len(bodies), 3)),
    )


@functools.lru_cache(maxsize=None)
def kernels(dtype, passive=False):
    """The restart kernel; ``passive``: it also restarts the passive terms' rate history."""
    o = ops(dtype)
    vec3, vec12, mat33 = o.vec3, o.vec12, o.mat33
    one = dtype(1.0)

    @wp.func
    def pack(p: vec3, R: mat33):
        """q = (p, rows of R)."""
        return vec12(p[0], p[1], p[2], R[0, 0], R[0, 1], R[0, 2], R[1, 0], R[1, 1], R[1, 2], R[2, 0], R[2, 1], R[2, 2])

    @wp.func
    def rotation(q: vec12):
        return mat33(q[3], q[4], q[5], q[6], q[7], q[8], q[9], q[10], q[11])

    @wp.func
    def axis_rotation(t: vec3, x: dtype):
        """Rotation by x [rad] about the unit axis t (Rodrigues)."""
        K = wp.skew(t)
        return wp.identity(3, dtype) + wp.sin(x) * K + (one - wp.cos(x)) * (K * K)

    begin_joint, joint_coordinates = coordinate_funcs(dtype, passive)[:2]

    @wp.kernel(module="unique")
    def restart(
        idx: wp.array(dtype=wp.int32), xx: wp.array3d(dtype=dtype),
        steps: wp.array2d(dtype=wp.int32), sign: wp.array(dtype=dtype), R_rel0: wp.array(dtype=mat33),
        p_rel0: wp.array(dtype=vec3), t_loc: wp.array(dtype=vec3), c_loc: wp.array(dtype=vec3),
        R0: wp.array(dtype=mat33), p0: wp.array(dtype=vec3), dt: dtype, omega: wp.array2d(dtype=vec3),
        q: wp.array2d(dtype=vec12), qd: wp.array2d(dtype=vec12), q_prev: wp.array2d(dtype=vec12),
        q_hist: wp.array2d(dtype=vec12), qd_hist: wp.array2d(dtype=vec12), qd_hist2: wp.array2d(dtype=vec12),
        order3: wp.array2d(dtype=wp.int32), status: wp.array(dtype=wp.int32),
        fresh: wp.array(dtype=wp.int32), mask: wp.array(dtype=wp.int32), masked: int,
        num_joints: int, body_a: wp.array(dtype=wp.int32), body_b: wp.array(dtype=wp.int32),
        kind: wp.array(dtype=wp.int32), c_a: wp.array2d(dtype=vec3), c_b: wp.array2d(dtype=vec3),
        t_a: wp.array2d(dtype=vec3), n_a: wp.array2d(dtype=vec3), b_a: wp.array2d(dtype=vec3),
        n_b: wp.array2d(dtype=vec3), b_b: wp.array2d(dtype=vec3), c_ref: wp.array2d(dtype=dtype),
        s_ref: wp.array2d(dtype=dtype), theta0: wp.array2d(dtype=dtype), c_prev: wp.array2d(dtype=dtype),
        s_prev: wp.array2d(dtype=dtype), unwrapped: wp.array2d(dtype=dtype), x_hist: wp.array2d(dtype=dtype),
        h_step: wp.array(dtype=dtype), h: dtype, x_anchor: wp.array2d(dtype=dtype), coord: wp.array2d(dtype=dtype),
        coord_vel: wp.array2d(dtype=dtype), coord_vel_hist: wp.array2d(dtype=dtype), v_anchor: wp.array2d(dtype=dtype),
    ):  # fmt: skip
        """World idx[i] at joint coordinates xx[i, 0] and rates xx[i, 1], its whole restart in one
        thread: the bodies placed (below), their restart history as rows.restart_q (no past:
        q^{n−1} = q − dt q̇, q̇^{n−1} = q̇, fresh) and status OK; then, as a step's bracket does, each
        joint's angle history (coordinates.begin_joint, from q^{t−1} = q), its coordinate and its
        rate ∇x·q̇ (joint_coordinates), and its multi-turn coordinate xx[i, 0, j] with the BDF2
        history x^{n−1} = x − dt ẋ.  ``omega`` holds each body's angular velocity while the tree is
        walked.  ``masked``: thread i is world i, placed from xx[i] where mask[i] != 0 (idx unused)."""
        i = wp.tid()
        k = world_of(i, idx, mask, masked)
        if k < 0:
            return
        for b in range(q.shape[1]):
            q[k, b] = pack(p0[b], R0[b])
            qd[k, b] = vec12()
            omega[k, b] = vec3()
        for s in range(steps.shape[0]):
            j = steps[s, 0]
            par = steps[s, 1]
            ch = steps[s, 2]
            step_kind = steps[s, 3]
            xs = sign[s] * xx[i, 0, j]
            vs = sign[s] * xx[i, 1, j]
            qp = q[k, par]
            Rp = rotation(qp)
            pp = vec3(qp[0], qp[1], qp[2])
            vpar = qd[k, par]
            vp = vec3(vpar[0], vpar[1], vpar[2])
            wpar = omega[k, par]
            R_rel = R_rel0[s]
            p_rel = p_rel0[s]
            if step_kind == REVOLUTE_CODE:
                G = axis_rotation(t_loc[s], xs)
                R_rel = G * R_rel
                p_rel = c_loc[s] + G * (p_rel - c_loc[s])
            elif step_kind == PRISMATIC_CODE:
                p_rel = p_rel + xs * t_loc[s]
            Rc = Rp * R_rel
            pc = pp + Rp * p_rel
            t_world = Rp * t_loc[s]
            vc = vp + wp.cross(wpar, pc - pp)
            wc = wpar
            if step_kind == REVOLUTE_CODE:
                anchor = pp + Rp * c_loc[s]
                wc = wc + vs * t_world
                vc = vc + wp.cross(vs * t_world, pc - anchor)
            elif step_kind == PRISMATIC_CODE:
                vc = vc + vs * t_world
            q[k, ch] = pack(pc, Rc)
            qd[k, ch] = pack(vc, wp.skew(wc) * Rc)
            omega[k, ch] = wc
        for b in range(q.shape[1]):
            qb = q[k, b]
            vb = qd[k, b]
            q_prev[k, b] = qb
            q_hist[k, b] = qb - dt * vb
            qd_hist[k, b] = vb
            qd_hist2[k, b] = vb
            order3[k, b] = 0
        status[k] = 0
        fresh[k] = SET
        for j in range(num_joints):
            begin_joint(q, body_a, body_b, kind, n_a, b_a, n_b, b_b, c_ref, s_ref, theta0, c_prev, s_prev, unwrapped,
                        x_hist, h_step, h, x_anchor, coord_vel, coord_vel_hist, v_anchor, k, j)  # fmt: skip
        for j in range(num_joints):
            joint_coordinates(q, q_prev, qd, body_a, body_b, kind, c_a, c_b, t_a, n_a, b_a, n_b, b_b, theta0, c_prev,
                              s_prev, h, h_step, 0, 1, coord, coord_vel, unwrapped, x_hist, coord_vel_hist, k, j)  # fmt: skip
        for j in range(num_joints):
            u = xx[i, 0, j]
            unwrapped[k, j] = u
            x_hist[k, j] = u - dt * coord_vel[k, j]

    return restart


def restart_launch(plan: TreePlan, omega: wp.array, state, model, solver, idx: wp.array, xx: wp.array, N: int,
                   dt: float, mask: wp.array | None = None):  # fmt: skip
    """(kernel, dim, inputs) that restart the worlds idx[:N] at joint coordinates xx[:N, 0] and rates
    xx[:N, 1] (device arrays; xx (≥N, 2, max(joints, 1))), bodies and joints (see ``restart``), for
    the caller to launch or replay.  With ``mask`` (int32 (W,)): every world w with mask[w] != 0,
    from xx[w] (N = W, idx unused).  ``omega``: the (W, bodies) angular velocities the walk keeps;
    ``solver``: its step length h and per-world h_step (the joints' drive anchors)."""
    masked, m, st = mask is not None, model, state
    return kernels(model.dtype, model.num_passive > 0), N, [
        idx, xx, plan.steps, plan.sign, plan.R_rel0, plan.p_rel0, plan.t_loc, plan.c_loc, plan.R0, plan.p0, float(dt),
        omega, st.q, st.qd, st.q_prev, st.q_hist, st.qd_hist, st.qd_hist2, st.order3, st.status, st.fresh,
        mask if masked else idx, int(masked),
        m.num_joints, m.body_a, m.body_b, m.joint_kind, m.c_a, m.c_b, m.t_a, m.n_a, m.b_a, m.n_b, m.b_b, m.c_ref, m.s_ref,
        st.theta0, st.c_prev, st.s_prev, st.unwrapped, st.x_hist, solver.h_step, float(solver.dt), st.x_anchor, st.coord,
        st.coord_vel, st.coord_vel_hist, st.v_anchor]
