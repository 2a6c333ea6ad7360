"""State: the per-step arrays of every world.

``q``/``qd``/``q_prev`` (W, bodies) vec12; per joint (W, joints): the seed's ``θ0`` and
cos/sin θ of ``q^{t−1}``, the coordinate x, its rate, and the multi-turn angle (displacement
for sliders), with their BDF2 histories and the step's anchors; per drive (W, drives) the control; per world a status (status.WorldStatus), Newton
iterations and Cholesky factorisations used in the last step, and whether it converged.
"""
from __future__ import annotations

import numpy as np
import warp as wp


class State:
    def __init__(self, model):
        W, dev, scalar = model.num_worlds, model.device, model.dtype
        nb, nj, nd = model.num_bodies, max(model.num_joints, 1), max(model.num_drives, 1)
        self.q = wp.zeros((W, nb), dtype=model.vec12, device=dev)
        self.qd = wp.zeros_like(self.q)
        self.q_prev = wp.zeros_like(self.q)
        # BDF2 history: qⁿ⁻¹, q̇ⁿ⁻¹ and the multi-turn coordinate xⁿ⁻¹; x_anchor is the drives' x̂
        self.q_hist = wp.zeros_like(self.q)
        self.qd_hist = wp.zeros_like(self.q)
        self.theta0, self.c_prev, self.s_prev, self.coord, self.coord_vel, self.unwrapped, self.x_hist, self.x_anchor = (
            wp.zeros((W, nj), dtype=scalar, device=dev) for _ in range(8)
        )
        # the passive terms' rate history ẋⁿ⁻¹ and predicted rate v̂ (constitutions.passive; kept
        # where the scene has passive terms)
        self.coord_vel_hist, self.v_anchor = (wp.zeros((W, nj), dtype=scalar, device=dev) for _ in range(2))
        self.control = wp.zeros((W, nd), dtype=scalar, device=dev)
        # q̇ⁿ⁻², whether its third-order extrapolation guesses a body's next step, the last step's
        # controls and the steps in a row with the same (solver.kernels.predict_body, open_body)
        self.qd_hist2 = wp.zeros_like(self.q)
        self.order3 = wp.zeros((W, nb), dtype=wp.int32, device=dev)
        self.control_prev = wp.zeros_like(self.control)
        self.calm = wp.zeros(W, dtype=wp.int32, device=dev)
        self.status = wp.zeros(W, dtype=wp.int32, device=dev)
        # nonzero: the world's next step is an implicit Euler step even under BDF2 (solver.kernels.
        # open_body): RESET (1), it has no past step (new, or its state was just set) or a limit
        # released one step ago; RESTART (2), a limit was engaged at the end of its last step
        self.fresh = wp.ones(W, dtype=wp.int32, device=dev)
        self.iterations = wp.zeros(W, dtype=wp.int32, device=dev)
        self.factorizations = wp.zeros(W, dtype=wp.int32, device=dev)
        self.converged = wp.ones(W, dtype=wp.int32, device=dev)
        # 1: the last step's solve was started again from a fresh factor (Solver: a retry)
        self.retried = wp.zeros(W, dtype=wp.int32, device=dev)
        # the substeps the last step took: 1, or 2 or 4 where it failed and was retried (solver.retry)
        self.substeps = wp.ones(W, dtype=wp.int32, device=dev)
        # the energy test (solver.energy_gain), per world as of after its last step: the total
        # energy (NaN: not known, computed before the next step), the lowest gravity potential and
        # the largest swing energy since the state was set, and the step's allowance; and 1 where
        # the last step gained more than the test allows at 4 substeps too (kept, reported)
        self.energy = wp.full((W, 4), np.nan, dtype=scalar, device=dev)
        self.gained = wp.zeros(W, dtype=wp.int32, device=dev)
        self.time = np.zeros(W)  # seconds since the world's last reset (host bookkeeping)

    def snapshot(self) -> dict:
        """Host copies of every per-world array and of the clock ``time``, by name."""
        snap = {name: a.numpy().copy() for name, a in vars(self).items() if isinstance(a, wp.array)}
        snap["time"] = self.time.copy()
        return snap

    def restore(self, snap: dict):
        """``snapshot``'s values written back into this state's arrays (same shapes and dtypes)."""
        for name, values in snap.items():
            if name == "time":
                self.time[...] = values
            else:
                getattr(self, name).assign(values)
