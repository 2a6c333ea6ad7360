"""set_joint_state's forward kinematics (kinematics.py, a Warp kernel) against a float64 NumPy
reference, on scenes with revolute, prismatic and fixed joints, a joint listed child-first (its
coordinate's sign flips), a free root body, and a closed loop; rates included."""
import numpy as np
import pytest

import abd_gym as ag
from abd_gym.sim import mechanisms
from abd_gym.sim.loops import tree_order
from abd_gym.sim.scene import PRISMATIC, REVOLUTE


def _rot(t, x):
    K = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return np.eye(3) + np.sin(x) * K + (1 - np.cos(x)) * K @ K


def reference(scene, x, xd):
    """Body states (bodies, 12) and rates of one world, placing each body from its parent."""
    bodies = scene.bodies
    R = [b.rotation.copy() for b in bodies]
    p = [b.position.copy() for b in bodies]
    v = [np.zeros(3) for _ in bodies]
    w = [np.zeros(3) for _ in bodies]
    for k, par, ch, sign in tree_order(scene)[0]:  # the placement order; the placing below is the reference's own
        j = scene.joints[k]
        Bp, Bc = bodies[par], bodies[ch]
        R_rel, p_rel = Bp.rotation.T @ Bc.rotation, Bp.rotation.T @ (Bc.position - Bp.position)
        t, c = Bp.to_local_dir(j.frame[0]), Bp.to_local_point(j.anchor)
        xs, vs = sign * x[k], sign * xd[k]
        if j.kind == REVOLUTE:
            G = _rot(t, xs)
            R_rel, p_rel = G @ R_rel, c + G @ (p_rel - c)
        elif j.kind == PRISMATIC:
            p_rel = p_rel + xs * t
        R[ch], p[ch] = R[par] @ R_rel, p[par] + R[par] @ p_rel
        t_world = R[par] @ t
        v[ch], w[ch] = v[par] + np.cross(w[par], p[ch] - p[par]), w[par].copy()
        if j.kind == REVOLUTE:
            w[ch] = w[ch] + vs * t_world
            v[ch] = v[ch] + np.cross(vs * t_world, p[ch] - (p[par] + R[par] @ c))
        elif j.kind == PRISMATIC:
            v[ch] = v[ch] + vs * t_world
    skew = [np.array([[0, -u[2], u[1]], [u[2], 0, -u[0]], [-u[1], u[0], 0]]) for u in w]
    q = np.array([np.concatenate([p[i], R[i].ravel()]) for i in range(len(bodies))])
    qd = np.array([np.concatenate([v[i], (skew[i] @ R[i]).ravel()]) for i in range(len(bodies))])
    return q, qd


def mixed_scene():
    """A fixed base, a slider listed child-first, a hinge on the slider, a welded tip, a free
    body with no joint, and a second hinge on the first's axis closing a loop."""
    sc = ag.Scene()
    base = sc.add_body(ag.Box((0.05, 0.05, 0.05)), fixed=True)
    cart = sc.add_body(ag.Box((0.2, 0.1, 0.05)), mass=1.0, position=(0.1, 0.0, 0.2))
    arm = sc.add_body(ag.Box((0.02, 0.02, 0.3)), mass=0.5, position=(0.1, 0.0, -0.1))
    tip = sc.add_body(ag.Sphere(0.05), mass=0.1, position=(0.1, 0.0, -0.4))
    sc.add_body(ag.Sphere(0.05), mass=0.2, position=(1.0, 1.0, 1.0))  # free, no joint
    sc.add_prismatic_joint(cart, base, anchor=(0.0, 0.0, 0.2), axis=(1.0, 0.0, 0.3))  # child first
    sc.add_revolute_joint(cart, arm, anchor=(0.1, 0.0, 0.2), axis=(0.0, 1.0, 0.2))
    sc.add_fixed_joint(arm, tip, anchor=(0.1, 0.0, -0.4))
    # closes a loop: a second hinge on the arm's axis, which every coordinate closes
    sc.add_revolute_joint(cart, arm, anchor=(0.1, 0.1, 0.22), axis=(0.0, 1.0, 0.2), half_length=0.05)
    return sc


@pytest.mark.parametrize("dtype, tol", [("float64", 1e-12), ("float32", 2e-6)])
@pytest.mark.parametrize("make", [mechanisms.cartpole, mechanisms.double_pendulum, mixed_scene])
def test_set_joint_state_matches_numpy_forward_kinematics(make, dtype, tol):
    scene = make()
    sim = ag.Simulator(scene, num_worlds=4, dtype=dtype)
    rng = np.random.default_rng(7)
    x = rng.uniform(-2.0, 2.0, (3, scene.num_joints))
    xd = rng.uniform(-3.0, 3.0, (3, scene.num_joints))
    sim.set_joint_state(x, xd, worlds=[0, 2, 3])
    q, qd = sim.state.q.numpy(), sim.state.qd.numpy()
    for i, w in enumerate([0, 2, 3]):
        q_ref, qd_ref = reference(scene, x[i], xd[i])
        np.testing.assert_allclose(q[w], q_ref, atol=tol)
        np.testing.assert_allclose(qd[w], qd_ref, atol=10 * tol)
    # the restart history: no past (q^{n-1} = q - dt q̇, q̇^{n-1} = q̇), world 1 untouched
    np.testing.assert_allclose(sim.state.q_hist.numpy()[2], q[2] - sim.dt * qd[2], atol=tol)
    np.testing.assert_array_equal(sim.state.qd_hist.numpy()[2], qd[2])
    np.testing.assert_allclose(q[1], sim.model.q0, atol=tol)
