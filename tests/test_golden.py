"""Stored trajectories: the physics and the tasks step bit for bit as when these were written.

Every registered task's vector env (N worlds, a fixed seed, a fixed action sequence) and two
mechanisms on the Simulator (a 5-link chain with limits, BDF2; a double pendulum in float64) are
stepped from a fixed start; their observations, rewards and body coordinates must equal the stored
ones exactly (on the CPU, where they were written: a GPU's float32 rounds otherwise).  A change that alters the arithmetic of a step fails here; regenerate only when that
change is meant (``python tests/test_golden.py --write KEY_PREFIX ...``, e.g. ``planar:``; no prefix
rewrites every key) and say so in its commit message.  "task:…" and the mechanisms are the
12-unknown step; "planar:…" each task's default form (a planar scene's 6 unknowns a body).
"""
import os
import sys

import gymnasium as gym
import numpy as np
import pytest

import abd_gym as ag
from abd_gym.sim import mechanisms, planar
from abd_gym.vector.registration import env_ids

PATH = os.path.join(os.path.dirname(__file__), "data", "golden.npz")
N, STEPS = 3, 30


def task_trajectory(env_id):
    env = gym.make_vec(env_id, num_envs=N, vectorization_mode="vector_entry_point", device="cpu")
    try:
        obs, _ = env.reset(seed=7)
        rng = np.random.default_rng(11)
        out = [obs.astype(np.float64)]
        for _ in range(STEPS):
            a = rng.uniform(env.single_action_space.low, env.single_action_space.high, (N,) + env.single_action_space.shape)
            obs, r, te, tr, _ = env.step(a.astype(env.single_action_space.dtype))
            out.append(np.concatenate([obs, r[:, None], te[:, None], tr[:, None]], axis=1).astype(np.float64))
        return np.stack(out[1:])
    finally:
        env.close()


def mechanism_trajectories():
    """The two Simulator scenes: 5-link chain with limits (BDF2, float32), double pendulum (float64)."""
    out = {}
    cases = {
        "chain5_bdf2": (mechanisms.chain(5, length=0.2, limit=(-1.0, 1.0, 1e3)), dict(integrator="bdf2")),
        "double_pendulum_f64": (mechanisms.double_pendulum(), dict(dtype="float64")),
    }
    for name, (scene, kw) in cases.items():
        sim = ag.Simulator(scene, num_worlds=N, dt=0.01, device="cpu", **kw)
        rng = np.random.default_rng(5)
        sim.set_joint_state(rng.uniform(-0.8, 0.8, (N, len(scene.joints))), rng.uniform(-2, 2, (N, len(scene.joints))))
        qs = []
        for _ in range(STEPS):
            sim.step()
            qs.append(sim.body_q())
        out[name] = np.stack(qs)
    return out


class twelve_unknowns:
    """Within it, every scene is solved with 12 unknowns a body (the planar reduction off: the
    trajectories "task:…" and the mechanisms' were stored with it)."""

    def __enter__(self):
        self.patch = pytest.MonkeyPatch()
        self.patch.setattr(planar, "plane_of", lambda scene: None)

    def __exit__(self, *exc):
        self.patch.undo()


def all_trajectories():
    with twelve_unknowns():
        out = {f"task:{i}": task_trajectory(i) for i in env_ids()}
        out.update(mechanism_trajectories())
    out.update({f"planar:{i}": task_trajectory(i) for i in env_ids()})
    return out


@pytest.fixture(scope="module")
def stored():
    with np.load(PATH) as f:
        return dict(f)


@pytest.mark.parametrize("env_id", env_ids())
def test_task_trajectory_is_the_stored_one(env_id, stored):
    """12 unknowns a body, and the form each task gets by default (a planar scene's 6)."""
    with twelve_unknowns():
        np.testing.assert_array_equal(task_trajectory(env_id), stored[f"task:{env_id}"])
    np.testing.assert_array_equal(task_trajectory(env_id), stored[f"planar:{env_id}"])


def test_mechanism_trajectories_are_the_stored_ones(stored):
    with twelve_unknowns():
        for name, q in mechanism_trajectories().items():
            np.testing.assert_array_equal(q, stored[name], err_msg=name)


if __name__ == "__main__" and "--write" in sys.argv:
    keys = sys.argv[sys.argv.index("--write") + 1:]  # the keys to rewrite (prefixes; none: all)
    old = dict(np.load(PATH)) if os.path.exists(PATH) else {}
    new = all_trajectories()
    kept = {k: v for k, v in old.items() if keys and not any(k.startswith(p) for p in keys)}
    np.savez_compressed(PATH, **{**new, **kept})
    print("wrote", PATH, "rewriting", sorted(set(new) - set(kept)))
