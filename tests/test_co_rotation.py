"""The co-rotated frames of scripts/constant_factor_study.py (docs/design.md, "A constant factor"):
in each body's frame dA = R dF, dp = R dp′ the mass matrix and the orthogonality Hessian at a
rotation are constant, a point joint's diagonal blocks too, and its coupling block holds the two
bodies' relative rotation; the study's flop count of the envelope factor."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from abd_gym.constitutions import affine_body
from abd_gym.constitutions._point_joint import point_joint_np
from abd_gym.core import affine


@pytest.fixture
def study(script):
    return script("constant_factor_study")


def _rotations(n, seed=0):
    return Rotation.random(n, random_state=seed).as_matrix()


def _body(R, p=(0.3, -0.2, 0.5)):
    return np.concatenate([p, R.ravel()])


def test_polar_rotation(study):
    rng = np.random.default_rng(1)
    R = _rotations(1)[0]
    S = np.eye(3) + 1e-3 * (lambda X: X + X.T)(rng.standard_normal((3, 3)))
    Rp = study.polar_rotation(R @ S)
    np.testing.assert_allclose(Rp @ Rp.T, np.eye(3), atol=1e-14)
    np.testing.assert_allclose(Rp, R, atol=1e-12)
    assert np.linalg.det(Rp) > 0


def test_mass_and_orthogonality_constant_in_the_body_frame(study):
    kv = 3.7e4
    M = affine.mass_matrix(2.0, np.array([0.01, -0.02, 0.05]), np.diag([2e-3, 5e-4, 1e-5]) + 1e-5)
    H_rest = affine_body.orthogonality_np(_body(np.eye(3)), kv)[2]
    for R in _rotations(4):
        T = study.body_frame(R)
        np.testing.assert_allclose(T.T @ T, np.eye(12), atol=1e-14)
        np.testing.assert_allclose(T.T @ M @ T, M, atol=1e-14 * np.abs(M).max())
        _, _, H, Hp = affine_body.orthogonality_np(_body(R), kv)
        np.testing.assert_allclose(T.T @ H @ T, H_rest, atol=1e-12 * np.abs(H_rest).max())
        np.testing.assert_allclose(T.T @ Hp @ T, H_rest, atol=1e-12 * np.abs(H_rest).max())


def test_co_rotated_hessian_by_finite_differences(study):
    """The Hessian of V(R·F) in F's coordinates at F = I, by central differences of the library's
    gradient carried into the body frame, is the constant one."""
    kv, eps = 1.0, 1e-6
    R = _rotations(1, seed=3)[0]
    T = study.body_frame(R)
    q = _body(R)
    H_rest = affine_body.orthogonality_np(_body(np.eye(3)), kv)[2]
    fd = np.zeros((12, 12))
    for k in range(12):
        e = T[:, k] * eps
        fd[:, k] = T.T @ (affine_body.orthogonality_np(q + e, kv)[1] - affine_body.orthogonality_np(q - e, kv)[1])
    np.testing.assert_allclose(fd / (2 * eps), H_rest, atol=1e-7)


def test_joint_coupling_holds_the_relative_rotation(study):
    """A point joint: its diagonal blocks are constant in the body frames and its coupling block
    is −K J(x̄ᵢ)ᵀ RᵢᵀRⱼ J(x̄ⱼ): no constant factor holds it once the joint turns."""
    K, xi, xj = 50.0, [np.array([0.1, 0.0, 0.02])], [np.array([-0.05, 0.01, 0.0])]
    Ri, Rj = _rotations(2, seed=5)
    H = point_joint_np(np.concatenate([_body(Ri), _body(Rj)]), xi, xj, K)[2]
    Ti, Tj = study.body_frame(Ri), study.body_frame(Rj)
    H0 = point_joint_np(np.zeros(24), xi, xj, K)[2]  # (the Hessian is q's constant)
    np.testing.assert_allclose(Ti.T @ H[:12, :12] @ Ti, H0[:12, :12], atol=1e-12 * K)
    np.testing.assert_allclose(Tj.T @ H[12:, 12:] @ Tj, H0[12:, 12:], atol=1e-12 * K)
    coupling = Ti.T @ H[:12, 12:] @ Tj
    expected = -K * affine.J(xi[0]).T @ Ri.T @ Rj @ affine.J(xj[0])
    np.testing.assert_allclose(coupling, expected, atol=1e-12 * K)
    assert np.abs(coupling - H0[:12, 12:]).max() > 0.1 * K


@pytest.mark.parametrize("n", [1, 5, 12])
def test_envelope_flops_of_a_dense_matrix(study, n):
    """A dense n × n factor: Σᵢ (i+1)² = n(n+1)(2n+1)/6 flops, and 2n(n+1) for the two solves."""
    first = study.envelope(np.ones((n, n)))
    assert list(first) == [0] * n
    assert study.factor_flops(first) == n * (n + 1) * (2 * n + 1) // 6
    assert study.solve_flops(first) == 2 * n * (n + 1)


def test_envelope_of_a_band(study):
    H = np.eye(6) + np.diag(np.ones(5), 1) + np.diag(np.ones(5), -1)
    first = study.envelope(H)
    assert list(first) == [0, 0, 1, 2, 3, 4]
    assert study.factor_flops(first) == 1 + 5 * 4  # a row: one division, one 2-flop dot product and a root
