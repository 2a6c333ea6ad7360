"""``python -m abd_gym.bench robustness``: hard cases with default settings.

Each case is a scene, a step dt and a batch of worlds with random initial states drawn from a
fixed seed, run for a fixed number of steps under each integrator and dtype with the simulator's
default settings (only the scene and dt are chosen).  Per run it reports:

- ``reported``: worlds whose ``world_status()`` left OK at any step (with the causes, by
  ``WorldStatus`` name); a reported world's later steps are left out of every other column; at
  dt NO_RETRY_DT and above, also without the retry of failed steps (``retry=False``);
- ``substeps``: world-steps retried as 2, or 4, substeps (``Simulator.substeps``): steps that
  failed, or that gained more energy than the simulator's energy test allows (conservative
  worlds, ``Simulator(energy_gain=...)``); ``kept gain``: world-steps that still gained at 4
  substeps and were kept (``Simulator.energy_gained``);
- ``silent``: world-steps whose Newton solve ended unconverged (``converged()`` False) on a world
  that was not reported: a step committed with nothing said;
- ``gain > 5%`` and ``worst gain`` (conservative cases only: no drive acts): the energy gain
  max_t E(t) − E(0) of each world's total energy E (the sum of ``energies()``: kinetic, gravity,
  orthogonality, joints, limits), relative to the world's swing energy S = E(0) − min_t V_g(t),
  its energy above the lowest gravity potential it visits (for a conservative world, its largest
  kinetic plus elastic energy; T(0) where gravity does no work), ``step gain``, the largest rise
  of E in one OK step over S, and ``ΔE at end``, the mean (E(end) − E(0)) / S (the energy a run
  kept); a gain and a step's rise are counted beyond the rounding allowances A of the two states
  compared (``Simulator.energy_allowance``, the energy test's), so a world gains only what its
  energy can resolve;
- ``gap``: the largest joint residual ``joint_violation()`` [mm];
- ``overshoot``: the largest excursion of a limited joint past its bound (multi-turn angle [rad],
  displacement [m]), and its ratio to the estimate of docs/design.md §3.3 with the world's whole
  swing energy arriving at the limit: (S dt²/s)^(1/3) rad for a revolute limit of strength s
  (its physical stiffness s/dt², as ``energies()`` counts it), w·(S dt²/s)^(1/3) m for a
  prismatic one of range width w;
- ``iterations``: Newton iterations a step, mean and max;
- ``refused`` / ``warned``: the simulator raised an error when built or given the initial
  state / issued a warning then.

Prints a table, writes ``robustness.json`` to --out and, with --md PATH or --write-doc, the
Markdown report (docs/robustness.md).
"""
import argparse
import datetime
import json
import os
import platform
import sys
import time
import warnings
from dataclasses import dataclass

import numpy as np
import warp as wp

from ..sim import mechanisms
from ..sim.scene import Scene
from ..sim.shapes import Box
from ..sim.simulator import Simulator
from ..sim.status import WorldStatus

INTEGRATORS = ("implicit_euler", "bdf2")
DTYPES = ("float32", "float64")
GAIN_LIMIT = 0.05  # relative energy gain counted as a gain
NO_RETRY_DT = 0.1  # runs at this dt and above are repeated with the retry of failed steps off
DOC = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "docs", "robustness.md")


@dataclass
class Case:
    """A hard case: ``scene()`` builds it, ``state(rng, n)`` draws (coordinates, rates) of n worlds,
    stepped ``seconds`` at each of ``dts``; ``conservative``: no drive acts (a closed-loop task's
    effort drive is left at zero), so energy must not grow."""

    name: str
    scene: object
    state: object
    dts: tuple
    seconds: float
    what: str
    conservative: bool = True


def _angles(lo, hi, joints, rates=0.0):
    """Uniform random joint angles in [lo, hi] and rates in ±rates."""
    def draw(rng, n):
        return rng.uniform(lo, hi, (n, joints)), rng.uniform(-rates, rates, (n, joints))
    return draw


def _spins(rng, n):
    """A link near hanging (±1 rad) spun at 10–50 rad/s either way."""
    speed = rng.uniform(10.0, 50.0, n) * rng.choice([-1.0, 1.0], n)
    return rng.uniform(-1.0, 1.0, (n, 1)), speed[:, None]


