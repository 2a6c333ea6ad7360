"""The structs a fused kernel reads: ``Terms``, everything the incremental potential reads besides
q (the model's constants, the joints' history, the controls), and ``Bracket``, what opening and
closing a world's step reads and writes besides them.  Made once per scalar type."""
import functools
from types import SimpleNamespace

import warp as wp

from ...constitutions import COORDINATE, REGISTRY
from ...core.warp_ops import ops

# the kinds of Terms.work's items (a lane group's joints, limits and drives)
WORK_REVOLUTE, WORK_FIXED, WORK_PRISMATIC, WORK_REVOLUTE_LIMIT, WORK_PRISMATIC_LIMIT, WORK_DRIVE = 1, 2, 3, 4, 5, 6
WORK_ANGLE = 7  # a revolute joint's folded limit and drives on its one angle (fused.angle_term)
# the kind of each term of its own (terms.term_counts' keys), the order of a lane group's share
WORK_KINDS = {"revolute_joint": WORK_REVOLUTE, "fixed_joint": WORK_FIXED, "prismatic_joint": WORK_PRISMATIC,
              "revolute_limit": WORK_REVOLUTE_LIMIT, "prismatic_limit": WORK_PRISMATIC_LIMIT, "drive": WORK_DRIVE,
              "angle": WORK_ANGLE}  # fmt: skip


def fold_fields() -> dict:
    """Terms' fields of the coordinate terms folded on joint terms, in registry order: for each
    coordinate constitution and joint kind it sits on, ``fold_<name>_<kind>`` (int32: joint term
    a's instances, or −1; (joint terms,) for one slot, else (joint terms, slots))."""
    return {c.fold_field(kind): wp.array(dtype=wp.int32) if slots == 1 else wp.array2d(dtype=wp.int32)
            for c in REGISTRY if c.kind == COORDINATE for kind, slots in c.slots.items()}  # fmt: skip


def _after(fields: dict, name: str, more: dict) -> dict:
    """``fields`` with ``more`` inserted after field ``name``."""
    out = {}
    for k, v in fields.items():
        out[k] = v
        if k == name:
            out.update(more)
    return out


@functools.lru_cache(maxsize=None)
def structs(dtype):
    """``Terms`` and ``Bracket`` for ``dtype``."""
    o = ops(dtype)
    vec3, vec12, mat33 = o.vec3, o.vec12, o.mat33

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
        h_joint: dtype  # the step whose joint stiffness K/ĥ² every step keeps (Solver.h_joint)
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
        drive_rest: wp.array(dtype=wp.int32)  # the drives with a term of their own
        ang_joint: wp.array(dtype=wp.int32)  # angle term a's revolute joint
        # (here: fold_fields, the coordinate terms folded on each joint term)
        drive_mode: wp.array(dtype=wp.int32)
        kp: wp.array2d(dtype=dtype)
        kd: wp.array2d(dtype=dtype)
        fmax: wp.array2d(dtype=dtype)
        control: wp.array2d(dtype=dtype)
        unwrapped: wp.array2d(dtype=dtype)
        x_anchor: wp.array2d(dtype=dtype)
        # the passive terms' parameters (W, terms) and predicted rate v̂ (W, joints) (constitutions.passive)
        pas_arm: wp.array2d(dtype=dtype)
        pas_damp: wp.array2d(dtype=dtype)
        v_anchor: wp.array2d(dtype=dtype)
        retried: wp.array(dtype=wp.int32)  # State.retried
        exact: wp.array(dtype=wp.int32)  # (W,) 1: the Hessian assembled now is exact (newton.iterate)
        clock: wp.array2d(dtype=wp.int64)  # (W, len(PHASES)) with phase_clock, else unused
        # lane groups: group c's joints, limits and drives, (kind WORK_*, index in its kind) for
        # it < work_n[c] (Solver.lane_work); unused with one group
        work_kind: wp.array2d(dtype=wp.int32)
        work_idx: wp.array2d(dtype=wp.int32)
        work_n: wp.array(dtype=wp.int32)

    Terms.__annotations__ = _after(Terms.__annotations__, "ang_joint", fold_fields())
    Terms = wp.struct(Terms)

    @wp.struct
    class Bracket:
        """What opening and closing a world's step reads and writes besides Terms (bracket=True)."""

        qd: wp.array2d(dtype=vec12)
        q_prev: wp.array2d(dtype=vec12)
        q_hist: wp.array2d(dtype=vec12)
        qd_hist: wp.array2d(dtype=vec12)
        qd_hist2: wp.array2d(dtype=vec12)
        order3: wp.array2d(dtype=wp.int32)
        control_prev: wp.array2d(dtype=dtype)
        calm: wp.array(dtype=wp.int32)
        fresh: wp.array(dtype=wp.int32)
        c_ref: wp.array2d(dtype=dtype)
        s_ref: wp.array2d(dtype=dtype)
        x_hist: wp.array2d(dtype=dtype)
        coord: wp.array2d(dtype=dtype)
        velocity: wp.array2d(dtype=dtype)
        velocity_hist: wp.array2d(dtype=dtype)  # the passive terms' ẋⁿ⁻¹ (State.coord_vel_hist)
        hold: wp.array(dtype=wp.int32)  # (W,): a world with hold[w] != 0 is not stepped (step_world)
        go: wp.array(dtype=wp.int32)  # (1,): 0 steps no world
        gravity: vec3
        h: dtype
        bdf2: int

    return SimpleNamespace(Terms=Terms, Bracket=Bracket)
