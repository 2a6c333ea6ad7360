"""Fixed joint (weld; our UID 25): revolute constraints plus no relative rotation.

Four points fixed in both bodies, ``anchor`` and ``anchor + L·e_k`` (k = x, y, z; L the
joint's ``half_length`` [m]), must coincide: ``E = K/2 Σ_p ‖x_i(P_p) − x_j(P_p)‖²`` [J·s²],
``K = strength_ratio·(m_i + m_j)``; linear constraints, exact PSD Hessian.
"""
from ._point_joint import launch_points, point_joint_np
from .protocol import JOINT, Constitution

UID = 25
NAME = "fixed_joint"
KIND = "fixed"
NUM_POINTS = 4


def terms(model, physical=False):
    return (NAME,) if model.joint_count[KIND] else ()


def launch(model, state, ctx, q, E, g, H, active, derivs, cols, physical=False):
    launch_points(model, ctx, KIND, NUM_POINTS, q, E, g, H, active, derivs, cols[NAME], physical)


CONSTITUTION = Constitution(NAME, UID, JOINT, point_joint_np, terms, launch, work=13.0, joint=KIND)
