"""The Hessian's envelope: a chain factors only the band its joints couple, with the dense factor's
result; a closed loop widens the envelope to the bodies it closes on.  The chains here move in a
plane; they are solved with 12 unknowns a body (``_chain``), whose block band these tests check
(tests/test_planar.py: the planar form's envelope)."""
import numpy as np
import pytest

import abd_gym as ag
from abd_gym.sim import mechanisms


def _chain(n, **kw):
    """mechanisms.chain, solved with 12 unknowns a body (Scene.planar False)."""
    scene = mechanisms.chain(n, **kw)
    scene.planar = False
    return scene


def test_envelope_follows_the_joints():
    dense = ag.Simulator(mechanisms.double_pendulum(), num_worlds=1)
    assert not dense.model.envelope  # two coupled bodies: dense, the plain loops run
    chain = ag.Simulator(_chain(4), num_worlds=1, plan=ag.ExecutionPlan(scratch="global"))
    assert chain.model.envelope and chain.plan.envelope  # (a GPU's lane-split step keeps H packed whole)
    np.testing.assert_array_equal(chain.model.first_np[::12], [0, 0, 12, 24])
    assert (chain.model.first_np.reshape(4, 12) == chain.model.first_np[::12, None]).all()
    # closing the chain on its first link (body 1): the last link's rows start at link 0
    scene = _chain(4)
    scene.add_revolute_joint(1, 4, anchor=(0.0, 0.0, -1.0), axis=(0, 1, 0))
    loop = ag.Simulator(scene, num_worlds=1).model
    np.testing.assert_array_equal(loop.first_np[::12], [0, 0, 12, 0])


@pytest.mark.parametrize("fused,workers", [(True, 1), (True, 2), (False, 1)])
def test_envelope_factor_gives_the_dense_trajectory(fused, workers):
    """A 5-link chain (float64): 20 steps with the envelope factor match the dense factor to
    rounding (the back substitution runs in another order), staged, and fused where the step stores
    only the block band (Model.banded), in one launch and in two concurrent ones on the CPU (each
    with its own block of scratch columns)."""
    x0 = [[0.4, -0.3, 0.2, 0.5, -0.1], [1.0, 0.0, -0.5, 0.3, 0.2]] * 2
    runs = {}
    for envelope in (False, True):
        sim = ag.Simulator(_chain(5, length=0.2), num_worlds=4, dt=0.01, dtype="float64",
                           plan=ag.ExecutionPlan(envelope=envelope, fused=fused,
                                                 cpu_workers=workers if fused else None))  # fmt: skip
        assert sim.solver.band == (fused and envelope) and len(sim.solver.newton_launches) == (workers if fused else 1)
        sim.set_joint_state(x0)
        sim.step(20)
        assert sim.converged().all()
        runs[envelope] = sim.body_q()
    np.testing.assert_allclose(runs[True], runs[False], rtol=0, atol=1e-11)


def test_lane_split_band_gives_the_dense_trajectory():
    """The lane-split step in the block band (its factor and substitutions a column at a time
    within it, 8 lanes as cooperative CPU fibers): a 5-link chain's 10 steps equal the packed
    triangle's bit for bit (float64); by default only chains whose rows overflow a warp's registers
    keep the band in lanes (plan.lanes_band)."""
    import warp as wp

    from abd_gym.solver.plan import lanes_band

    assert not lanes_band(60, True) and lanes_band(108, True) and not lanes_band(108, False)
    before = wp.config.enable_cpu_blocks
    wp.config.enable_cpu_blocks = True
    try:
        runs = {}
        for band in (False, True):
            sim = ag.Simulator(_chain(5, length=0.2), num_worlds=2, dt=0.01, dtype="float64", device="cpu",
                               plan=ag.ExecutionPlan(scratch="lanes", block_dim=8, envelope=band))  # fmt: skip
            assert sim.solver.band == band
            sim.set_joint_state([[0.4, -0.3, 0.2, 0.5, -0.1], [1.0, 0.0, -0.5, 0.3, 0.2]])
            sim.step(10)
            assert sim.converged().all()
            runs[band] = sim.body_q()
        np.testing.assert_array_equal(runs[True], runs[False])
    finally:
        wp.config.enable_cpu_blocks = before


