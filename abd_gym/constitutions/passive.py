"""Passive joint terms: a joint's damping and armature (MuJoCo's joint ``damping``, ``armature``).

On the joint coordinate x (the drives' x, drive.py: the multi-turn angle [rad] or the
displacement [m]), inside the potential's ĥ² as the drives are:

    E(x) = a/(2ĥ²)·(x − x̂ − ĥ v̂)² + d/(2ĥ)·(x − x̂)²

with a the armature [kg·m² or kg], d the damping [N·m·s/rad or N·s/m], ĥ the world's step (h, or
2h/3 for BDF2), x̂ the step's anchor (``State.x_anchor``: xⁿ, or (4xⁿ − xⁿ⁻¹)/3) and v̂ its predicted
rate (``State.v_anchor``: ẋⁿ, or (4ẋⁿ − ẋⁿ⁻¹)/3).  x − x̂ = ĥ ẋⁿ⁺¹ (both integrators' rate), so
E′ = a(ẋⁿ⁺¹ − v̂)/ĥ + d ẋⁿ⁺¹: the armature is an inertia on x, predicted exactly as the bodies'
inertia predicts q̃ (solver.kernels.predict_body), and the damper the force −d ẋⁿ⁺¹.  A quadratic:
E″ = a/ĥ² + d/ĥ.  The terms below return ĥ²·(E, E′, E″).

``energies()["kinetic"]`` includes the armature's ½ a ẋ²; the damper's work is dissipated.
The fused step always folds the term into its joint's (one instance a joint).
"""

import functools
from types import SimpleNamespace

import warp as wp

from ..core.angles import angle_ops
from ..core.warp_ops import ops
from .protocol import COORDINATE, Constitution

NAME = "passive"
UID = None  # libuipc has no passive joint constitution


def passive_np(x, x_anchor, v_anchor, armature, damping, h):
    """E(x), E′(x), E″(x) of the passive term per unit ĥ² (float64; h = ĥ)."""
    r = x - x_anchor
    ra = r - h * v_anchor
    e = 0.5 * armature / h**2 * ra * ra + 0.5 * damping / h * r * r
    return e, armature / h**2 * ra + damping / h * r, armature / h**2 + damping / h


@functools.lru_cache(maxsize=None)
def kernel(dtype):
    o = ops(dtype)
    an = angle_ops(dtype)
    vec12, vec3 = o.vec12, o.vec3
    add_energy, scatter_pair, outer_blocks = o.add_energy, o.scatter_pair, o.outer_blocks
    cos_sin, delta_theta, theta_grad = an.cos_sin, an.delta_theta, an.theta_grad
    displacement, displacement_grad = an.displacement, an.displacement_grad
    half = dtype(0.5)

    @wp.func
    def passive_scalar(r: dtype, v: dtype, arm: dtype, damp: dtype, h: dtype):
        """ĥ²·(E, E′, E″) at r = x − x̂ [rad or m], v = v̂ [rad/s or m/s], h = ĥ [s]: a·(r − ĥv̂)²/2 +
        d·ĥ·r²/2 (no division: the energy is the module's, times ĥ²)."""
        ra = r - h * v
        dh = damp * h
        return half * (arm * ra * ra + dh * r * r), arm * ra + dh * r, arm + dh

    @wp.func
    def passive_parts(
        qi: vec12, qj: vec12, w: int, k: int, joint: wp.array(dtype=wp.int32), joint_kind: wp.array(dtype=wp.int32),
        c_a: wp.array2d(dtype=vec3), c_b: wp.array2d(dtype=vec3), t_a: wp.array2d(dtype=vec3),
        n_a: wp.array2d(dtype=vec3), b_a: wp.array2d(dtype=vec3), n_b: wp.array2d(dtype=vec3), b_b: wp.array2d(dtype=vec3),
        c_prev: wp.array2d(dtype=dtype), s_prev: wp.array2d(dtype=dtype),
        armature: wp.array2d(dtype=dtype), damping: wp.array2d(dtype=dtype), unwrapped: wp.array2d(dtype=dtype),
        x_anchor: wp.array2d(dtype=dtype), v_anchor: wp.array2d(dtype=dtype), h: dtype, derivs: int,
    ):  # fmt: skip
        """ĥ²·(E, E′, E″) of passive term k and ∇_i x, ∇_j x (for derivs != 0).  A revolute joint's
        r = x − x̂ is δ − (x̂ − xⁿ), δ = ΔΘ(q, q^{t−1}), as the fused angle term forms it."""
        j = joint[k]
        r = dtype(0.0)
        c = dtype(0.0)
        s = dtype(0.0)
        rev = joint_kind[j] == 0
        if rev:
            c, s = cos_sin(qi, qj, n_a[w, j], b_a[w, j], n_b[w, j], b_b[w, j])
            r = delta_theta(c, s, c_prev[w, j], s_prev[w, j]) - (x_anchor[w, j] - unwrapped[w, j])
        else:
            r = displacement(qi, qj, c_a[w, j], c_b[w, j], t_a[w, j]) - x_anchor[w, j]
        e, de, dde = passive_scalar(r, v_anchor[w, j], armature[w, k], damping[w, k], h)
        gi = vec12()
        gj = vec12()
        if derivs != 0 and rev:
            gi, gj = theta_grad(qi, qj, n_a[w, j], b_a[w, j], n_b[w, j], b_b[w, j], c, s)
        elif derivs != 0:
            gi, gj = displacement_grad(qi, qj, c_a[w, j], c_b[w, j], t_a[w, j])
        return e, de, dde, gi, gj

    @wp.kernel(module="unique")
    def passive(
        q: wp.array2d(dtype=vec12), joint: wp.array(dtype=wp.int32), joint_kind: wp.array(dtype=wp.int32),
        body_a: wp.array(dtype=wp.int32), body_b: wp.array(dtype=wp.int32), dof: wp.array(dtype=wp.int32),
        c_a: wp.array2d(dtype=vec3), c_b: wp.array2d(dtype=vec3), t_a: wp.array2d(dtype=vec3),
        n_a: wp.array2d(dtype=vec3), b_a: wp.array2d(dtype=vec3), n_b: wp.array2d(dtype=vec3), b_b: wp.array2d(dtype=vec3),
        c_prev: wp.array2d(dtype=dtype), s_prev: wp.array2d(dtype=dtype),
        armature: wp.array2d(dtype=dtype), damping: wp.array2d(dtype=dtype), unwrapped: wp.array2d(dtype=dtype),
        x_anchor: wp.array2d(dtype=dtype), v_anchor: wp.array2d(dtype=dtype), velocity: wp.array2d(dtype=dtype),
        h_step: wp.array(dtype=dtype), physical: int, active: wp.array(dtype=wp.int32), derivs: int, col: int,
        E: wp.array2d(dtype=dtype), g: wp.array2d(dtype=dtype), H: wp.array3d(dtype=dtype),
    ):  # fmt: skip
        """Passive term k of world w inside ĥ²; ``physical``: the armature's kinetic energy ½aẋ² [J]
        at the state's rate ẋ (``col`` the report's kinetic column)."""
        w, k = wp.tid()
        if active[w] == 0:
            return
        j = joint[k]
        if physical != 0:
            v = velocity[w, j]
            add_energy(E, w, col, half * armature[w, k] * v * v)
            return
        bi = body_a[j]
        bj = body_b[j]
        e, de, dde, gi, gj = passive_parts(q[w, bi], q[w, bj], w, k, joint, joint_kind, c_a, c_b, t_a, n_a, b_a, n_b,
                                           b_b, c_prev, s_prev, armature, damping, unwrapped, x_anchor, v_anchor,
                                           h_step[w], derivs)  # fmt: skip
        add_energy(E, w, col, e)
        if derivs != 0:
            hii, hij, hjj = outer_blocks(gi, gj, dde, derivs)
            scatter_pair(g, H, w, dof[bi], dof[bj], de * gi, de * gj, hii, hij, hjj)

    return SimpleNamespace(kernel=passive, parts=passive_parts, scalar=passive_scalar)


