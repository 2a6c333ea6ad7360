"""The fused step's terms for a model's scene: which joints, limits and drives it evaluates, and
which limits and drives ride on their joint's own term (a prismatic joint's limit and drive on its
displacement, a revolute joint's limit and drives on its angle).  Read by the execution plan (the
number of terms sets the default lane groups) and by the solver (the kernel's flags and arrays).
"""
from __future__ import annotations

import numpy as np

from .scene import FIXED, PRISMATIC, REVOLUTE


def fused_flags(model, jt: dict | None = None):
    """What fused_kernel is built with for ``model``'s scene: (its positional has_* flags: revolute,
    fixed and prismatic joints, revolute and prismatic limits left with terms of their own, drives
    with terms of their own; the keyword flags pri_limits, pri_drives, rev_angles), from
    ``joint_terms`` (``jt``, computed when not given)."""
    jt = joint_terms(model) if jt is None else jt
    fuse_lim, fuse_drv = bool((jt["pri_lim"] >= 0).any()), bool((jt["pri_drv"] >= 0).any())
    angles = len(jt["ang_joint"]) > 0
    m = model
    has = (m.joint_count[REVOLUTE] > 0, m.joint_count[FIXED] > 0, m.joint_count[PRISMATIC] > 0,
           len(m.limit_joints[REVOLUTE]) > 0 and not angles, len(m.limit_joints[PRISMATIC]) > 0 and not fuse_lim,
           len(jt["rest"]) > 0)  # fmt: skip
    return has, dict(pri_limits=fuse_lim, pri_drives=fuse_drv, rev_angles=angles)


def joint_terms(model) -> dict:
    """How the fused step groups the limits and drives with their joints.  ``pri_lim``, ``pri_drv``:
    for each prismatic joint (Model.joint_ids order) its limit and the first drive on it, or −1
    (fused.prismatic_term; H100: 1.17x cart-poles at 1,024 worlds, results/fused_prismatic_h100.md);
    ``ang_joint``, ``ang_lim``, ``ang_drv`` (A, 2): the revolute joints with a limit or a drive, each
    with its limit (index of the revolute limits) and up to two drives, or −1 (fused.angle_term);
    ``rest``: the drives left for terms of their own, in order."""
    drive_joint = [int(j) for j in model.drive_joint.numpy()[: model.num_drives]]
    out = {}
    taken = set()
    pri = [int(j) for j in model.joint_ids[PRISMATIC].numpy()[: model.joint_count[PRISMATIC]]]
    at = {j: k for k, j in enumerate(pri)}
    out["pri_lim"] = np.full(len(pri), -1, np.int32)
    for kl, j in enumerate(model.limit_joints[PRISMATIC]):
        out["pri_lim"][at[int(j)]] = kl
    out["pri_drv"] = np.full(len(pri), -1, np.int32)
    for kd, j in enumerate(drive_joint):
        if j in at and out["pri_drv"][at[j]] < 0:
            out["pri_drv"][at[j]] = kd
            taken.add(kd)
    rev = set(int(j) for j in model.joint_ids[REVOLUTE].numpy()[: model.joint_count[REVOLUTE]])
    lims = {int(j): kl for kl, j in enumerate(model.limit_joints[REVOLUTE])}
    drives = {}
    for kd, j in enumerate(drive_joint):
        if j in rev and len(drives.setdefault(j, [])) < 2:
            drives[j].append(kd)
            taken.add(kd)
    joints = sorted(set(lims) | set(drives))
    out["ang_joint"] = np.array(joints, np.int32)
    out["ang_lim"] = np.array([lims.get(j, -1) for j in joints], np.int32)
    out["ang_drv"] = np.array([(drives.get(j, []) + [-1, -1])[:2] for j in joints], np.int32).reshape(-1, 2)
    out["rest"] = [kd for kd in range(model.num_drives) if kd not in taken]
    return out


def term_counts(model, jt: dict) -> dict:
    """The fused step's terms of each kind (lane_work's ``counts``), given joint_terms' grouping
    ``jt``: the limits and drives on a joint's own term are no terms of their own."""
    m, angles = model, len(jt["ang_joint"]) > 0
    return {"revolute": m.joint_count[REVOLUTE], "fixed": m.joint_count[FIXED], "prismatic": m.joint_count[PRISMATIC],
            "revolute_limit": len(m.limit_joints[REVOLUTE]) * (not angles),
            "prismatic_limit": len(m.limit_joints[PRISMATIC]) * (not bool((jt["pri_lim"] >= 0).any())),
            "drive": len(jt["rest"]), "angle": len(jt["ang_joint"])}  # fmt: skip