def _solve_kernel(dtype, envelope, packed=False):
    import warp as wp

    from abd_gym.solver import kernels as solver_kernels

    cholesky_solve = solver_kernels.kernels(dtype, envelope, packed)["cholesky_solve"]

    @wp.kernel(module="unique")
    def solve(H: wp.array(dtype=dtype), g: wp.array(dtype=dtype), dq: wp.array(dtype=dtype), n: int,
              first: wp.array(dtype=wp.int32), out: wp.array2d(dtype=dtype)):  # fmt: skip
        w = wp.tid()
        ok, gdq, dmax, g_abs = cholesky_solve(H, g, dq, w, n, out.shape[0], first)
        out[w, 0] = dtype(ok)
        out[w, 1] = gdq
        out[w, 2] = dmax
        out[w, 3] = g_abs

    return solve


def _stored(n, band):
    """(rows, cols) of the entries a scratch column stores, row by row: the lower triangle, or its
    block band (row i of body b ≥ 1 from column 12(b − 1))."""
    rows, cols = np.tril_indices(n)
    if band:
        keep = cols >= np.maximum(rows // 12 - 1, 0) * 12
        rows, cols = rows[keep], cols[keep]
    return rows, cols


@pytest.mark.parametrize("dtype,envelope,packed", [("float64", False, False), ("float32", False, False),
                                                   ("float64", True, False), ("float64", False, True),
                                                   ("float32", False, True), ("float64", True, True),
                                                   ("float32", True, True)])  # fmt: skip
def test_factor_and_solves_match_numpy(dtype, envelope, packed):
    """The per-world Cholesky solve (4 × 4 tiles when dense; flat world-minor scratch, entry (i, j)
    of world w at (i·n + j)·W + w, packed at (i(i+1)/2 + j)·W + w, or in the packed block band at
    (h_row_starts[i] + j)·W + w) against NumPy on random SPD systems of 12 to 60 unknowns (block
    tridiagonal by 12 × 12 blocks for the envelope and the band), with the factor left in H's lower
    triangle; a matrix that is not positive definite reports 0."""
    import warp as wp

    from abd_gym.solver.kernels import h_row_starts, h_words

    wdt = getattr(wp, dtype)
    rng = np.random.default_rng(3)
    band = envelope and packed
    for n in (12, 24, 36, 60):
        W = 5
        A = rng.normal(size=(W, n, n))
        H = A @ A.transpose(0, 2, 1) + n * np.eye(n)
        first = np.zeros(n, dtype=np.int32)
        if envelope:  # body b couples only to b − 1: block tridiagonal
            first = np.maximum(np.arange(n) // 12 - 1, 0).astype(np.int32) * 12
            H *= np.abs(np.arange(n)[:, None] // 12 - np.arange(n)[None, :] // 12) <= 1
        H[-1] = -np.eye(n)  # not positive definite
        g = rng.normal(size=(W, n))
        rows, cols = _stored(n, band)
        if packed:
            at = h_row_starts(n, packed, band)[rows] + cols
            np.testing.assert_array_equal(at, np.arange(h_words(n, packed, band)))  # row by row, no gaps
            Hd = wp.array(H[:, rows, cols].T.reshape(-1), dtype=wdt)
        else:
            Hd = wp.array(np.tril(H).transpose(1, 2, 0).reshape(-1), dtype=wdt)
        gd = wp.array(g.T.reshape(-1), dtype=wdt)
        dq = wp.zeros(n * W, dtype=wdt)
        out = wp.zeros((W, 4), dtype=wdt)
        wp.launch(_solve_kernel(wdt, envelope, packed), dim=W, inputs=[Hd, gd, dq, n, wp.array(first), out])
        out = out.numpy()
        x = dq.numpy().reshape(n, W).T
        if packed:
            L = np.zeros((W, n, n))
            L[:, rows, cols] = Hd.numpy().reshape(-1, W).T
        else:
            L = Hd.numpy().reshape(n, n, W).transpose(2, 0, 1)
        rtol = 1e-10 if dtype == "float64" else 2e-4
        for w in range(W - 1):
            ref = -np.linalg.solve(H[w], g[w])
            np.testing.assert_allclose(x[w], ref, rtol=rtol, atol=rtol * np.abs(ref).max())
            np.testing.assert_allclose(np.tril(L[w]), np.linalg.cholesky(H[w]), rtol=rtol, atol=rtol * 10)
            np.testing.assert_allclose(out[w], [1, g[w] @ ref, np.abs(ref).max(), np.abs(g[w]).sum()], rtol=rtol * 10)
        assert out[W - 1, 0] == 0
