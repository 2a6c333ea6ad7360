"""Joint coordinates in float64 NumPy (``abd_gym.core.angles``): the seed's atan2 revolute angle
(sign convention, principal branch plus one increment through ±π, derivatives) and the
prismatic displacement.  Frames come from ``scene.axis_frame`` (rows t̂, n̂, b̂ in world); with both
bodies created at identity rotation the local frames equal the world frames."""
import math

import numpy as np
import pytest

from abd_gym.core import angles
from abd_gym.sim.scene import axis_frame

AXES = [(0.0, 0.0, 1.0), (1.0, 2.0, 2.0), (-0.3, 0.9, -0.1)]


def rot(axis, angle):
    """Right-hand rotation about ``axis`` (Rodrigues), written independently of the package."""
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def pair(Ai, Aj, pi=(0.0, 0.0, 0.0), pj=(0.0, 0.0, 0.0)):
    return np.concatenate([pi, np.asarray(Ai).ravel(), pj, np.asarray(Aj).ravel()])


def frames_of(axis):
    """(n̂_i, b̂_i, n̂_j, b̂_j) local frames of two bodies created at identity rotation."""
    _, n, b = axis_frame(axis)
    return n, b, n, b


def fd_grad(f, q, h=1e-6):
    g = np.empty(q.size)
    for k in range(q.size):
        e = np.zeros(q.size)
        e[k] = h
        g[k] = (f(q + e) - f(q - e)) / (2 * h)
    return g


def fd_jac(f, q, h=1e-6):
    cols = []
    for k in range(q.size):
        e = np.zeros(q.size)
        e[k] = h
        cols.append((f(q + e) - f(q - e)) / (2 * h))
    return np.stack(cols, axis=1)


def rel_err(a, b):
    return np.linalg.norm(np.asarray(a) - np.asarray(b)) / np.linalg.norm(b)


def test_axis_frame_is_orthonormal_with_b_equal_n_cross_t():
    for axis in AXES:
        t, n, b = axis_frame(axis)
        np.testing.assert_allclose(np.stack([t, n, b]) @ np.stack([t, n, b]).T, np.eye(3), atol=1e-14)
        np.testing.assert_allclose(t, np.asarray(axis) / np.linalg.norm(axis), atol=1e-15)
        np.testing.assert_allclose(b, np.cross(n, t), atol=1e-15)


@pytest.mark.parametrize("axis", AXES)
@pytest.mark.parametrize("phi", [-3.1, -1.2, -0.2, 0.0, 0.4, 2.5, 3.1])
def test_revolute_angle_sign_convention(axis, phi):
    """A right-hand rotation of body j by φ about t̂ relative to body i reads +φ, whatever common
    rotation both bodies share; rotating body i instead reads −φ."""
    fr = frames_of(axis)
    q_ref = pair(np.eye(3), np.eye(3))
    G = rot((0.3, -1.0, 0.5), 0.9)  # a common rotation of both bodies changes nothing
    for q in (pair(np.eye(3), rot(axis, phi)), pair(G, G @ rot(axis, phi), (0.1, 0.2, 0.3), (-1.0, 0.5, 2.0))):
        # x = θ0 (q_prev = q, as after a set) and x = δ (q_prev = q_ref) both read +φ
        assert angles.revolute_angle_np(q, q, q_ref, fr)[0] == pytest.approx(phi, abs=1e-12)
        assert angles.revolute_angle_np(q, q_ref, q_ref, fr)[0] == pytest.approx(phi, abs=1e-12)
    q = pair(rot(axis, phi), np.eye(3))
    assert angles.revolute_angle_np(q, q, q_ref, fr)[0] == pytest.approx(-phi, abs=1e-12)


@pytest.mark.parametrize("axis", AXES)
def test_revolute_angle_rate_along_a_spin_is_one(axis):
    """∇x · dq/dφ = 1 for a spin of body j about t̂ (the gradient's sign and scale)."""
    fr = frames_of(axis)
    q_ref = pair(np.eye(3), np.eye(3))
    for phi in (-2.0, 0.3, 3.0):
        q = pair(np.eye(3), rot(axis, phi))
        dq = (pair(np.eye(3), rot(axis, phi + 1e-6)) - pair(np.eye(3), rot(axis, phi - 1e-6))) / 2e-6
        _, g, _ = angles.revolute_angle_np(q, q, q_ref, fr)
        assert g @ dq == pytest.approx(1.0, abs=1e-8)