def slammer(half_range=0.25, strength=1e5, mass=1.0) -> Scene:
    """A 1 kg block on a horizontal prismatic joint limited to ±``half_range`` [m] (strength [J])."""
    scene = Scene()
    base = scene.add_body(Box(half_extents=(0.05, 0.05, 0.05)), fixed=True)
    block = scene.add_body(Box(half_extents=(0.05, 0.05, 0.05)), mass=mass)
    j = scene.add_prismatic_joint(base, block, anchor=(0, 0, 0), axis=(1, 0, 0))
    scene.add_prismatic_limit(j, -half_range, half_range, strength)
    return scene


def _slams(rng, n):
    """From within ±0.1 m at 15–25 m/s either way."""
    speed = rng.uniform(15.0, 25.0, n) * rng.choice([-1.0, 1.0], n)
    return rng.uniform(-0.1, 0.1, (n, 1)), speed[:, None]


def _closed_loop(env_cls):
    """(scene, state) of a closed-loop task: its scene and its reset distribution, no control."""
    env = env_cls(num_envs=1)
    scene = env.build_scene()

    def draw(rng, n):
        return env.initial_state(n, rng, None)

    return scene, draw


def _fourbar():
    from ..envs.fourbar import FourBarVectorEnv

    return _closed_loop(FourBarVectorEnv)


def _slider_crank():
    from ..envs.slider_crank import SliderCrankVectorEnv

    return _closed_loop(SliderCrankVectorEnv)


def cases():
    """The hard cases, in report order."""
    spin = lambda: mechanisms.pendulum(limit=(-3.1, 3.1, 1e5))  # noqa: E731
    out = [
        Case("light_under_heavy", lambda: mechanisms.chain(2, masses=[1.0, 0.001]), _angles(-1.5, 1.5, 2), (0.01, 0.03),
             1.0, "0.001 kg link under a 1 kg link (0.5 m links), released from ±1.5 rad"),
        Case("heavy_under_light", lambda: mechanisms.chain(2, masses=[1.0, 1000.0]), _angles(-1.5, 1.5, 2),
             (0.01, 0.03), 1.0, "1000 kg link hanging under a 1 kg link, released from ±1.5 rad"),
        Case("chain20", lambda: mechanisms.chain(20, length=0.1), _angles(-0.3, 0.3, 20), (0.01,), 5.0,
             "20 links of 0.1 m, 1 kg, released from ±0.3 rad a joint"),
        Case("spin_into_limit", spin, _spins, (0.002, 0.01), 0.5,
             "1 kg link spun at 10–50 rad/s into a revolute limit at ±3.1 rad (strength 1e5)"),
        Case("prismatic_slam", slammer, _slams, (0.01,), 1.0,
             "1 kg block at 15–25 m/s into a prismatic limit at ±0.25 m (strength 1e5)"),
    ]
    for ratio in (1.0, 1e2, 1e4, 1e6, 1e8):
        out.append(Case(f"strength_{ratio:g}", lambda r=ratio: mechanisms.double_pendulum(strength_ratio=r),
                        _angles(-2.0, 2.0, 2), (0.01,), 1.0, f"double pendulum, joint strength_ratio {ratio:g}"))
    out += [
        Case("absurd_rates", mechanisms.double_pendulum, _angles(-1.0, 1.0, 2, rates=1e9), (0.01,), 0.1,
             "double pendulum started at joint rates up to ±1e9 rad/s: to be refused or reported"),
        Case("large_dt", mechanisms.double_pendulum, _angles(-2.5, 2.5, 2), (0.03, 0.05, 0.1, 0.2), 2.0,
             "double pendulum released from ±2.5 rad"),
        Case("fourbar", lambda: _loop("fourbar")[0], lambda rng, n: _loop("fourbar")[1](rng, n),
             (0.03, 0.05, 0.1, 0.2), 2.0, "FourBar-v0's linkage (closed loop) from its reset distribution, no torque"),
        Case("mixed_chain", lambda: mechanisms.chain(10, length=0.1, masses=[1.0, 0.01] * 5), _angles(-0.5, 0.5, 10),
             (0.01,), 2.0, "10 links of 0.1 m alternating 1 kg and 0.01 kg, released from ±0.5 rad a joint"),
        Case("slider_crank", lambda: _loop("slider_crank")[0], lambda rng, n: _loop("slider_crank")[1](rng, n),
             (0.03, 0.05),
             2.0, "SliderCrank-v0's linkage (closed loop, stroke limit) from its reset distribution, no torque"),
    ]
    return out


