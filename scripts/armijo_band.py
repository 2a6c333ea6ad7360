#!/usr/bin/env python3
"""How often a Newton step that quadratic_stop could end is rejected by its Armijo test at α = 1:
hard cases traced through the staged solver (CPU by default).

    python scripts/armijo_band.py [--device cpu]

A fresh factor's step between 10× and quadratic_stop (100) × q's rounding floor is searched (its
energy assembled at the trial point); this counts those steps and the ones rejected at α = 1, the
case for keeping the test (results/quadratic_stop.md §6: 1 of 6,000+, at a track limit of
strength 1e6)."""
import argparse

import numpy as np

import abd_gym as ag
from abd_gym import mechanisms


def count(scene, W, dt, steps, x0, ctrl, device):
    sim = ag.Simulator(scene, num_worlds=W, dt=dt, fused=False, use_graph=False, device=device)
    s, rec = sim.solver, []
    inner = s._newton_iteration

    def iteration(state):
        chord = s.chord.numpy().copy()
        inner(state)
        q = state.q.numpy().reshape(W, -1)
        rounding = np.finfo(np.float32).eps * (1 + np.abs(q).max(1))
        rec.append((s.dq_max.numpy().copy(), s.alpha.numpy().copy(), chord, rounding, state.iterations.numpy().copy()))

    s._newton_iteration = iteration
    rng = np.random.default_rng(0)
    sim.set_joint_state(x0)
    band = rejected = 0
    for _ in range(steps):
        if ctrl:
            sim.set_controls(rng.uniform(-1, 1, (W, sim.model.num_drives)) * ctrl)
        rec.clear()
        sim.step()
        before = np.zeros(W, int)
        for dq, alpha, chord, rounding, its in rec:
            took = its > before
            before = its
            m = took & (chord <= 0) & (dq < 400 * rounding) & (dq >= 40 * rounding)
            band += int(m.sum())
            rejected += int((m & (alpha < 1)).sum())
    return band, rejected


def main():
    from abd_gym.envs.acrobot import build_acrobot_scene
    from abd_gym.envs.cartpole import build_cart_scene

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args()
    r = np.random.default_rng
    cases = [
        ("double pendulums, dt 0.05, up to 2.5 rad", mechanisms.double_pendulum(), 32, 0.05, 100, r(0).uniform(-2.5, 2.5, (32, 2)), 0),
        ("CartPole-v0 scene, random 10 N", build_cart_scene(), 32, 0.02, 100, np.c_[np.zeros(32), r(0).uniform(-0.2, 0.2, 32)], 10.0),
        ("mass ratio 1:1000", mechanisms.chain(2, masses=(0.01, 10.0)), 8, 0.01, 100, np.tile([[1.0, 0.5]], (8, 1)), 0),
        ("20-link chain", mechanisms.chain(20, length=0.1), 4, 0.01, 50, np.full((4, 20), 0.1), 0),
        ("cart-pole at its track limit, random 10 N", mechanisms.cartpole(), 32, 0.01, 200,
         np.c_[r(1).uniform(-2.3, 2.3, 32), r(2).uniform(-3, 3, 32)], 10.0),
        ("Acrobot elbow limit, torque 4", build_acrobot_scene(), 32, 0.02, 150, r(3).uniform(-2.4, 2.4, (32, 2)), 4.0),
        ("Acrobot limit strength 1e5, torque 20", build_acrobot_scene(limit_strength=1e5), 32, 0.02, 150,
         r(3).uniform(-2.4, 2.4, (32, 2)), 20.0),
        ("track limit strength 1e6 at 0.3 m, random 10 N", build_cart_scene(limit_strength=1e6, track=0.3), 32, 0.02, 150,
         np.c_[np.zeros(32), r(0).uniform(-0.2, 0.2, 32)], 10.0),
    ]  # fmt: skip
    for name, scene, W, dt, steps, x0, ctrl in cases:
        band, rejected = count(scene, W, dt, steps, x0, ctrl, args.device)
        print(f"{name}: searched steps in the band {band}, rejected at alpha 1: {rejected}", flush=True)


if __name__ == "__main__":
    main()
