"""Joint drives: motors and implicit PD targets on a revolute angle or prismatic displacement.

The drive coordinate x is the multi-turn angle [rad] (x_prev + ΔΘ(q, q^{t−1})) or the
displacement [m].  Drives are physical potentials, so they sit inside h² in the solve:

- effort (motor): ``E = −τ (x − x_prev)`` with ``τ = clip(u, ±max_effort)`` [N·m or N]; the
  Hessian of x is dropped (a force held over the step).
- position / velocity (implicit PD): force ``f(x) = k(x − x*) + (d/h)(x − x_prev − h v*)``
  (position: x* = u, v* = 0; velocity: k = 0, v* = u).  Under BDF2, h → ĥ = 2h/3 and
  x_prev → x̂ = (4xⁿ − xⁿ⁻¹)/3, its velocity being (x − x̂)/ĥ.  The energy is the integral of
  ``clip(f, ±max_effort)``: a Huber function of x, convex, so large gains stay stable and the
  effort limit holds inside the solve.  ``E = a·huber(x − x0, max_effort/a)``, ``a = k + d/h``.

``energies()["drive"]`` reports the physical spring energy ½k(x − x*)² of position drives.
"""

import functools
from types import SimpleNamespace

import numpy as np
import warp as wp

from ..core.angles import angle_ops
from ..core.warp_ops import ops
from .protocol import COORDINATE, Constitution

NAME = "drive"
UID = None  # libuipc has no drive constitution
EFFORT, POSITION, VELOCITY = 0, 1, 2
MODES = {"effort": EFFORT, "position": POSITION, "velocity": VELOCITY}


def drive_np(x, x_prev, u, mode, k, d, max_effort, h):
    """E(x), E'(x), E''(x) of one drive per unit h² (float64)."""
    if mode == EFFORT:
        tau = float(np.clip(u, -max_effort, max_effort))
        return -tau * (x - x_prev), -tau, 0.0
    xs, vs = (u, 0.0) if mode == POSITION else (0.0, u)
    a = k + d / h
    x0 = (k * xs + d / h * (x_prev + h * vs)) / a
    e = x - x0
    cap = max_effort / a
    if abs(e) <= cap:
        return 0.5 * a * e * e, a * e, a
    return max_effort * (abs(e) - 0.5 * cap), max_effort * np.sign(e), 0.0


@functools.lru_cache(maxsize=None)
def scalar_func(dtype):
    """drive_scalar: one drive's energy and its first two derivatives at its coordinate."""
    half = dtype(0.5)
    zero = dtype(0.0)

    @wp.func
    def drive_scalar(x: dtype, xp: dtype, md: int, u: dtype, fmax: dtype, kp: dtype, kd: dtype, anchor: dtype,
                     h: dtype):  # fmt: skip
        """(E, E'(x), E''(x)) of one drive per unit h² at its coordinate x [rad or m]: effort
        −clip(u, ±fmax)(x − xp); position / velocity the Huber energy of the clipped PD force
        (module docstring; ``kd`` the damping [N·s/m or N·m·s/rad], ``anchor`` x̂ of BDF2, else xp)."""
        e = zero
        de = zero
        dde = zero
        if md == 0:
            tau = wp.clamp(u, -fmax, fmax)
            e = -tau * (x - xp)
            de = -tau
        else:
            kdh = kd / h
            xs = u
            vs = zero
            if md == 2:
                xs = zero
                vs = u
            aa = kp + kdh
            x0 = (kp * xs + kdh * (anchor + h * vs)) / aa
            r = x - x0
            cap = fmax / aa
            if wp.abs(r) <= cap:
                e = half * aa * r * r
                de = aa * r
                dde = aa
            else:
                e = fmax * (wp.abs(r) - half * cap)
                de = fmax * wp.sign(r)
        return e, de, dde

    return drive_scalar


