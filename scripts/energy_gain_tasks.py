"""Whether BDF2 steps of the registered tasks, at their own dt, gain energy when nothing pushes.

For each task of ``abd_gym.vector.registration.TASKS`` (its scene, its simulator dt), 64 worlds
from random joint states, zero controls, stepped 2 s under BDF2 in float32 and float64, with the
energy test off (``energy_gain=0``) and on (``energy_gain=0.05``).  Two draws of the state:

- ``reset``: the task's own reset distribution (its ``initial_state``);
- ``wide``: beyond it: each joint ±1 (rad or m) off the reset state and ±5 (rad/s or m/s) rates,
  a limited joint kept 5% of its range inside its bounds; a closed-loop task (four-bar, slider
  crank) at any crank angle its reset draws from with crank rates ±5 rad/s, its other joints
  following the loop.

Per run, as ``python -m abd_gym.bench robustness`` measures it (bench/robustness.py): the largest
single-step rise of a world's total energy beyond the rounding allowance of the two states
(``Simulator.energy_allowance``) over its swing energy (``worst step gain``; far below 0 where
the allowance exceeds the swing energy), the worlds whose step gain exceeds 5%, the substeps
the energy test retried and the world-steps it kept after 4 substeps.  A scene with a position drive is not conservative (its spring's energy is not
in ``energies()``) and is listed without gains.  The gravity turn of a step
(``conditioning.gravity_turn``) says where a vector env runs the test by default (above
``conditioning.ENERGY_TEST_TURN``; a Simulator runs it in every conservative scene).

    python scripts/energy_gain_tasks.py [--tasks Pendulum-v0 ...] [--worlds 64] [--seconds 2]
                                        [--out results/energy_gain_tasks_cpu.json]

Prints a Markdown table and writes the rows as JSON.  ``--cost`` instead times what the test costs
on the CPU, in one process, the variants in alternating rounds, each keeping its fastest (process
CPU time): a one-world env step (``gym.make``, random actions: every step's drive pushes, so the
test is built but skipped) with ``energy_gain`` 0 and 0.05, and a Simulator step of a pendulum
and a double pendulum (an effort drive on the first hinge) of 1 and 64 worlds: the test off (0)
and on (0.05) at controls 0 (every world tested), off and skipped (0.05) at controls 1 (every
drive pushing); each variant's time against the test off at the same controls.

    python scripts/energy_gain_tasks.py --cost [--ids CartPole-v0 InvertedPendulum-v5]
                                        [--out results/energy_gain_cost_cpu.json]

``--profile`` times where a tested step's time goes: each phase of a Simulator step (the test's
``before``: host checks and the state's copy; the step's own launches; ``check``: ``mark`` and
the verdict, whose energy ``measure`` is also timed alone) of the pendulum and double pendulum
above at zero controls, the test off and on, best of alternating rounds (µs of process CPU time
a call: the CPU's concurrent Newton launches count each core's time).

    python scripts/energy_gain_tasks.py --profile [--profile-worlds 1 64 1024] [--rounds 3]
                                        [--out results/energy_gain_profile_cpu.json]
"""
import argparse
import datetime
import importlib
import json
import math
import os
import platform
import sys
import time
import warnings

import numpy as np
import warp as wp

import abd_gym
from abd_gym.bench.robustness import _measure
from abd_gym.sim import conditioning
from abd_gym.sim.simulator import Simulator
from abd_gym.vector.registration import TASKS

DTYPES = ("float32", "float64")
GAINS = (0.0, 0.05)
WIDE_OFFSET, WIDE_RATE, LIMIT_MARGIN = 1.0, 5.0, 0.05


def task_env(name):
    """A one-env vector env of task ``name`` (its scene, dt and state draws)."""
    module, _, vector = TASKS[name][:3]
    return getattr(importlib.import_module(module), vector)(num_envs=1)


def _loop_state(phi, rate, coords):
    """(coordinates, rates) of a closed loop at crank angles phi turning at ``rate`` (``coords``:
    the task's crank angle -> joint coordinates)."""
    eps = 1e-5
    return coords(phi), (coords(phi + eps * rate) - coords(phi - eps * rate)) / (2 * eps)


