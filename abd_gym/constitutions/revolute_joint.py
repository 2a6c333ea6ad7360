"""Revolute joint (libuipc UID 18).

Two points on the hinge axis, ``P± = anchor ± L·t̂`` (L = the joint's ``half_length`` [m]), are
fixed in both bodies at scene creation and must coincide:
``E = K/2 Σ_± ‖x_i(P±) − x_j(P±)‖²`` [J·s²], ``K = strength_ratio·(m_i + m_j)`` [kg].
A penalty added to the incremental potential as it is (not inside h²), so its physical
stiffness is K/h² and the joint stays equally tight at any step size.
"""
from ._point_joint import launch_points, point_joint_np
from .protocol import JOINT, Constitution

UID = 18
NAME = "revolute_joint"
KIND = "revolute"
NUM_POINTS = 2


def terms(model, physical=False):
    return (NAME,) if model.joint_count[KIND] else ()


def launch(model, state, ctx, q, E, g, H, active, derivs, cols, physical=False):
    launch_points(model, ctx, KIND, NUM_POINTS, q, E, g, H, active, derivs, cols[NAME], physical)


CONSTITUTION = Constitution(NAME, UID, JOINT, point_joint_np, terms, launch, work=9.0, joint=KIND)