_LOOPS = {}  # closed-loop task name -> (scene, state), built once (building one builds its env)


def _loop(name):
    """(scene, state) of the closed-loop task ``name`` ("fourbar" or "slider_crank")."""
    if name not in _LOOPS:
        _LOOPS[name] = _fourbar() if name == "fourbar" else _slider_crank()
    return _LOOPS[name]


CASE_NAMES = tuple(c.name for c in cases())


def case(name) -> Case:
    """The case called ``name``."""
    for c in cases():
        if c.name == name:
            return c
    raise ValueError(f"unknown case {name!r}; cases: {', '.join(c.name for c in cases())}")


def _limits(scene):
    """(joint indices, lower, upper, strength, range width or None for revolute) of limited joints."""
    out = []
    for j, joint in enumerate(scene.joints):
        if joint.has_limit:
            a = joint.attributes
            lo, up, s = a["limit/lower"], a["limit/upper"], a["limit/strength"]
            out.append((j, lo, up, s, None if joint.kind == "revolute" else up - lo))
    return out


def run_case(c: Case, dt, integrator="implicit_euler", dtype="float32", worlds=64, steps=None, device="cpu",
             seed=0, scene=None, retry=True, energy_gain=None) -> dict:
    """Step ``worlds`` worlds of case ``c`` at ``dt`` for ``steps`` steps (default: ``c.seconds``)
    with default settings (``retry``: False turns the retry of failed steps off; ``energy_gain``,
    where given, the simulator's energy test's tolerance, 0 off); the row of
    measurements described in the module docstring.  ``scene``: a prebuilt scene of the case
    (building one per run is the same scene)."""
    steps = steps or int(round(c.seconds / dt))
    row = dict(case=c.name, dt=dt, integrator=integrator, dtype=dtype, worlds=worlds, steps=steps,
               conservative=c.conservative, refused=None, warnings=[])  # fmt: skip
    scene = scene or c.scene()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            more = {} if energy_gain is None else dict(energy_gain=energy_gain)
            sim = Simulator(scene, num_worlds=worlds, dt=dt, integrator=integrator, dtype=dtype, device=device,
                            retry=retry, **more)  # fmt: skip
            x0, v0 = c.state(np.random.default_rng(seed), worlds)
            sim.set_joint_state(x0, v0)
        except (ValueError, RuntimeError) as e:
            row["refused"] = f"{type(e).__name__}: {e}"
            return row
    row["warnings"] = sorted({str(w.message) for w in caught})
    return _measure(sim, scene, steps, row)