def draw(env, how, n, rng):
    """(coordinates, rates) of n worlds: the task's reset draw, or ``wide`` beyond it (docstring)."""
    x, v = env.initial_state(n, rng, {})
    if how == "reset":
        return np.asarray(x, np.float64), np.asarray(v, np.float64)
    rate = rng.uniform(-WIDE_RATE, WIDE_RATE, n)
    if hasattr(env, "joint_angles"):  # four-bar: any crank angle
        return _loop_state(rng.uniform(-math.pi, math.pi, n), rate, env.joint_angles)
    if hasattr(env, "joint_state"):  # slider crank: the crank range it resets in
        lo, hi = env.phi_range
        return _loop_state(rng.uniform(lo + 0.05, hi - 0.05, n), rate, env.joint_state)
    x = np.asarray(x, np.float64) + rng.uniform(-WIDE_OFFSET, WIDE_OFFSET, np.shape(x))
    v = np.asarray(v, np.float64) + rng.uniform(-WIDE_RATE, WIDE_RATE, np.shape(v))
    for j, joint in enumerate(env.scene.joints):
        if joint.has_limit:
            lo, up = joint.attributes["limit/lower"], joint.attributes["limit/upper"]
            m = LIMIT_MARGIN * (up - lo)
            x[:, j] = np.clip(x[:, j], lo + m, up - m)
    return x, v


def conservative(scene) -> bool:
    """No position drive: every energy the scene stores is in ``energies()``."""
    return all(d.mode != "position" for d in scene.drives)


def run_one(env, name, how, dtype, gain, worlds, seconds, seed):
    """One run's row (bench/robustness.py's measurements)."""
    dt = float(env.dt)
    steps = int(round(seconds / dt))
    row = dict(task=name, draw=how, dtype=dtype, energy_gain=gain, dt=dt, worlds=worlds, steps=steps,
               gravity_turn=conditioning.gravity_turn(env.scene, dt), conservative=conservative(env.scene),
               warnings=[])  # fmt: skip
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sim = Simulator(env.scene, num_worlds=worlds, dt=dt, integrator="bdf2", dtype=dtype, energy_gain=gain)
        x, v = draw(env, how, worlds, np.random.default_rng(seed))
        sim.set_joint_state(x, v)
        sim.set_controls(np.zeros((worlds, len(env.scene.drives))))
    row["warnings"] = sorted({str(w.message) for w in caught})
    t0 = time.process_time()
    row = _measure(sim, env.scene, steps, row)
    row["cpu_seconds"] = time.process_time() - t0
    return row


