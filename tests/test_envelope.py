"""The Hessian's envelope: a chain factors only the band its joints couple, with the dense factor's
result; a closed loop widens the envelope to the bodies it closes on."""
import numpy as np
import pytest

import abd_gym as ag
from abd_gym import mechanisms


def test_envelope_follows_the_joints():
    dense = ag.Simulator(mechanisms.double_pendulum(), num_worlds=1)
    assert not dense.model.envelope  # two coupled bodies: dense, the plain loops run
    chain = ag.Simulator(mechanisms.chain(4), num_worlds=1)
    assert chain.model.envelope and chain.solver.envelope
    np.testing.assert_array_equal(chain.model.first_np[::12], [0, 0, 12, 24])
    assert (chain.model.first_np.reshape(4, 12) == chain.model.first_np[::12, None]).all()
    # closing the chain on its first link (body 1): the last link's rows start at link 0
    scene = mechanisms.chain(4)
    scene.add_revolute_joint(1, 4, anchor=(0.0, 0.0, -1.0), axis=(0, 1, 0))
    loop = ag.Simulator(scene, num_worlds=1).model
    np.testing.assert_array_equal(loop.first_np[::12], [0, 0, 12, 0])


@pytest.mark.parametrize("fused", [True, False])
def test_envelope_factor_gives_the_dense_trajectory(fused):
    """A 5-link chain (float64): 20 steps with the envelope factor match the dense factor to
    rounding (the back substitution runs in another order), fused and staged."""
    x0 = [[0.4, -0.3, 0.2, 0.5, -0.1], [1.0, 0.0, -0.5, 0.3, 0.2]]
    runs = {}
    for envelope in (False, True):
        sim = ag.Simulator(mechanisms.chain(5, length=0.2), num_worlds=2, dt=0.01, dtype="float64",
                           envelope=envelope, fused=fused)  # fmt: skip
        sim.set_joint_state(x0)
        sim.step(20)
        assert sim.converged().all()
        runs[envelope] = sim.body_q()
    np.testing.assert_allclose(runs[True], runs[False], rtol=0, atol=1e-11)
