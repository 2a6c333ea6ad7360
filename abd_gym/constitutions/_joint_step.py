"""A joint's K in a step whose length differs from the simulator's own (docs/design.md §2).

A joint's penalty K/2 Σ‖C‖² sits outside ĥ² in the incremental potential, so its physical
stiffness is K/ĥ²: it depends on the step.  A simulator's steps are not all of one length: under
BDF2 (ĥ₀ = 2h/3) a world whose state was set, whose limit acts or whose step was retried takes an
implicit Euler step (ĥ = h), and a retried step is taken as substeps (ĥ = h/2, h/4, or 2/3 of
those under BDF2).  With K as it is, such a step's joints are (ĥ₀/ĥ)² as stiff as the others',
so under a load F they stretch by Fĥ²/K instead of Fĥ₀²/K, and the next step of length ĥ₀ moves
that difference of stretch back against the load: gravity's work F²|ĥ² − ĥ₀²|/K comes out of or
into the total energy with nothing acting, a large share of the swing energy of a world near rest
(docs/design.md §2).  A step of length ĥ therefore takes K·(ĥ/ĥ₀)², the stiffness K/ĥ₀² of
every other step.  ĥ₀ is the simulator's effective step
(``Solver.h_joint``: its own ĥ, its parent's for a retry's substep solver); a step within 0.1%
of it (rounding of 2h/3) takes K itself, so the simulator's ordinary steps are untouched.
"""
import functools

import warp as wp


@functools.lru_cache(maxsize=None)
def funcs(dtype):
    """``joint_k(K, h_step, h_joint, w, j)``: joint j's K in world w's step (module docstring);
    h_joint 0: K itself (an energy reported outside a step)."""

    @wp.func
    def joint_k(K: wp.array2d(dtype=dtype), h_step: wp.array(dtype=dtype), h_joint: dtype, w: int, j: int):
        kk = K[w, j]
        hs = h_step[w]
        if h_joint > dtype(0.0) and wp.abs(hs - h_joint) > dtype(1.0e-3) * h_joint:
            r = hs / h_joint
            kk = kk * r * r
        return kk

    return joint_k
