"""``python -m abd_gym.bench accuracy``: speed against error, abd_gym beside MuJoCo's integrators.

Every mechanism of :data:`~abd_gym.bench.cases.CASES` (``--cases``) starts from the same random
joint coordinates and rates in every run and is stepped for 1 s at each dt (``--dts``, default
0.04 … 0.001 s).  Runs:

* abd_gym, each integrator (implicit Euler, BDF2), dtype (float32 default) and Newton tolerance:
  the trajectory on the bench device; world-steps/s from a separate run of the same batch
  (``bench compare``'s timing: steps launched back to back).
* MuJoCo, each integrator of ``--mj-integrators`` (Euler, implicitfast, RK4): the trajectory with
  MuJoCo C on the CPU (``mujoco.rollout``; the algorithms MuJoCo Warp runs), world-steps/s with
  MuJoCo Warp on the bench device at the same batch, replayed as CUDA graphs of 10 steps (NaN
  without ``mujoco_warp``).

Error: against MuJoCo's RK4 at ``--reference-dt`` (1e-4 s) from the same starts (our own float64
BDF2 run at that dt and tol 1e-8 without ``mujoco``), over the coordinates MuJoCo has a qpos for (a
joint that closes a loop is not compared), sampled every 0.02 s; ``error_max`` is the largest
over the second and the measured worlds of |angle − reference| over revolute joints [rad];
``error_max_slide`` the same over prismatic joints [m] (None without one); ``error_final`` the
revolute error at t = 1 s.  A run whose coordinates become non-finite, or that MuJoCo resets as
unstable, is ``diverged`` and has no error.  ``own_error_*``: the same against the engine's own
converged run (ours: float64 BDF2 at the reference dt; MuJoCo's: its RK4 reference), the
integration error alone; ``model_gap``: our converged run against MuJoCo's, the two models'
difference (on an inverted mechanism a small difference grows exponentially over the second).
``limited_reference_worlds``: where limits act the two limit models differ as well.

Equal error (:func:`equal_error_summary`): each setting is a curve of (error_max, simulated
world-seconds per second = world-steps/s × dt) over dt; at each error level (1e-3 … 1e-1 rad) the
fastest abd_gym setting and the fastest MuJoCo integrator that reach it are compared, once
against MuJoCo's reference (``summary``) and once each against its own (``summary_own``).  Writes
``accuracy.json`` (after every mechanism, so a run cut short keeps what it measured) and, with
matplotlib, ``accuracy.png`` (:func:`plot`: one panel per mechanism, each engine's error against
its own converged run) to --out.
"""
import argparse
import json
import math
import os
import time

import numpy as np
import warp as wp

from .compare import mjw_steps_per_second, ours_steps_per_second
from .cases import CASES, with_integrator
from ..sim.scene import PRISMATIC
from ..sim.simulator import Simulator

DTS = (0.04, 0.02, 0.01, 0.005, 0.002, 0.001)
MJ_INTEGRATORS = ("Euler", "implicitfast", "RK4")
LEVELS = (1e-3, 3e-3, 1e-2, 3e-2, 1e-1)  # error levels of the equal-error summary [rad]
T_END, SAMPLE = 1.0, 0.02


def _samples(dt):
    """(steps between samples, steps in 1 s): a sample every 0.02 s, or every step when dt is larger."""
    every = max(1, int(round(SAMPLE / dt)))
    return every, int(round(T_END / dt))


def measured_joints(case):
    """abd_gym joint indices that MuJoCo has a qpos for (the order of ``ours_from_qpos``)."""
    return [j for j, a in enumerate(CASES[case].qpos_of_joint) if a is not None]


def slide_mask(case):
    """Per measured joint: True for a prismatic joint (error in m), False for a revolute one [rad]."""
    joints = CASES[case].scene().joints
    return np.array([joints[j].kind == PRISMATIC for j in measured_joints(case)], dtype=bool)


def _mujoco_starts(mjm, case, q0, v0):
    """(an MjData of ``mjm``, each world's full physics state (worlds, nstate)) at joint
    coordinates q0 and rates v0 (worlds, num_joints) in abd_gym's joint order: the initial states
    ``mujoco.rollout`` takes."""
    import mujoco

    c = CASES[case]
    mjd = mujoco.MjData(mjm)
    qpos, qvel = c.mujoco_qpos(q0), c.mujoco_qpos(v0)
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    x0 = np.empty((len(q0), mujoco.mj_stateSize(mjm, spec)))
    for w in range(len(q0)):
        mujoco.mj_resetData(mjm, mjd)
        mjd.qpos[:], mjd.qvel[:] = qpos[w], qvel[w]
        mujoco.mj_getState(mjm, mjd, x0[w], spec)
    return mjd, x0