@pytest.mark.parametrize("side", [+1, -1])
def test_revolute_angle_continues_past_pi_by_the_increment(side):
    """q_prev just inside +π (−π), q across the cut: x = θ0 + δ continues past ±π by the step's
    increment instead of jumping by 2π; the plain ΔΘ(q, q_ref) is on the other branch."""
    axis = (1.0, 2.0, 2.0)
    fr = frames_of(axis)
    q_ref = pair(np.eye(3), np.eye(3))
    prev_angle, angle = side * (math.pi - 0.01), side * (math.pi + 0.02)
    q_prev = pair(np.eye(3), rot(axis, prev_angle))
    q = pair(np.eye(3), rot(axis, angle))
    x, g, H = angles.revolute_angle_np(q, q_prev, q_ref, fr)
    assert x == pytest.approx(side * (math.pi + 0.02), abs=1e-12)
    cs = [tuple(v[0] for v in angles.cos_sin_np(s, *fr)) for s in (q, q_prev, q_ref)]
    assert angles.delta_theta_np(cs[0], cs[2]) == pytest.approx(-side * (math.pi - 0.02), abs=1e-12)
    assert angles.delta_theta_np(cs[1], cs[2]) == pytest.approx(prev_angle, abs=1e-12)  # θ0
    assert angles.delta_theta_np(cs[0], cs[1]) == pytest.approx(side * 0.03, abs=1e-12)  # δ
    # smooth through the cut: the derivatives are those of θ0 + δ(q)
    f = lambda z: angles.revolute_angle_np(z, q_prev, q_ref, fr)[0]  # noqa: E731
    assert rel_err(fd_grad(f, q), g) < 1e-6
    assert rel_err(fd_jac(lambda z: angles.revolute_angle_np(z, q_prev, q_ref, fr)[1], q), H) < 1e-5


def _random_affine_pair(rng, eps=1e-2):
    out = []
    for _ in range(2):
        M = rng.normal(size=(3, 3))
        Q, R = np.linalg.qr(M)
        Q = Q * np.sign(np.diag(R))
        if np.linalg.det(Q) < 0:
            Q[:, 0] *= -1
        out.append(np.concatenate([rng.normal(scale=0.5, size=3), (Q + eps * rng.normal(size=(3, 3))).ravel()]))
    return np.concatenate(out)


def _random_frames(rng):
    """Local frames (n̂_i, b̂_i, n̂_j, b̂_j) of one world frame seen from two bodies at random poses."""
    t, n, b = axis_frame(rng.normal(size=3))
    Ri, Rj = (np.linalg.qr(rng.normal(size=(3, 3)))[0] for _ in range(2))
    return Ri.T @ n, Ri.T @ b, Rj.T @ n, Rj.T @ b


def test_revolute_angle_derivatives_and_independence_of_q_prev():
    """Gradient and exact Hessian of x against central differences at random affine states; the
    gradient is the same whichever q_prev the increment starts from (it is ∇θ)."""
    rng = np.random.default_rng(0)
    for _ in range(5):
        fr = _random_frames(rng)
        q = _random_affine_pair(rng)
        q_ref = _random_affine_pair(rng)
        grads = []
        for q_prev in (q + 0.05 * rng.normal(size=24), q + 0.2 * rng.normal(size=24), q):
            x, g, H = angles.revolute_angle_np(q, q_prev, q_ref, fr)
            f = lambda z: angles.revolute_angle_np(z, q_prev, q_ref, fr)[0]  # noqa: E731
            assert rel_err(fd_grad(f, q), g) < 1e-6
            assert rel_err(fd_jac(lambda z: angles.revolute_angle_np(z, q_prev, q_ref, fr)[1], q), H) < 1e-5
            np.testing.assert_allclose(H, H.T, atol=1e-12 * np.abs(H).max())
            grads.append(fd_grad(f, q))
        for other in grads[1:]:
            assert rel_err(other, grads[0]) < 1e-6


def test_prismatic_displacement_sign_and_derivatives():
    rng = np.random.default_rng(1)
    axis = np.array([1.0, 2.0, 2.0]) / 3.0
    ci, cj = np.array([0.15, 0.0, 0.0]), np.array([-0.15, 0.0, 0.0])  # anchor (0.15, 0, 0); body j at x = 0.3
    for d in (-0.4, 0.0, 0.25):
        q = pair(np.eye(3), np.eye(3), (0, 0, 0), np.array([0.3, 0, 0]) + d * axis)
        assert angles.prismatic_displacement_np(q, ci, cj, axis)[0] == pytest.approx(d, abs=1e-14)
    for _ in range(5):
        q = _random_affine_pair(rng)
        ci, cj, ti = rng.normal(size=(3, 3))
        x, g, H = angles.prismatic_displacement_np(q, ci, cj, ti)
        assert rel_err(fd_grad(lambda z: angles.prismatic_displacement_np(z, ci, cj, ti)[0], q), g) < 1e-6
        assert rel_err(fd_jac(lambda z: angles.prismatic_displacement_np(z, ci, cj, ti)[1], q), H) < 1e-5
