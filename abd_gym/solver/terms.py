"""The fused step's terms for a model's scene, from the constitution registry: which constitutions
have fused terms of their own, and which coordinate terms (limits, drives) ride on their joint's
coordinate term instead (protocol.Constitution.slots).  Read by the execution plan (the number of
terms sets the default lane groups) and by the solver (the kernel's spec and arrays).

A joint kind's coordinate term: a prismatic joint's own term (fused.prismatic_term, every
prismatic joint); a revolute joint's angle term (fused.angle_term, a term beside its point-joint
term, for the revolute joints with a folded instance).
"""
from __future__ import annotations

import numpy as np

from ..constitutions import COORDINATE, JOINT, REGISTRY
from ..sim.scene import PRISMATIC, REVOLUTE

# the angle term's joint kind (a term of its own, "angle" in term_counts)
ANGLE = REVOLUTE


def joint_terms(model) -> dict:
    """How the fused step folds the coordinate terms into their joints' terms, each coordinate
    constitution in registry order, each instance in order onto its joint's next free slot:

    - ``joints``: {joint kind: joint ids of its coordinate terms} (prismatic: every prismatic
      joint in Model.joint_ids order, so that row k of a fold belongs to the prismatic joint's
      own term k, which assembles it in the same pass; revolute: the joints with a folded
      instance, ascending);
    - ``folds``: {(name, joint kind): int32 (joint terms,) for one slot, else (joint terms, slots),
      the instances folded on each, or −1};
    - ``rest``: {name: the instances left with terms of their own, in order}."""
    kind_of = {int(j): kind for kind in (REVOLUTE, PRISMATIC)
               for j in model.joint_ids[kind].numpy()[: model.joint_count[kind]]}  # fmt: skip
    taken, rest = {}, {}
    for c in (c for c in REGISTRY if c.kind == COORDINATE):
        rest[c.name] = []
        for k, j in enumerate(int(j) for j in c.instances(model)):
            on = taken.setdefault((c.name, kind_of.get(j)), {}).setdefault(j, [])
            if len(on) < c.slots.get(kind_of.get(j), 0):
                on.append(k)
            else:
                rest[c.name].append(k)
    pri = [int(j) for j in model.joint_ids[PRISMATIC].numpy()[: model.joint_count[PRISMATIC]]]
    ang = sorted({j for (_, kind), on in taken.items() if kind == ANGLE for j in on})
    joints = {PRISMATIC: pri, ANGLE: ang}
    folds = {}
    for c in (c for c in REGISTRY if c.kind == COORDINATE):
        for kind, slots in c.slots.items():
            on = taken.get((c.name, kind), {})
            a = np.array([(on.get(j, []) + [-1] * slots)[:slots] for j in joints[kind]], np.int32)
            folds[c.name, kind] = a.reshape(-1, slots)[:, 0] if slots == 1 else a.reshape(-1, slots)
    return {"joints": {kind: np.array(v, np.int32) for kind, v in joints.items()}, "folds": folds, "rest": rest}


def fused_flags(model, jt: dict | None = None):
    """What fused_kernel is built with for ``model``'s scene, from ``joint_terms`` (``jt``,
    computed when not given): (``own``: the names of the joint and coordinate constitutions with
    fused terms of their own, in registry order; ``folds``: the (name, joint kind) of the coordinate
    terms folded into a joint's term somewhere in the scene, in registry order)."""
    jt = joint_terms(model) if jt is None else jt
    counts = term_counts(model, jt)
    own = tuple(c.name for c in REGISTRY if c.kind in (JOINT, COORDINATE) and counts[c.name] > 0)
    folds = tuple(key for key, a in jt["folds"].items() if (a >= 0).any())
    return own, folds


def term_counts(model, jt: dict) -> dict:
    """The fused step's terms of each kind (lane_work's ``counts``), given joint_terms' grouping
    ``jt``: {constitution name: its terms of their own, "angle": the angle terms}; the limits and
    drives folded into a joint's term are no terms of their own."""
    out = {}
    for c in REGISTRY:
        if c.kind == JOINT:
            out[c.name] = model.joint_count[c.joint]
        elif c.kind == COORDINATE:
            out[c.name] = len(jt["rest"][c.name])
    out["angle"] = len(jt["joints"][ANGLE])
    return out