@functools.lru_cache(maxsize=None)
def kernel(dtype):
    o = ops(dtype)
    a = angle_ops(dtype)
    vec12 = o.vec12
    vec3 = o.vec3
    add_energy, scatter_pair, outer_blocks = o.add_energy, o.scatter_pair, o.outer_blocks
    cos_sin, delta_theta, theta_grad = a.cos_sin, a.delta_theta, a.theta_grad
    displacement, displacement_grad = a.displacement, a.displacement_grad
    half = dtype(0.5)
    zero = dtype(0.0)
    drive_scalar = scalar_func(dtype)

    @wp.func
    def drive_parts(
        qi: vec12, qj: vec12, w: int, k: int, joint: wp.array(dtype=wp.int32), joint_kind: wp.array(dtype=wp.int32),
        c_a: wp.array2d(dtype=vec3), c_b: wp.array2d(dtype=vec3), t_a: wp.array2d(dtype=vec3),
        n_a: wp.array2d(dtype=vec3), b_a: wp.array2d(dtype=vec3), n_b: wp.array2d(dtype=vec3), b_b: wp.array2d(dtype=vec3),
        c_prev: wp.array2d(dtype=dtype), s_prev: wp.array2d(dtype=dtype),
        mode: wp.array(dtype=wp.int32), stiffness: wp.array2d(dtype=dtype), damping: wp.array2d(dtype=dtype),
        max_effort: wp.array2d(dtype=dtype), control: wp.array2d(dtype=dtype), x_prev_joint: wp.array2d(dtype=dtype),
        x_anchor: wp.array2d(dtype=dtype),
        h: dtype, scale: dtype, physical: int, derivs: int,
    ):  # fmt: skip
        """(E, E'(x), E''(x), ∇_i x, ∇_j x), scaled by ``scale``: the gradient is E'∇x, the Hessian
        E''∇x∇xᵀ (0 for effort drives and clipped PD drives); ∇x for derivs != 0.  ``physical``:
        E is the report's spring energy and the rest zero."""
        j = joint[k]
        rev = joint_kind[j] == 0
        xp = x_prev_joint[w, j]  # multi-turn angle / displacement at the start of the step
        c = zero
        s = zero
        x = zero
        if rev:
            c, s = cos_sin(qi, qj, n_a[w, j], b_a[w, j], n_b[w, j], b_b[w, j])
            x = xp + delta_theta(c, s, c_prev[w, j], s_prev[w, j])
        else:
            x = displacement(qi, qj, c_a[w, j], c_b[w, j], t_a[w, j])
        md = mode[k]
        u = control[w, k]
        fmax = max_effort[w, k]
        kp = stiffness[w, k]
        gi = vec12()
        gj = vec12()
        if physical != 0:
            e_phys = zero
            if md == 1:
                e_phys = half * kp * (x - u) * (x - u)
            return e_phys, zero, zero, gi, gj
        e, de, dde = drive_scalar(x, xp, md, u, fmax, kp, damping[w, k], x_anchor[w, j], h)
        if derivs != 0 and rev:
            gi, gj = theta_grad(qi, qj, n_a[w, j], b_a[w, j], n_b[w, j], b_b[w, j], c, s)
        elif derivs != 0:
            gi, gj = displacement_grad(qi, qj, c_a[w, j], c_b[w, j], t_a[w, j])
        return scale * e, scale * de, scale * dde, gi, gj

    @wp.func
    def drive_eval(
        qi: vec12, qj: vec12, w: int, k: int, joint: wp.array(dtype=wp.int32), joint_kind: wp.array(dtype=wp.int32),
        c_a: wp.array2d(dtype=vec3), c_b: wp.array2d(dtype=vec3), t_a: wp.array2d(dtype=vec3),
        n_a: wp.array2d(dtype=vec3), b_a: wp.array2d(dtype=vec3), n_b: wp.array2d(dtype=vec3), b_b: wp.array2d(dtype=vec3),
        c_prev: wp.array2d(dtype=dtype), s_prev: wp.array2d(dtype=dtype),
        mode: wp.array(dtype=wp.int32), stiffness: wp.array2d(dtype=dtype), damping: wp.array2d(dtype=dtype),
        max_effort: wp.array2d(dtype=dtype), control: wp.array2d(dtype=dtype), x_prev_joint: wp.array2d(dtype=dtype),
        x_anchor: wp.array2d(dtype=dtype),
        h: dtype, scale: dtype, physical: int, derivs: int,
    ):  # fmt: skip
        """(E, g_i, g_j, H_ii, H_ij, H_jj) of drive k (drive_parts)."""
        e, de, dde, gi, gj = drive_parts(qi, qj, w, k, joint, joint_kind, c_a, c_b, t_a, n_a, b_a, n_b, b_b, c_prev,
                                         s_prev, mode, stiffness, damping, max_effort, control, x_prev_joint, x_anchor,
                                         h, scale, physical, derivs)  # fmt: skip
        # effort drives and clipped PD drives are linear in x (dde = 0): no Hessian to build
        hii, hij, hjj = outer_blocks(gi, gj, dde, derivs)
        return e, de * gi, de * gj, hii, hij, hjj

    @wp.kernel(module="unique")
    def drive(
        q: wp.array2d(dtype=vec12), joint: wp.array(dtype=wp.int32), joint_kind: wp.array(dtype=wp.int32),
        body_a: wp.array(dtype=wp.int32), body_b: wp.array(dtype=wp.int32), dof: wp.array(dtype=wp.int32),
        c_a: wp.array2d(dtype=vec3), c_b: wp.array2d(dtype=vec3), t_a: wp.array2d(dtype=vec3),
        n_a: wp.array2d(dtype=vec3), b_a: wp.array2d(dtype=vec3), n_b: wp.array2d(dtype=vec3), b_b: wp.array2d(dtype=vec3),
        c_prev: wp.array2d(dtype=dtype), s_prev: wp.array2d(dtype=dtype),
        mode: wp.array(dtype=wp.int32), stiffness: wp.array2d(dtype=dtype), damping: wp.array2d(dtype=dtype),
        max_effort: wp.array2d(dtype=dtype), control: wp.array2d(dtype=dtype), x_prev_joint: wp.array2d(dtype=dtype),
        x_anchor: wp.array2d(dtype=dtype),
        h_step: wp.array(dtype=dtype), physical: int, active: wp.array(dtype=wp.int32), derivs: int, col: int,
        E: wp.array2d(dtype=dtype), g: wp.array2d(dtype=dtype), H: wp.array3d(dtype=dtype),
    ):  # fmt: skip
        w, k = wp.tid()
        if active[w] == 0:
            return
        j = joint[k]
        bi = body_a[j]
        bj = body_b[j]
        h = h_step[w]
        scale = h * h  # inside the potential's ĥ²; the report's physical energy is unscaled
        if physical != 0:
            scale = dtype(1.0)
        e, gi, gj, hii, hij, hjj = drive_eval(
            q[w, bi], q[w, bj], w, k, joint, joint_kind, c_a, c_b, t_a, n_a, b_a, n_b, b_b, c_prev, s_prev, mode,
            stiffness, damping, max_effort, control, x_prev_joint, x_anchor, h, scale, physical, derivs)  # fmt: skip
        add_energy(E, w, col, e)
        if derivs != 0 and physical == 0:
            scatter_pair(g, H, w, dof[bi], dof[bj], gi, gj, hii, hij, hjj)

    return SimpleNamespace(kernel=drive, eval=drive_eval, parts=drive_parts, scalar=drive_scalar)