def mujoco_run(case, q0, v0, dt, integrator="RK4"):
    """MuJoCo C's coordinates (samples, worlds, measured joints) [rad, m] every 0.02 s over 1 s with
    ``integrator`` at step dt [s], from joint coordinates q0 and rates v0 (worlds, num_joints) in
    abd_gym's joint order; and whether MuJoCo reset a world as unstable (its time restarts)."""
    import mujoco
    from mujoco import rollout

    c = CASES[case]
    mjm = mujoco.MjModel.from_xml_string(with_integrator(c.xml(dt), integrator))
    mjd, x0 = _mujoco_starts(mjm, case, q0, v0)
    qpos = c.mujoco_qpos(q0)
    every, n = _samples(dt)
    state, _ = rollout.rollout(mjm, mjd, x0, nstep=n)  # (worlds, steps, nstate): time, qpos, qvel, ...
    reset = not np.allclose(state[:, -1, 0], n * dt, rtol=1e-6)
    qs = np.concatenate([qpos[:, None], state[:, every - 1 :: every, 1 : 1 + mjm.nq]], 1)
    return np.stack([c.ours_from_qpos(s) for s in qs.transpose(1, 0, 2)]), reset


def limited_worlds(case, dt=1e-3):
    """The fraction of the reference worlds (random starts, seed 1) in which MuJoCo's RK4 run at
    step dt [s] takes a limited joint past its range within the second.  Where a limit acts, the
    two engines' limit models differ (abd_gym's cubic barrier, MuJoCo's soft constraint), and the
    error against MuJoCo's reference holds that difference, not only the integration error."""
    import mujoco
    from mujoco import rollout

    c = CASES[case]
    mjm = mujoco.MjModel.from_xml_string(with_integrator(c.xml(dt), "RK4"))
    limited = [j for j in range(mjm.njnt) if mjm.jnt_limited[j]]
    if not limited:
        return 0.0
    mjd, x0 = _mujoco_starts(mjm, case, *c.states(8, 1))
    state, _ = rollout.rollout(mjm, mjd, x0, nstep=int(round(T_END / dt)))
    out = np.zeros(len(x0), bool)
    for j in limited:
        q = state[:, :, 1 + mjm.jnt_qposadr[j]]
        lo, hi = mjm.jnt_range[j]
        out |= ((q < lo) | (q > hi)).any(axis=1)
    return float(out.mean())


