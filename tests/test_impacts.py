"""BDF2 at stiff limits: a conservative scene gains no energy when a limit engages or releases,
and a body that has left a limit moves on at a constant velocity (no force acts on it)."""
import numpy as np
import pytest

import abd_gym as ag
from abd_gym.sim import mechanisms

W = 32


def _slider(strength):
    """A 1 kg block on a horizontal prismatic joint limited to ±0.5 m (gravity across the axis)."""
    scene = ag.Scene(gravity=(0.0, 0.0, -9.81))
    base = scene.add_body(ag.Box(half_extents=(0.05, 0.05, 0.05)), fixed=True)
    block = scene.add_body(ag.Box(half_extents=(0.05, 0.05, 0.05)), mass=1.0)
    joint = scene.add_prismatic_joint(base, block, anchor=(0, 0, 0), axis=(1, 0, 0))
    scene.add_prismatic_limit(joint, -0.5, 0.5, strength)
    return scene, 0.5


def _spinner(strength):
    """A link on a hinge limited to ±1 rad, without gravity."""
    return mechanisms.chain(1, gravity=(0.0, 0.0, 0.0), limit=(-1.0, 1.0, strength)), 1.0


def _slam(scene, bound, dtype, speeds, dt=0.01, steps=50):
    """Each world starts at x = 0 with its speed (random sign); per step: total energy, coordinate,
    coordinate rate."""
    sim = ag.Simulator(scene, num_worlds=W, dt=dt, dtype=dtype, integrator="bdf2")
    rng = np.random.default_rng(3)
    v0 = rng.uniform(*speeds, W) * rng.choice([-1.0, 1.0], W)
    sim.set_joint_state(np.zeros((W, 1)), v0[:, None])
    kinetic0 = sim.energies()["kinetic"]
    energy, x, v = [sum(sim.energies().values())], [], []
    for _ in range(steps):
        sim.step()
        energy.append(sum(sim.energies().values()))
        x.append(sim.joint_coordinates()[:, 0].copy())
        v.append(sim.joint_velocities()[:, 0].copy())
    assert sim.converged().all() and len(sim.failed_worlds()) == 0
    return np.array(energy), kinetic0, np.array(x), np.array(v)


@pytest.mark.parametrize("dtype", ["float32", "float64"])
@pytest.mark.parametrize("case, speeds, strengths", [
    (_slider, (10.0, 30.0), (10.0, 1e3, 1e5)),  # m/s
    (_spinner, (5.0, 20.0), (10.0, 1e3, 1e5)),  # rad/s
])  # fmt: skip
def test_no_world_leaves_a_limit_with_more_energy(case, speeds, strengths, dtype):
    """Slams into stiff limits, with rebounds off both bounds: no world's total energy ever exceeds
    its start by more than 5% of its kinetic energy (a penalty limit absorbs part of it)."""
    for strength in strengths:
        scene, bound = case(strength)
        energy, kinetic0, x, _ = _slam(scene, bound, dtype, speeds)
        assert (np.abs(x) > bound).any(axis=0).all()  # every world hits a limit
        gain = (energy.max(axis=0) - energy[0]) / kinetic0
        assert gain.max() <= 0.05, (strength, gain.max())


@pytest.mark.parametrize("dtype", ["float32", "float64"])
@pytest.mark.parametrize("case, speeds", [(_slider, (10.0, 30.0)), (_spinner, (5.0, 20.0))])
def test_velocity_is_constant_once_off_the_limit(case, speeds, dtype):
    """A soft limit (strength 10) that the body leaves again: over a step whose start and the ends
    of the steps before and after it lie inside the bounds, no force acts, so the rate stays that of
    the step before, to 1e-3 of the start speed (the hinge's penalty settling after the impulse moves
    the rate by up to 2.3e-4 of it; BDF2 with a history spanning the impulse carries half of the
    impulse's last change of velocity on: 0.1 of it)."""
    scene, bound = case(10.0)
    _, _, x, v = _slam(scene, bound, dtype, speeds)
    inside = np.abs(x) < bound
    free = inside[2:] & inside[1:-1] & inside[:-2]  # x at the ends of steps n − 1, n and n + 1
    rebounded = np.cumsum(~inside, axis=0)[2:] > 0  # a limit was engaged before
    moving_free = free & rebounded
    assert moving_free.sum(axis=0).min() >= 5  # every world moves freely after its rebound
    change = np.abs(v[2:] - v[1:-1]) / np.abs(v[0])
    assert change[moving_free].max() <= 1e-3, change[moving_free].max()