def table(rows) -> str:
    """The Markdown table: one line per task, draw and dtype, the test off and on side by side."""
    key = lambda r: (r["task"], r["draw"], r["dtype"])  # noqa: E731
    by = {}
    for r in rows:
        by.setdefault(key(r), {})[r["energy_gain"]] = r
    head = ("| task | dt [s] | turn [rad] | draw | dtype | swing [J] | off: worst step gain | off: worlds > 5% | "
            "off: reported | on: worst step gain | on: worlds > 5% | on: substeps 2/4 | on: kept gain | on: reported |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]

    def pct(r, k):
        v = r.get(k)
        return "n/a" if v is None else f"{100 * v:.2f}%"

    for k, pair in by.items():
        off, on = pair.get(0.0), pair.get(0.05)
        first = off or on
        swing = first.get("swing_J")
        cells = [k[0], f"{first['dt']:g}", f"{first['gravity_turn']:.3f}", k[1], k[2],
                 f"{swing[0]:.2g}–{swing[1]:.2g}" if swing else ""]
        for r in (off, on):
            if r is None or not r["conservative"]:
                cells += ["not conservative"] + [""] * (1 if r is off else 4)
                continue
            cells += [pct(r, "worst_step_gain"), str(r["step_gain_worlds"])]
            if r is on:
                sub = {int(n): count for n, count in r["substeps"].items()}  # (JSON's keys are strings)
                cells += [f"{sub[2]}/{sub[4]}", str(r["kept_gain"])]
            cells.append(str(r["reported"]))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _env_runner(name, gain, steps, seed=0):
    """A one-world env of task ``name`` (energy_gain ``gain``) and its timed round (bench/single.py)."""
    import gymnasium as gym

    from abd_gym.bench.single import Runner
    from abd_gym.vector.registration import NAMESPACE

    env = gym.make(f"{NAMESPACE}/{name}", simulator_options=dict(energy_gain=gain))
    return env, Runner(env, steps, seed, time.process_time)


def _sim_round(scene, worlds, gain, control, steps):
    """A Simulator of ``scene`` (energy_gain ``gain``, every control ``control``) and its timed
    round: steps/s of ``steps`` single steps from the same state."""
    from abd_gym.sim.simulator import Simulator as Sim

    sim = Sim(scene, num_worlds=worlds, dt=0.01, energy_gain=gain)
    x0 = np.random.default_rng(0).uniform(-1.0, 1.0, (worlds, scene.num_joints))
    sim.set_controls(np.full((worlds, len(scene.drives)), control))

    def round_(n=steps):
        sim.set_joint_state(x0, np.zeros_like(x0))
        t0 = time.process_time()
        for _ in range(n):
            sim.step()
        return n / (time.process_time() - t0)

    return sim, round_


def cost(ids, steps, sim_steps, rounds, sims=True):
    """Rows of steps/s (best of ``rounds`` alternating rounds) of every variant (module docstring)."""
    from abd_gym.sim import mechanisms

    variants = {}  # (what, variant) -> round
    envs = []
    for name in ids:
        for gain in GAINS:
            env, runner = _env_runner(name, gain, steps)
            envs.append(env)
            variants[(f"env {name}", f"energy_gain {gain}")] = runner
    mechanisms_timed = (("pendulum", mechanisms.pendulum), ("double pendulum", mechanisms.double_pendulum))
    for label, build in mechanisms_timed if sims else ():
        scene = build()
        scene.add_drive(0, mode="effort")
        for worlds in (1, 64):
            for variant, gain, control in (("off", 0.0, 0.0), ("on", 0.05, 0.0), ("off, pushed", 0.0, 1.0),
                                           ("skipped", 0.05, 1.0)):  # fmt: skip
                variants[(f"sim {label} x{worlds}", variant)] = _sim_round(scene, worlds, gain, control, sim_steps)[1]
    best = {}
    for k, r in variants.items():  # warm-up: kernels loaded, graphs captured
        r.round(steps=200) if hasattr(r, "round") else r(50)
    for _ in range(rounds):
        for k, r in variants.items():
            rate = r.round()[0] if hasattr(r, "round") else r()
            best[k] = max(best.get(k, 0.0), rate)
    for env in envs:
        env.close()
    rows = []
    for (what, variant), rate in best.items():
        off = "energy_gain 0.0" if what.startswith("env") else "off, pushed" if variant == "skipped" else "off"
        base = best[(what, off)]
        rows.append(dict(what=what, variant=variant, steps_per_s=rate, cost_vs_off=base / rate - 1.0))
    return rows


def _phase_times(sim, n):
    """{phase: µs of process CPU time a call} of one step's phases (Solver.step_phases: the test's ``before``, the
    step's own parts, ``check``), each replayed n times as the simulator's step replays it (a
    capturable phase as a graph), and of the test's energy measure alone (``measure``, a graph)."""
    from abd_gym.core import graphs

    state, solver = sim.state, sim.solver
    dev = sim.device
    calls = {}
    for phase, capturable in solver.step_phases(1):
        name = getattr(phase, "func", phase).__name__
        if capturable:
            graph = graphs.capture(dev, lambda phase=phase: phase(state))[0]
            calls[name] = lambda graph=graph: wp.capture_launch(graph)
        else:
            calls[name] = lambda phase=phase: phase(state)
    energy = solver.retry.energy if solver.retry is not None else None
    if energy is not None:
        graph = graphs.capture(dev, lambda: energy.measure(state, solver.all_active))[0]
        calls["measure"] = lambda: wp.capture_launch(graph)
    calls["step"] = sim.step
    out = {}
    for name, call in calls.items():
        t0 = time.process_time()
        for _ in range(n):
            call()
        out[name] = (time.process_time() - t0) / n * 1e6
    return out


def profile(worlds, rounds):
    """Rows of µs a call (best of ``rounds`` alternating rounds) of each phase of a simulator step,
    the test off (0) and on (0.05) at controls 0 (module docstring, --profile)."""
    from abd_gym.sim import mechanisms

    sims = {}
    for label, build in (("pendulum", mechanisms.pendulum), ("double pendulum", mechanisms.double_pendulum)):
        scene = build()
        scene.add_drive(0, mode="effort")
        for w in worlds:
            for gain in GAINS:
                sim = Simulator(scene, num_worlds=w, dt=0.01, energy_gain=gain)
                x0 = np.random.default_rng(0).uniform(-1.0, 1.0, (w, scene.num_joints))
                sim.set_joint_state(x0, np.zeros_like(x0))
                sim.step(3)
                sims[(label, w, gain)] = sim
    best = {}
    for _ in range(rounds):
        for (label, w, gain), sim in sims.items():
            for phase, us in _phase_times(sim, max(100, 20000 // w)).items():
                key = (label, w, gain, phase)
                best[key] = min(best.get(key, math.inf), us)
    return [dict(what=f"sim {label} x{w}", energy_gain=gain, phase=phase, us=us)
            for (label, w, gain, phase), us in best.items()]


def cost_table(rows) -> str:
    lines = ["| what | variant | steps/s (process CPU) | time vs off |", "|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['what']} | {r['variant']} | {r['steps_per_s']:.0f} | {100 * r['cost_vs_off']:+.1f}% |")
    return "\n".join(lines)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--tasks", nargs="*", default=list(TASKS))
    p.add_argument("--draws", nargs="*", default=["reset", "wide"])
    p.add_argument("--dtypes", nargs="*", default=list(DTYPES))
    p.add_argument("--worlds", type=int, default=64)
    p.add_argument("--seconds", type=float, default=2.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None, help="default: results/energy_gain_tasks_cpu.json, with --cost "
                   "results/energy_gain_cost_cpu.json")
    p.add_argument("--table", metavar="JSON", help="print the table of a JSON this wrote, and run nothing")
    p.add_argument("--cost", action="store_true", help="time the test's cost instead (module docstring)")
    p.add_argument("--ids", nargs="*", default=["CartPole-v0", "InvertedPendulum-v5"])
    p.add_argument("--steps", type=int, default=3000, help="--cost: env steps a round")
    p.add_argument("--sim-steps", type=int, default=1000, help="--cost: simulator steps a round")
    p.add_argument("--rounds", type=int, default=3, help="--cost: alternating rounds")
    p.add_argument("--envs-only", action="store_true", help="--cost: the envs only, not the simulator loops")
    p.add_argument("--profile", action="store_true", help="time each phase of a simulator step instead")
    p.add_argument("--profile-worlds", nargs="*", type=int, default=[1, 64, 1024])
    a = p.parse_args(argv)
    meta = dict(date=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                machine=platform.processor() or platform.machine(), device="cpu",
                energy_test_turn=conditioning.ENERGY_TEST_TURN, abd_gym=os.path.dirname(abd_gym.__file__),
                command=" ".join(["python scripts/energy_gain_tasks.py"] + (sys.argv[1:] if argv is None else argv)))
    if a.table:
        with open(a.table) as f:
            print(table(json.load(f)["rows"]))
        return
    if a.profile:
        rows = profile(a.profile_worlds, a.rounds)
        for r in rows:
            print(f"| {r['what']} | {r['energy_gain']} | {r['phase']} | {r['us']:.1f} |")
        out = a.out or "results/energy_gain_profile_cpu.json"
        with open(out, "w") as f:
            json.dump(dict(meta=meta, rows=rows), f, indent=1)
        print(f"wrote {out}")
        return
    if a.cost:
        rows = cost(a.ids, a.steps, a.sim_steps, a.rounds, sims=not a.envs_only)
        print(cost_table(rows))
        out = a.out or "results/energy_gain_cost_cpu.json"
        with open(out, "w") as f:
            json.dump(dict(meta=meta, rows=rows), f, indent=1)
        print(f"wrote {out}")
        return
    rows = []
    for name in a.tasks:
        env = task_env(name)
        for how in a.draws:
            for dtype in a.dtypes:
                for gain in GAINS:
                    r = run_one(env, name, how, dtype, gain, a.worlds, a.seconds, a.seed)
                    rows.append(r)
                    print(f"{name} {how} {dtype} gain {gain}: worst step gain {r.get('worst_step_gain')}, "
                          f"> 5% {r.get('step_gain_worlds')}, reported {r['reported']}, substeps {r['substeps']}, "
                          f"{r['cpu_seconds']:.1f} s", flush=True)  # fmt: skip
        env.close()
    print(table(rows))
    meta.update(integrator="bdf2", seconds=a.seconds, worlds=a.worlds)
    out = a.out or "results/energy_gain_tasks_cpu.json"
    with open(out, "w") as f:
        json.dump(dict(meta=meta, rows=rows), f, indent=1)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