def _measure(sim, scene, steps, row):
    W = sim.num_worlds
    limits = _limits(scene)
    e = sim.energies()
    E0, Vmin = sum(e.values()), e["gravity"].copy()
    A0 = sim.energy_allowance()  # the energy test's rounding allowance of each state's total
    Emax = np.full(W, -np.inf)  # largest energy after a step less its allowance
    alive = np.ones(W, bool)  # not reported so far
    reported_at = np.full(W, -1)
    causes = {}
    silent = 0
    gap = np.zeros(W)
    over = np.zeros((W, len(limits)))
    iters = []
    step_gain = np.full(W, -np.inf)  # largest energy change of one OK step beyond both states' allowances
    substeps = np.zeros(5, dtype=int)  # world-steps taken as 1, 2 or 4 substeps
    kept_gain = 0  # world-steps that gained at 4 substeps too (kept)
    E_prev, A_prev = E0, A0
    t0 = time.perf_counter()
    for k in range(steps):
        sim.step()
        status = sim.world_status()
        substeps += np.bincount(np.where(alive & (status == WorldStatus.OK), sim.substeps(), 0), minlength=5)
        kept_gain += int((alive & sim.energy_gained()).sum())
        failed = status != WorldStatus.OK
        new = failed & alive
        if new.any():
            reported_at[new] = k
            for w in np.flatnonzero(new):
                cause = WorldStatus(int(status[w])).name
                causes[cause] = causes.get(cause, 0) + 1
        alive &= ~failed
        silent += int((~sim.converged() & alive).sum())
        iters.append(np.where(alive, sim.newton_iterations(), -1))
        e = sim.energies()
        E, A = sum(e.values()), sim.energy_allowance()
        Emax = np.where(alive, np.maximum(Emax, E - A), Emax)
        step_gain = np.where(alive, np.maximum(step_gain, E - E_prev - A - A_prev), step_gain)
        E_prev, A_prev = E, A
        Vmin = np.where(alive, np.minimum(Vmin, e["gravity"]), Vmin)
        gap = np.where(alive, np.maximum(gap, np.nan_to_num(sim.joint_violation(), nan=np.inf)), gap)
        if limits:
            x = sim.joint_angles_unwrapped()
            for i, (j, lo, up, _, _) in enumerate(limits):
                over[:, i] = np.where(alive, np.maximum(over[:, i], np.maximum(x[:, j] - up, lo - x[:, j])), over[:, i])
    seconds = time.perf_counter() - t0
    it = np.array(iters)
    it = it[it >= 0]
    swing = np.maximum(E0 - Vmin, 1e-12)
    gain = (Emax - E0 - A0) / swing
    bound = np.zeros_like(over)
    for i, (_, _, _, s, width) in enumerate(limits):
        bound[:, i] = (swing * sim.dt**2 / s) ** (1 / 3) * (1.0 if width is None else width)
    row.update(reported=int((reported_at >= 0).sum()), first_report_step=int(reported_at[reported_at >= 0].min())
               if (reported_at >= 0).any() else None, causes={str(k): v for k, v in sorted(causes.items())},
               silent=silent, seconds=seconds, substeps={n: int(substeps[n]) for n in (2, 4)}, kept_gain=kept_gain,
               iterations_mean=float(it.mean()) if it.size else None, iterations_max=int(it.max()) if it.size else None,
               gap_mm=float(gap.max() * 1e3))  # fmt: skip
    if row["conservative"]:
        kept = gain[alive & np.isfinite(gain)]
        final = ((E - E0) / swing)[alive & np.isfinite(E)]
        step = (step_gain / swing)[alive & np.isfinite(gain)]
        row.update(step_gain_worlds=int((step > GAIN_LIMIT).sum()), worst_step_gain=float(step.max()) if step.size else None)
        row.update(gain_worlds=int((kept > GAIN_LIMIT).sum()), worst_gain=float(kept.max()) if kept.size else None,
                   final_change=float(final.mean()) if final.size else None,
                   swing_J=[float(swing.min()), float(swing.max())])  # fmt: skip
    if limits:
        row.update(overshoot=float(over.max()), overshoot_unit="m" if limits[0][4] is not None else "rad",
                   overshoot_over_bound=float((over / bound).max()))  # fmt: skip
    return row


def run(names=None, worlds=64, integrators=INTEGRATORS, dtypes=DTYPES, device="cpu", steps=None, seed=0,
        progress=print) -> list:
    """Rows of every case in ``names`` (default: all) × its dts × integrators × dtypes."""
    rows = []
    for c in cases():
        if names and c.name not in names:
            continue
        scene = c.scene()
        for dt in c.dts:
            for integrator in integrators:
                for dtype in dtypes:
                    rows.append(run_case(c, dt, integrator, dtype, worlds, steps, device, seed, scene))
                    if dt >= NO_RETRY_DT and not rows[-1]["refused"]:
                        plain = run_case(c, dt, integrator, dtype, worlds, steps, device, seed, scene, retry=False)
                        rows[-1]["reported_without_retry"] = plain["reported"]
                    if progress:
                        progress(line(rows[-1]))
    return rows


def line(r) -> str:
    """One run's row as a line of text."""
    if r["refused"]:
        return f"{r['case']:18s} dt {r['dt']:<6g} {r['integrator']:15s} {r['dtype']:8s} refused: {r['refused']}"
    gain = "" if r.get("worst_gain") is None else (f" gain>5% {r['gain_worlds']:3d} worst {r['worst_gain']:+.1%}"
                                                   f" step gain>5% {r['step_gain_worlds']:3d}")  # fmt: skip
    over = "" if "overshoot" not in r else \
        f" overshoot {r['overshoot']:.3g} {r['overshoot_unit']} ({r['overshoot_over_bound']:.2f} of bound)"
    return (f"{r['case']:18s} dt {r['dt']:<6g} {r['integrator']:15s} {r['dtype']:8s} reported {r['reported']:3d} "
            f"substeps 2/4 {r['substeps'][2]}/{r['substeps'][4]} kept gain {r['kept_gain']} silent {r['silent']:5d}{gain} gap {r['gap_mm']:.3g} mm"
            f"{over} iters {_its(r)} ({r['seconds']:.1f} s)")