def terms(model, physical=False):
    return (NAME,) if model.num_drives else ()


def launch(model, state, ctx, q, E, g, H, active, derivs, cols, physical=False):
    m = model
    wp.launch(kernel(m.dtype).kernel, dim=(m.num_worlds, m.num_drives),
              inputs=[q, m.drive_joint, m.joint_kind, m.body_a, m.body_b, m.dof, m.c_a, m.c_b, m.t_a,
                      m.n_a, m.b_a, m.n_b, m.b_b, state.c_prev, state.s_prev, m.drive_mode, m.drive_stiffness,
                      m.drive_damping, m.drive_max_effort, state.control, state.unwrapped, state.x_anchor,
                      ctx.h_step, int(physical), active, derivs, cols[NAME], E, g, H], device=m.device)  # fmt: skip


# drives a joint's term folds: one on a prismatic joint's displacement, two on a revolute joint's
# angle (a position and an effort drive on one motor); more keep terms of their own
SLOTS = {"prismatic": 1, "revolute": 2}


@functools.lru_cache(maxsize=None)
def fold(dtype, Terms):
    """Drives folded into their joint's term (protocol.Constitution.fold): ``drive_at``, a drive's
    (E, E′, E″) at its joint's coordinate inside ĥ², and one fold per joint kind."""
    drive_scalar = kernel(dtype).scalar
    REV_SLOTS = SLOTS["revolute"]

    @wp.func
    def drive_at(t: Terms, w: int, j: int, kd: int, x: dtype, hw: dtype):
        """(E, E′, E″) of drive kd on joint j at its coordinate x, inside ĥ² (drive.scalar from the
        joint's coordinate at the step's start, Terms.unwrapped)."""
        ed, dd, ddd = drive_scalar(x, t.unwrapped[w, j], t.drive_mode[kd], t.control[w, kd], t.fmax[w, kd], t.kp[w, kd],
                                   t.kd[w, kd], t.x_anchor[w, j], hw)  # fmt: skip
        h2 = hw * hw
        return h2 * ed, h2 * dd, h2 * ddd

    @wp.func
    def prismatic(t: Terms, w: int, j: int, a: int, x: dtype, e: dtype, de: dtype, dde: dtype):
        """Joint term a's drive, if it has one, at the displacement x."""
        kd = t.fold_drive_prismatic[a]
        if kd >= 0:
            ed, dd, ddd = drive_at(t, w, j, kd, x, t.h_step[w])
            e += ed
            de += dd
            dde += ddd
        return e, de, dde

    @wp.func
    def revolute(t: Terms, w: int, j: int, a: int, x: dtype, hw: dtype, e: dtype, de: dtype, dde: dtype):
        """Joint term a's drives at the multi-turn angle x_prev + δ (x = δ)."""
        for slot in range(REV_SLOTS):
            kd = t.fold_drive_revolute[a, slot]
            if kd >= 0:
                ed, d1, d2 = drive_at(t, w, j, kd, t.unwrapped[w, j] + x, hw)
                e += ed
                de += d1
                dde += d2
        return e, de, dde

    return SimpleNamespace(drive_at=drive_at, prismatic=prismatic, revolute=revolute)


CONSTITUTION = Constitution(NAME, UID, COORDINATE, drive_np, terms, launch, work=10.0,
                            instances=lambda model: [int(j) for j in model.drive_joint.numpy()[: model.num_drives]],
                            slots=SLOTS, fold=fold)  # fmt: skip
