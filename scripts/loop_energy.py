"""Where the four-bar's step gains come from: the loop's closure after ``set_joint_state`` and the
energy of each step that gains more than 5% of the swing energy.

For the robustness bench's ``fourbar`` case (FourBar-v0's linkage from its reset distribution, no
torque; ``python -m abd_gym.bench robustness``) and the tasks named by ``--tasks`` (their reset
draw at their own dt, zero controls: scripts/energy_gain_tasks.py), 64 worlds, 2 s, per dt,
integrator and dtype:

- after ``set_joint_state``: the largest gap of the loop's closing joints (the joints forward
  kinematics does not place: ``kinematics.tree_plan``), ``joint_violation(joints)`` [m], and the
  largest joint energy (``energies()``, the joint columns: K/2 Σ‖C‖²);
- each OK step whose total energy E (the sum of ``energies()``) rises by more than 5% of the
  world's swing energy S = E(0) − min_t V_g(t) (bench/robustness.py's ``step gain``): the step,
  its rise over S, the world's substeps in it and in the step before, its change of gravity
  potential, kinetic and joint energy, and ``rebound``: the rise of gravity potential that a
  joint stretch made by an implicit Euler step (stiffness K/h²) and released by a BDF2 step
  (K/ĥ², ĥ = 2h/3) gives under the same load F: the stretch falls from Fh²/K to Fĥ²/K, so gravity
  regains F²(h² − ĥ²)/K = (1 − 4/9)·2E_J/h², E_J the joints' K/2 Σ‖C‖² after the implicit
  Euler step (``energies()`` reports the physical K/(2ĥ₀²) Σ‖C‖², ĥ₀ the simulator's step).

    python scripts/loop_energy.py [--dts 0.1 0.2] [--tasks CartPoleSwingUp-v0 DoublePendulumCart-v0]
                                  [--out results/loop_energy_cpu.json]
"""
import argparse
import datetime
import json
import platform
import sys
import warnings

import numpy as np

from abd_gym.bench import robustness
from abd_gym.sim import kinematics
from abd_gym.sim.simulator import Simulator

sys.path.insert(0, __file__.rsplit("/", 1)[0])
import energy_gain_tasks  # noqa: E402  (the tasks' draws)

LIMIT = robustness.GAIN_LIMIT


def closing_joints(sim) -> list:
    """The joints forward kinematics leaves to the solver (they close a loop)."""
    placed = set(kinematics.tree_plan(sim.scene, sim.model).steps.numpy()[:, 0].tolist())
    return [j for j in range(len(sim.scene.joints)) if j not in placed]


def joint_energy(e) -> np.ndarray:
    return sum(v for k, v in e.items() if k.endswith("_joint"))


def run(scene, state, dt, integrator, dtype, worlds=64, seconds=2.0, controls=None) -> dict:
    """One run's row (module docstring)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sim = Simulator(scene, num_worlds=worlds, dt=dt, integrator=integrator, dtype=dtype)
    x, v = state
    sim.set_joint_state(x, v)
    if controls is not None:
        sim.set_controls(controls)
    loop = closing_joints(sim)
    e = sim.energies()
    row = dict(dt=dt, integrator=integrator, dtype=dtype, worlds=worlds, closing_joints=[scene.joints[j].name for j in loop],
               closing_gap_m=float(sim.joint_violation(loop).max()) if loop else None,
               joint_energy_after_set=float(joint_energy(e).max()))  # fmt: skip
    E0, Vmin = sum(e.values()), e["gravity"].copy()
    hist, prev_sub = [], np.ones(worlds, dtype=int)
    E_prev, e_prev = E0, e
    for k in range(int(round(seconds / dt))):
        sim.step()
        e, ok, sub = sim.energies(), sim.world_status() == 0, sim.substeps()
        E = sum(e.values())
        Vmin = np.where(ok, np.minimum(Vmin, e["gravity"]), Vmin)
        hist.append(dict(step=k + 1, dE=np.where(ok, E - E_prev, -np.inf), dV=e["gravity"] - e_prev["gravity"],
                         dK=e["kinetic"] - e_prev["kinetic"], dJ=joint_energy(e) - joint_energy(e_prev),
                         J_before=joint_energy(e_prev), sub=sub.copy(), sub_before=prev_sub))  # fmt: skip
        E_prev, e_prev, prev_sub = E, e, sub.copy()
    S = np.maximum(E0 - Vmin, 1e-12)
    h2 = dt * dt
    h0_2 = (2.0 * dt / 3.0 if integrator == "bdf2" else dt) ** 2  # energies()' joints are K/2 Σ‖C‖² over it
    gains = []
    for s in hist:
        for w in np.flatnonzero(s["dE"] / S > LIMIT):
            gains.append(dict(world=int(w), step=s["step"], gain=float(s["dE"][w] / S[w]), swing_J=float(S[w]),
                              dE_J=float(s["dE"][w]), d_gravity_J=float(s["dV"][w]), d_kinetic_J=float(s["dK"][w]),
                              d_joint=float(s["dJ"][w]), substeps=int(s["sub"][w]),
                              substeps_before=int(s["sub_before"][w]),
                              rebound_J=float((1 - 4 / 9) * 2 * s["J_before"][w] * h0_2 / h2)))  # fmt: skip
    worst = max((g["gain"] for g in gains), default=max(float((s["dE"] / S).max()) for s in hist))
    row.update(gain_worlds=len({g["world"] for g in gains}), worst_step_gain=worst, gains=gains)
    return row


def fourbar():
    c = robustness.case("fourbar")
    return c.scene(), lambda n: c.state(np.random.default_rng(0), n)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dts", nargs="*", type=float, default=[0.1, 0.2])
    p.add_argument("--integrators", nargs="*", default=list(robustness.INTEGRATORS))
    p.add_argument("--dtypes", nargs="*", default=list(robustness.DTYPES))
    p.add_argument("--tasks", nargs="*", default=["CartPoleSwingUp-v0", "DoublePendulumCart-v0"])
    p.add_argument("--out", default="results/loop_energy_cpu.json")
    a = p.parse_args(argv)
    rows = []
    scene, draw = fourbar()
    runs = [("fourbar", scene, draw, dt, None) for dt in a.dts]
    for name in a.tasks:
        env = energy_gain_tasks.task_env(name)
        runs.append((name, env.scene, lambda n, env=env: energy_gain_tasks.draw(env, "reset", n, np.random.default_rng(0)),
                     float(env.dt), np.zeros((64, len(env.scene.drives)))))  # fmt: skip
    for name, scene, draw, dt, controls in runs:
        for integrator in a.integrators:
            for dtype in a.dtypes:
                r = dict(case=name, **run(scene, draw(64), dt, integrator, dtype, controls=controls))
                rows.append(r)
                steps = sorted({g["step"] for g in r["gains"]})
                print(f"{name} dt {dt} {integrator} {dtype}: closing gap {r['closing_gap_m']}, worlds > 5% "
                      f"{r['gain_worlds']} (steps {steps}), worst {100 * r['worst_step_gain']:.2f}%", flush=True)
                for g in r["gains"][:12]:
                    print("   ", {k: (round(v, 6) if isinstance(v, float) else v) for k, v in g.items()})
    meta = dict(date=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                machine=platform.processor() or platform.machine(), device="cpu",
                command=" ".join(["python scripts/loop_energy.py"] + (sys.argv[1:] if argv is None else argv)))
    with open(a.out, "w") as f:
        json.dump(dict(meta=meta, rows=rows), f, indent=1)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