def _its(r):
    return "–" if r["iterations_mean"] is None else f"{r['iterations_mean']:.2f} / {r['iterations_max']}"


def _cell_reported(r):
    if not r["reported"]:
        return "0"
    causes = ", ".join(f"{n}× {k}" for k, n in r["causes"].items())
    return f"{r['reported']} (step {r['first_report_step'] + 1}; {causes})"


def table(rows) -> str:
    """A Markdown table of the rows."""
    lines = ["| case | dt [s] | integrator | dtype | worlds × steps | reported | without retry | substeps 2 / 4 | kept gain | "
             "silent | "
             "gain > 5% | worst gain | step gain > 5% | worst step gain | ΔE at end | gap [mm] | overshoot (of bound) | "
             "iterations mean / max | build |",
             "|---|---:|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"]  # fmt: skip
    for r in rows:
        head = f"| {r['case']} | {r['dt']:g} | {r['integrator']} | {r['dtype']} | {r['worlds']} × {r['steps']} |"
        if r["refused"]:
            lines.append(head + f" – | – | – | – | – | – | – | – | – | – | – | – | – | refused: {r['refused']} |")
            continue
        gain = ("–", "–") if r.get("worst_gain") is None else (str(r["gain_worlds"]), f"{r['worst_gain']:+.2%}")
        step = ("–", "–") if r.get("worst_step_gain") is None else (str(r["step_gain_worlds"]),
                                                                    f"{r['worst_step_gain']:+.2%}")  # fmt: skip
        plain = str(r.get("reported_without_retry", "–"))
        subs = f"{r['substeps'][2]} / {r['substeps'][4]}"
        final = "–" if r.get("final_change") is None else f"{r['final_change']:+.1%}"
        over = "–" if "overshoot" not in r else \
            f"{r['overshoot']:.3g} {r['overshoot_unit']} ({r['overshoot_over_bound']:.2f})"
        build = "warned: " + "; ".join(r["warnings"]) if r["warnings"] else "ok"
        lines.append(head + f" {_cell_reported(r)} | {plain} | {subs} | {r['kept_gain']} | {r['silent']} | "
                     f"{gain[0]} | {gain[1]} | "
                     f"{step[0]} | {step[1]} | {final} | "
                     f"{r['gap_mm']:.3g} | "
                     f"{over} | {_its(r)} | {build} |")  # fmt: skip
    return "\n".join(lines)


