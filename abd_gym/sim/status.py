"""What a world's last step did, per world (``Simulator.world_status``, the vector envs'
``info["sim_status"]``).

A world whose status is not ``OK`` kept the state it had before that step and is not stepped
again until ``reset``, ``set_joint_state`` or ``set_body_states`` writes its rows; the other
worlds of the batch are untouched.  docs/design.md §4.1 gives the rules.
"""
from enum import IntEnum


class WorldStatus(IntEnum):
    """A world's status code (int32 on the device)."""

    # the step was taken: Newton met its stop test
    OK = 0
    # q or q̇ was NaN or infinite at the start of a step
    NONFINITE = 1
    # the Cholesky factorisation or the solve broke down (a non-positive pivot, a non-finite step)
    BREAKDOWN = 2
    # Newton did not converge within its budget (max_iterations, and as many again from a fresh
    # factor at every iteration where the factor was reused), or its line search ran out away from
    # convergence: the step was rejected
    UNCONVERGED = 3


# the codes as plain ints, as Warp kernels read them
OK, NONFINITE, BREAKDOWN, UNCONVERGED = (int(s) for s in WorldStatus)