def run_ours(case, q0, v0, dt, dtype, tol, device, integrator="implicit_euler", reuse_factor=False, **options):
    """Measured joints' coordinates (samples, worlds, measured joints) [rad, m] over 1 s from joint
    coordinates q0 and rates v0, the largest joint residual [m], the largest energy drift
    E(1 s) − E(0) [J] and whether Newton reused its factors (``options``: more Simulator settings)."""
    sim = Simulator(CASES[case].scene(), num_worlds=len(q0), dt=dt, device=device, dtype=dtype, tol=tol,
                    integrator=integrator, reuse_factor=reuse_factor, **options)  # fmt: skip
    sim.set_joint_state(q0, v0)
    cols = measured_joints(case)
    e0 = sum(sim.energies().values())
    every, n = _samples(dt)
    out = np.zeros((n // every + 1, len(q0), len(cols)))
    out[0] = sim.joint_angles_unwrapped()[:, cols]
    residual = 0.0
    failed = np.zeros(len(q0), bool)
    for i in range(1, n + 1):
        sim.step()
        if i % every == 0:
            # a world whose step failed keeps its last state and is no longer stepped: its
            # trajectory ends there (NaN, so the run counts as diverged), not frozen into an error
            failed |= sim.world_status() != 0
            out[i // every] = np.where(failed[:, None], np.nan, sim.joint_angles_unwrapped()[:, cols])
            residual = max(residual, float(sim.joint_violation().max()))
    drift = float(np.max(sum(sim.energies().values()) - e0))
    return out, residual, drift, sim.solver.reuse_factor


def errors(traj, ref, slide, diverged=False):
    """error_final, error_max [rad] over revolute coordinates and error_max_slide [m] over
    prismatic ones of a trajectory (samples, worlds, measured joints) against the reference
    (sampled every 0.02 s); all None when it diverged (or is not finite)."""
    if diverged or not np.all(np.isfinite(traj)):
        return dict(diverged=True, error_final=None, error_max=None, error_max_slide=None)
    ref = ref[:: (len(ref) - 1) // (len(traj) - 1)]  # the reference's samples at the run's (dt > 0.02 s)
    good = np.isfinite(ref).all(axis=(0, 2))  # worlds where the reference run itself failed are left out
    err = np.abs(traj[:, : ref.shape[1]] - ref)[:, good]
    rot, lin = err[..., ~slide], err[..., slide]
    return dict(diverged=False, error_final=float(rot[-1].max()) if rot.size else None,
                error_max=float(rot.max()) if rot.size else None,
                error_max_slide=float(lin.max()) if lin.size else None)  # fmt: skip


def _own(errs):
    """errors() against an engine's own converged run, under ``own_`` keys."""
    return {f"own_{k}": v for k, v in errs.items() if k != "diverged"}


def _ours_rows(case, q0, v0, ref, ref_own, dt, settings, device, repeat):
    """One row per abd_gym setting (integrator, dtype, tol, reuse_factor) at step dt [s]: its
    errors against MuJoCo's reference ``ref`` and against our own converged run ``ref_own``, and
    world-steps/s at the batch of q0."""
    slide, steps = slide_mask(case), _samples(dt)[1]
    for integrator, dtype, tol, reuse in settings:
        traj, residual, drift, reused = run_ours(case, q0, v0, dt, dtype, tol, device, integrator, reuse)
        sps = ours_steps_per_second(case, len(q0), steps, dt, device, dtype, repeat=repeat, tol=tol,
                                    integrator=integrator, reuse_factor=reuse)[0]  # fmt: skip
        yield dict(engine="abd_gym", integrator=integrator, case=case, dt=dt, dtype=dtype, tol=tol,
                   reuse_factor=reused, **errors(traj, ref, slide), **_own(errors(traj, ref_own, slide)),
                   joint_residual=residual, energy_drift=drift, world_steps_per_second=sps)  # fmt: skip


def _mujoco_row(case, q0, v0, ref, dt, integrator, device, repeat):
    """MuJoCo's ``integrator`` at step dt [s]: errors of MuJoCo C on the reference worlds (and the
    seconds that took), world-steps/s of MuJoCo Warp at the batch of q0 (NaN, with ``speed_note``,
    without mujoco_warp or without this integrator in it)."""
    t0 = time.perf_counter()
    traj, reset = mujoco_run(case, q0[: len(ref[0])], v0[: len(ref[0])], dt, integrator)
    seconds = time.perf_counter() - t0
    speed_note = None
    try:
        sps = mjw_steps_per_second(case, len(q0), _samples(dt)[1], dt, device, repeat, integrator)[0]
    except (ImportError, NotImplementedError) as e:
        sps, speed_note = float("nan"), f"{type(e).__name__}: {e}"
    errs = errors(traj, ref, slide_mask(case), reset)
    return dict(engine="mujoco_warp", integrator=integrator, case=case, dt=dt, dtype="float32", tol=None,
                reuse_factor=None, **errs, **_own(errs), error_from="mujoco C (float64, CPU)",
                mujoco_c_seconds=seconds, speed_note=speed_note, joint_residual=0.0, energy_drift=None,
                world_steps_per_second=sps)  # fmt: skip


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m abd_gym.bench accuracy", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--worlds", type=int, default=None, help="worlds per timed run (default 8 on CPU, 16384 on GPU)")
    ap.add_argument("--dts", default=",".join(str(d) for d in DTS))
    ap.add_argument("--dtypes", default="float32", help="comma-separated float32/float64 (ours)")
    ap.add_argument("--tols", default="1e-5,1e-3")
    ap.add_argument("--integrators", default="implicit_euler,bdf2", help="ours")
    ap.add_argument("--mj-integrators", default=",".join(MJ_INTEGRATORS), help="MuJoCo's (Euler, implicitfast, RK4)")
    ap.add_argument("--reuse-factors", default="0", help="comma-separated 0/1 (Simulator reuse_factor)")
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--reference-worlds", type=int, default=8, help="worlds the error is measured on")
    ap.add_argument("--reference-dt", type=float, default=1e-4, help="step of the reference run [s]")
    ap.add_argument("--repeat", type=int, default=3, help="throughput: best of this many timed runs")
    ap.add_argument("--out", default="bench_out")
    args = ap.parse_args(argv)
    W = args.worlds or (16384 if args.device.startswith("cuda") else 8)
    dts = [float(d) for d in args.dts.split(",")]
    reuse_choice = {"0": False, "1": True}
    settings = [(i, d, float(t), reuse_choice[r]) for i in args.integrators.split(",")
                for d in args.dtypes.split(",") for t in args.tols.split(",") for r in args.reuse_factors.split(",")]
    rows, references, reference_seconds, limits, gaps = [], {}, {}, {}, {}
    for case in args.cases.split(","):
        q0, v0 = CASES[case].states(W, 1)
        nref = min(args.reference_worlds, W)
        t0 = time.perf_counter()
        try:
            ref, reset = mujoco_run(case, q0[:nref], v0[:nref], args.reference_dt)
            references[case] = f"mujoco_rk4_dt{args.reference_dt:g}" + (" (reset as unstable)" if reset else "")
            reference_seconds[case] = time.perf_counter() - t0
            limits[case] = limited_worlds(case)
        except ImportError:
            ref = None
            references[case] = f"abd_gym_float64_bdf2_dt{args.reference_dt:g}"
        # tol 1e-8 m/s: at dt 1e-4 a tighter one is below what float64 resolves in some worlds
        ref_own = run_ours(case, q0[:nref], v0[:nref], args.reference_dt, "float64", 1e-8, args.device, "bdf2")[0]
        ref = ref_own if ref is None else ref
        gaps[case] = errors(ref_own, ref, slide_mask(case), not np.isfinite(ref_own).all())
        if gaps[case]["diverged"]:
            print(f"{case}: our converged run failed in {int((~np.isfinite(ref_own).all(axis=(0, 2))).sum())} of {nref} "
                  "worlds, left out of the errors against it", flush=True)  # fmt: skip
        print(f"{case}: our converged run (float64 BDF2, dt {args.reference_dt:g}) against the reference: "
              f"{_num(gaps[case]['error_max'])} rad, {_num(gaps[case]['error_max_slide'])} m", flush=True)
        mj_integrators = args.mj_integrators.split(",") if case in reference_seconds else []
        for dt in dts:
            for row in _ours_rows(case, q0, v0, ref, ref_own, dt, settings, args.device, args.repeat):
                rows.append(row)
                print(_fmt(row), flush=True)
            for integrator in mj_integrators:
                rows.append(_mujoco_row(case, q0, v0, ref, dt, integrator, args.device, args.repeat))
                print(_fmt(rows[-1]), flush=True)
        # written after every mechanism, so a run cut short keeps what it measured
        result = _result(args, W, references, reference_seconds, limits, gaps, rows, complete=False)
    result = _result(args, W, references, reference_seconds, limits, gaps, rows, complete=True)
    print(rows_table(rows))
    print()
    print(summary_table(result["summary"], limits))
    print()
    print("Against each engine's own converged run (integration error only):")
    print(summary_table(result["summary_own"], limits))
    plot(result, os.path.join(args.out, "accuracy.png"))
    return result


def _result(args, W, references, reference_seconds, limits, gaps, rows, complete):
    """The run's result so far, written to --out/accuracy.json (``complete``: every mechanism done)."""
    for r in rows:
        r["world_seconds_per_second"] = r["world_steps_per_second"] * r["dt"]
    result = dict(device=args.device, device_name=wp.get_device(args.device).name, worlds=W,
                  reference_worlds=min(args.reference_worlds, W), reference=references,
                  reference_seconds=reference_seconds, limited_reference_worlds=limits, model_gap=gaps,
                  complete=complete, rows=rows, summary=equal_error_summary(rows),
                  summary_own=equal_error_summary(rows, key="own_error_max"))  # fmt: skip
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "accuracy.json"), "w") as f:
        json.dump(result, f, indent=1)
    return result


def _setting(r):
    """A curve's name: MuJoCo's integrator, or our integrator, dtype, tolerance and factor reuse."""
    if r["engine"] != "abd_gym":
        return r["integrator"]
    return f"{r['integrator']} {r['dtype']} tol {r['tol']:g}" + (" reuse" if r["reuse_factor"] else "")


def curves(rows, case, engine, timed=True, key="error_max"):
    """Per setting of ``engine`` on ``case``: its measured (error [rad] under ``key``, world-seconds/s)
    points, sorted by error; diverged runs left out, and untimed (NaN) rates unless ``timed`` is False."""
    out = {}
    for r in rows:
        if r["case"] == case and r["engine"] == engine and r.get(key) is not None:
            rate = r["world_steps_per_second"] * r["dt"]
            if not timed or (math.isfinite(rate) and rate > 0):
                out.setdefault(_setting(r), []).append((r[key], rate))
    return {k: sorted(v) for k, v in out.items()}


def rate_at(points, level):
    """Simulated world-seconds/s of a curve at error ``level`` [rad]: (rate, bound), or None when
    every measured point errs more than ``level`` (not reached: no extrapolation).

    Inside the measured error range the rate is interpolated log-log between neighbouring points
    (or a faster measured point with a smaller error, when the curve is not monotonic), bound "=";
    when every point errs less than ``level`` the fastest point is taken, bound ">=" (a larger dt,
    not measured, may reach ``level`` faster)."""
    errs = np.array([p[0] for p in points])
    rates = np.array([p[1] for p in points])
    if not len(points) or level < errs.min():
        return None
    below = float(rates[errs <= level].max())
    if level > errs.max():
        return below, ">="
    return max(below, float(np.exp(np.interp(np.log(level), np.log(errs), np.log(rates))))), "="


def _best(curves_, level):
    """(setting, rate, bound) of the fastest curve at ``level``, or None when none reaches it."""
    got = [(name, *at) for name, pts in curves_.items() if (at := rate_at(pts, level)) is not None]
    return max(got, key=lambda g: g[1]) if got else None


def _smallest(curves_):
    """The smallest error [rad] over all curves' points, or None without points."""
    errs = [p[0] for pts in curves_.values() for p in pts]
    return min(errs) if errs else None


def _missing(engine, untimed, level):
    """Why ``engine`` has no rate at ``level``: not timed, or its smallest error is larger."""
    smallest = _smallest(untimed)
    if smallest is None:
        return f"{engine} has no finite run"
    if smallest <= level:
        return f"{engine} reaches this error but was not timed"
    return f"{engine} does not reach this error: its smallest is {smallest:.1e} rad"


def _verdict(ours, theirs, why_ours, why_theirs):
    """Who is ahead at one error level, plainly, from the two best (setting, rate, bound)."""
    if ours is None and theirs is None:
        return f"neither ({why_ours}; {why_theirs})"
    if ours is None:
        return f"MuJoCo Warp ({why_ours})"
    if theirs is None:
        return f"abd_gym ({why_theirs})" if "not timed" not in why_theirs else f"undecided ({why_theirs})"
    ratio = ours[1] / theirs[1]
    if ratio >= 1 and theirs[2] == "=":
        return "abd_gym"
    if ratio < 1 and ours[2] == "=":
        return "MuJoCo Warp"
    slower = "MuJoCo" if ratio >= 1 else "abd_gym"
    return f"undecided ({slower}'s rate is a lower bound: its largest dt errs less; measure a larger dt)"


def equal_error_summary(rows, levels=LEVELS, key="error_max"):
    """Per mechanism and error level [rad]: the fastest abd_gym setting and the fastest MuJoCo
    integrator (simulated world-seconds per second at that error, :func:`rate_at`), their ratio
    ours / MuJoCo's and who is ahead.  ``key``: "error_max" (both against MuJoCo's reference) or
    "own_error_max" (each against its own converged run: the integration error alone)."""
    out = []
    for case in dict.fromkeys(r["case"] for r in rows):
        ours_c, theirs_c = curves(rows, case, "abd_gym", key=key), curves(rows, case, "mujoco_warp", key=key)
        ours_all = curves(rows, case, "abd_gym", False, key)
        theirs_all = curves(rows, case, "mujoco_warp", False, key)
        for level in levels:
            ours, theirs = _best(ours_c, level), _best(theirs_c, level)
            why = _missing("abd_gym", ours_all, level), _missing("MuJoCo", theirs_all, level)
            out.append(dict(case=case, error=level,
                            abd_gym=None if ours is None else dict(setting=ours[0], world_seconds_per_second=ours[1], bound=ours[2]),
                            mujoco_warp=None if theirs is None else dict(integrator=theirs[0], world_seconds_per_second=theirs[1], bound=theirs[2]),
                            ratio=None if ours is None or theirs is None else ours[1] / theirs[1],
                            ahead=_verdict(ours, theirs, *why)))  # fmt: skip
    return out


def _side(s, name):
    if s is None:
        return "not reached"
    return f"{'≥ ' if s['bound'] == '>=' else ''}{s['world_seconds_per_second']:,.0f} ({s[name]})"


def summary_table(summary, limits=None):
    """Markdown: mechanism × error level, both sides' best and who is ahead; ``limits`` ({case:
    fraction of reference worlds that reach a limit}, :func:`limited_worlds`) marks the mechanisms
    whose errors hold the two limit models' difference."""
    limits = limits or {}
    lines = ["| mechanism | error [rad] | abd_gym best world-s/s (setting) | MuJoCo Warp best world-s/s (integrator) "
             "| ratio | ahead |", "|---|---:|---:|---:|---:|---|"]  # fmt: skip
    for s in summary:
        ratio = "" if s["ratio"] is None else f"{s['ratio']:.2f}"
        mark = " (limits act)" if limits.get(s["case"], 0) > 0 else ""
        lines.append(f"| {s['case']}{mark} | {s['error']:g} | {_side(s['abd_gym'], 'setting')} | "
                     f"{_side(s['mujoco_warp'], 'integrator')} | {ratio} | {s['ahead']} |")  # fmt: skip
    return "\n".join(lines)


def rows_table(rows):
    """Markdown: every run's error and speed."""
    lines = ["| mechanism | engine | setting | dt [s] | max error [rad] | max slide error [m] | world-steps/s "
             "| world-s/s |", "|---|---|---|---:|---:|---:|---:|---:|"]  # fmt: skip
    for r in rows:
        err = "diverged" if r["diverged"] else _num(r["error_max"])
        lines.append(f"| {r['case']} | {r['engine']} | {_setting(r)} | {r['dt']:g} | {err} | {_num(r['error_max_slide'])} "
                     f"| {r['world_steps_per_second']:,.0f} | {r['world_seconds_per_second']:,.0f} |")  # fmt: skip
    return "\n".join(lines)


def _num(x):
    return "—" if x is None else f"{x:.2e}"


def _fmt(r):
    drift = "" if r["energy_drift"] is None else f"  drift {r['energy_drift']:+.2e} J"
    err = ("diverged" if r["diverged"] else
           f"err(1s) {_num(r['error_final'])}  err(max) {_num(r['error_max'])} rad  slide {_num(r['error_max_slide'])} m")
    return (f"{r['engine']:11s} {_setting(r):38s} {r['case']:16s} dt {r['dt']:<6} {err}  "
            f"residual {r['joint_residual']:.1e}{drift}  {r['world_steps_per_second']:,.0f} world-steps/s")  # fmt: skip


def plot(result, path, key="own_error_max", title=None):
    """One log-log panel per mechanism of ``result`` (an ``accuracy.json``): each setting of each
    engine as a curve of (simulated world-seconds per wall second, error ``key`` [rad]) over dt,
    with :data:`LEVELS` as grey lines.  ``key``: ``own_error_max`` (each engine against its own
    converged run, the integration error alone) or ``error_max`` (against the common reference).
    ``title``: the device and batch of the rates (default: the result's).  Written to ``path``;
    False (nothing written) without matplotlib."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return False
    if title is None:
        title = f"{result['device_name']}, {result['worlds']} worlds"
    cases = list(dict.fromkeys(r["case"] for r in result["rows"]))
    ncol = min(3, len(cases))
    nrow = -(-len(cases) // ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(6 * ncol, 4.5 * nrow), squeeze=False)
    for ax in axes.flat[len(cases):]:
        ax.set_visible(False)
    against = "its own converged run" if key.startswith("own_") else "the reference"
    for ax, case in zip(axes.flat, cases):
        for engine, style in (("abd_gym", "o-"), ("mujoco_warp", "s--")):
            for name, pts in curves(result["rows"], case, engine, key=key).items():
                pts = sorted(pts, key=lambda p: p[1])  # along the rate axis (≈ dt order)
                ax.loglog([p[1] for p in pts], [p[0] for p in pts], style, label=f"{engine} {name}")
        for level in LEVELS:
            ax.axhline(level, color="grey", lw=0.5, alpha=0.5)
        ax.set_xlabel("simulated world-seconds per wall second (world-steps/s × dt)")
        ax.set_ylabel(f"max revolute-joint error over 1 s [rad]\nagainst {against}")
        ax.set_title(f"{case} ({title})")
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=6)
        ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return True