def document(result) -> str:
    """docs/robustness.md from a result."""
    case_lines = "\n".join(f"- `{c.name}` (dt {', '.join(f'{d:g}' for d in c.dts)} s, {c.seconds:g} s): {c.what}."
                           for c in cases() if c.name in {r['case'] for r in result['rows']})  # fmt: skip
    return f"""# Robustness on hard cases

Generated by `{result['command']}` on {result['device_name']} ({result['device']}), {result['date']},
warp {result['warp']}; {result['seconds']:.0f} s. Do not edit: re-run the command.

Every run uses the simulator's default settings (tolerance, iteration cap, factor reuse, joint
strength, stiffness, plan, the retry of a failed step as 2, then 4 substeps); only the scene, dt,
integrator and dtype are chosen. Each case
steps {result['worlds']} worlds from random initial states (seed {result['seed']}).

## Cases

{case_lines}

## Columns

- **reported**: worlds whose `world_status()` left `OK` at any step (the step of the first, and
  the causes, `abd_gym.WorldStatus` names, with their counts). A reported world's later steps are
  left out of the other columns.
- **without retry**: at dt {NO_RETRY_DT:g} s and above, **reported** of the same run with the
  retry of failed steps off (`Simulator(retry=False)`).
- **substeps 2 / 4**: world-steps that failed (Newton did not converge or broke down), or that
  converged but raised a conservative world's total energy by more than 5% of its swing energy
  known so far (the energy test, by default where a step turns the scene's fastest gravity mode past 0.16
  rad: here from dt 0.03 on; docs/design.md §4.1),
  and were taken again as 2, or 4, substeps (`Simulator.substeps`); a world that fails at 4 too
  is reported.
- **kept gain**: world-steps that still gained more than the energy test allows at 4 substeps and
  were kept (`Simulator.energy_gained`). The goal is 0.
- **silent**: world-steps whose Newton solve ended unconverged (`converged()` False) in a world
  that was not reported: steps committed with nothing said. The goal is 0.
- **gain > 5%** and **worst gain** (conservative cases, where no drive acts): the gain
  max_t E(t) − E(0) of each world's total energy E (the sum of `energies()`: kinetic, gravity,
  orthogonality, joints as their physical energy K/(2ĥ₀²) Σ‖C‖², limits), relative to its swing energy S = E(0) − min_t V_g(t), the energy
  above the lowest gravity potential the world visits (its largest kinetic plus elastic energy
  when energy is conserved; its initial kinetic energy where gravity does no work). Worst gain is
  the largest over the worlds (negative: every world lost energy). The goal is 0 worlds above 5%.
- **step gain > 5%** and **worst step gain** (conservative cases): the largest rise of E in one
  step of a world not reported, relative to S: worlds with a step above 5%, and the largest.
  BDF2's energy is not monotone from step to step (its two-step history carries energy between
  steps), so a step's rise can exceed the run's.
- Both gains are counted beyond the rounding of the two energies compared: E(t) − E(0) less
  A(t) + A(0), A a state's allowance `Simulator.energy_allowance()`, the energy test's (the sums'
  rounding and each term's energy at its quantity's rounding, docs/design.md §4.1), so a world
  counts only a gain its energy can resolve (float32 worlds of swing energies of 1e-9 J do not).
- **ΔE at end**: (E(end) − E(0)) / S, the mean over worlds: the energy a run kept (the numerical
  damping of a dissipative integrator shows here).
- **gap**: the largest joint residual `joint_violation()` over worlds and steps [mm].
- **overshoot**: where a joint has a limit, its largest excursion past a bound (multi-turn angle
  [rad] or displacement [m]), and in brackets its ratio to the estimate of docs/design.md §3.3
  with the world's whole swing energy S arriving at the limit: (S dt²/s)^(1/3) rad for a revolute
  limit of strength s (its physical stiffness s/dt², as `energies()` counts it), w·(S dt²/s)^(1/3) m
  for a prismatic limit of range width w. Above 1: the limit did not hold as the estimate says.
- **iterations**: Newton iterations a step, mean and largest.
- **build**: `refused` when the simulator raised an error when built or given the state, `warned`
  with the warnings it issued.

## Results

{table(result['rows'])}
"""


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m abd_gym.bench robustness", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--worlds", type=int, default=64)
    ap.add_argument("--steps", type=int, default=None, help="steps a run (default: each case's duration / dt)")
    ap.add_argument("--cases", default=None, help="comma-separated case names (default: all)")
    ap.add_argument("--integrators", default=",".join(INTEGRATORS))
    ap.add_argument("--dtypes", default=",".join(DTYPES))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="bench_out")
    ap.add_argument("--md", default=None, help="write the Markdown report here")
    ap.add_argument("--write-doc", action="store_true", help=f"write the Markdown report to {DOC}")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    rows = run(args.cases.split(",") if args.cases else None, args.worlds, args.integrators.split(","),
               args.dtypes.split(","), args.device, args.steps, args.seed)  # fmt: skip
    gpu = args.device.startswith("cuda")
    argv = sys.argv[1:] if argv is None else list(argv)
    shown = [a for i, a in enumerate(argv) if a != "--out" and (i == 0 or argv[i - 1] != "--out")]  # not the JSON's
    result = dict(command=" ".join(["python -m abd_gym.bench robustness"] + shown), device=args.device,
                  device_name=wp.get_device(args.device).name if gpu else platform.processor() or platform.machine(),
                  date=datetime.date.today().isoformat(), warp=wp.config.version, worlds=args.worlds, seed=args.seed,
                  seconds=time.perf_counter() - t0, rows=rows)  # fmt: skip
    print()
    print(table(rows))
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "robustness.json"), "w") as f:
        json.dump(result, f, indent=1)
    for path in ([args.md] if args.md else []) + ([DOC] if args.write_doc else []):
        with open(path, "w") as f:
            f.write(document(result))
    return result