def terms(model, physical=False):
    """The potential's column; the report adds the armature's energy to "kinetic" (no column)."""
    return (NAME,) if model.num_passive and not physical else ()


def launch(model, state, ctx, q, E, g, H, active, derivs, cols, physical=False):
    m = model
    col = cols["kinetic"] if physical else cols[NAME]
    wp.launch(kernel(m.dtype).kernel, dim=(m.num_worlds, m.num_passive),
              inputs=[q, m.passive_joint, m.joint_kind, m.body_a, m.body_b, m.dof, m.c_a, m.c_b, m.t_a, m.n_a, m.b_a,
                      m.n_b, m.b_b, state.c_prev, state.s_prev, m.passive_armature, m.passive_damping, state.unwrapped,
                      state.x_anchor, state.v_anchor, state.coord_vel, ctx.h_step, int(physical), active, derivs, col,
                      E, g, H], device=m.device)  # fmt: skip


# one passive term a joint (Model: one per joint with Joint.has_passive): always folded
SLOTS = {"prismatic": 1, "revolute": 1}


@functools.lru_cache(maxsize=None)
def fold(dtype, Terms):
    """The passive term folded into its joint's term (protocol.Constitution.fold), inside ĥ²."""
    passive_scalar = kernel(dtype).scalar

    @wp.func
    def prismatic(t: Terms, w: int, j: int, a: int, x: dtype, e: dtype, de: dtype, dde: dtype):
        """Joint term a's passive term, if it has one, at the displacement x."""
        k = t.fold_passive_prismatic[a]
        if k >= 0:
            ep, d1, d2 = passive_scalar(x - t.x_anchor[w, j], t.v_anchor[w, j], t.pas_arm[w, k], t.pas_damp[w, k],
                                        t.h_step[w])  # fmt: skip
            e += ep
            de += d1
            dde += d2
        return e, de, dde

    @wp.func
    def revolute(t: Terms, w: int, j: int, a: int, x: dtype, hw: dtype, e: dtype, de: dtype, dde: dtype):
        """Angle term a's passive term, if it has one, at the angle increment x = δ."""
        k = t.fold_passive_revolute[a]
        if k >= 0:
            ep, d1, d2 = passive_scalar(x - (t.x_anchor[w, j] - t.unwrapped[w, j]), t.v_anchor[w, j],
                                        t.pas_arm[w, k], t.pas_damp[w, k], hw)  # fmt: skip
            e += ep
            de += d1
            dde += d2
        return e, de, dde

    return SimpleNamespace(prismatic=prismatic, revolute=revolute)


CONSTITUTION = Constitution(NAME, UID, COORDINATE, passive_np, terms, launch, work=10.0,
                            instances=lambda model: [int(j) for j in model.passive_joint.numpy()[: model.num_passive]],
                            slots=SLOTS, fold=fold)  # fmt: skip
