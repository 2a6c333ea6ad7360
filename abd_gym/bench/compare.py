"""``python -m abd_gym.bench compare``: every mechanism of ``cases.CASES`` in abd_gym and in
MuJoCo Warp (optional: ``pip install mujoco mujoco-warp``), same device, same worlds, one process.

Speed: both step with dt = 0.01 from the case's random starts; MuJoCo Warp runs once per
``--mjw-integrators`` entry (Euler, its default, and RK4), replayed as a CUDA graph of 10 steps
(on the CPU it steps plainly); abd_gym replays its own captured step.  Each engine is timed
``--repeat`` times and keeps its fastest run.  Reports world-steps per second and the ratio
ours / MuJoCo Warp per integrator.

Accuracy, from a separate run of the first ``--accuracy-worlds`` worlds of the same batch over
1 s at the same dt, the largest value over every step and world whose state stayed finite:
joint residual [m] (ours: ``Simulator.joint_violation``; MuJoCo's tree joints hold exactly),
loop closure [m] (ours: the gap of the loop-closing joints' points; MuJoCo: the distance between
a ``connect``'s two anchors), limit penetration [rad or m] beyond any limited joint's range, and
the count of worlds whose state went non-finite (in that run or at the end of the timed one).
An engine with non-finite worlds is flagged (its speed is that of a diverged simulation) and no
ratio is given against it.
"""
import argparse
import json
import math
import os
import time

import numpy as np
import warp as wp

from .cases import CASES, connect_gap, mujoco_limit_penetration, ours_limit_penetration, with_integrator  # fmt: skip
from ..solver.plan import ExecutionPlan
from ..sim.simulator import Simulator
from ..solver.solver import SolverSettings

ACCURACY_DURATION = 1.0  # s


def random_states(case, n, seed=0):
    """Joint coordinates (n, joints) of ``case``'s random starts (cases.CASES)."""
    return CASES[case].states(n, seed)[0]


def _mjw_batch(case, num_worlds, dt, integrator):
    """(mujoco.MjModel, MuJoCo Warp model, data of ``num_worlds`` worlds at the case's random
    starts) on the current Warp device."""
    import mujoco
    import mujoco_warp as mjw

    c = CASES[case]
    mjm = mujoco.MjModel.from_xml_string(with_integrator(c.xml(dt), integrator))
    m = mjw.put_model(mjm)
    d = mjw.put_data(mjm, mujoco.MjData(mjm), nworld=num_worlds)
    q, qd = c.states(num_worlds, 0)
    d.qpos.assign(c.mujoco_qpos(q).astype(np.float32))
    d.qvel.assign(c.mujoco_qpos(qd).astype(np.float32))
    return mjm, m, d


def _nonfinite(*arrays):
    """(W,) bool: worlds with a non-finite entry in any of the arrays (leading axis: worlds)."""
    return np.any([~np.isfinite(a.reshape(len(a), -1)).all(axis=1) for a in arrays], axis=0)


def mjw_steps_per_second(case, num_worlds, steps, dt, device, repeat=1, integrator="Euler"):
    """MuJoCo Warp's world-steps/s: ``steps`` steps as 10-step CUDA graphs, best of ``repeat`` runs,
    and the count of worlds whose state is non-finite at the end."""
    import mujoco_warp as mjw

    with wp.ScopedDevice(device):
        mjm, m, d = _mjw_batch(case, num_worlds, dt, integrator)
        mjw.step(m, d)  # compile
        wp.synchronize()
        graph = None
        if wp.get_device(device).is_cuda:
            with wp.ScopedCapture() as capture:
                for _ in range(10):
                    mjw.step(m, d)
            graph = capture.graph
        reps = max(1, steps // 10)
        best = math.inf
        for _ in range(repeat):
            t0 = time.perf_counter()
            for _ in range(reps):
                if graph is not None:
                    wp.capture_launch(graph)
                else:
                    for _ in range(10):
                        mjw.step(m, d)
            wp.synchronize()
            best = min(best, time.perf_counter() - t0)
        return num_worlds * reps * 10 / best, int(_nonfinite(d.qpos.numpy(), d.qvel.numpy()).sum())


def mjw_accuracy(case, num_worlds, dt, device, integrator="Euler", duration=ACCURACY_DURATION):
    """MuJoCo Warp's accuracy over ``duration`` [s] (module docstring): dict of joint_residual,
    loop_closure [m] (NaN without a loop), limit_penetration, nonfinite."""
    import mujoco_warp as mjw

    with wp.ScopedDevice(device):
        mjm, m, d = _mjw_batch(case, num_worlds, dt, integrator)
        bad = np.zeros(num_worlds, dtype=bool)
        gap, pen = np.zeros(num_worlds), np.zeros(num_worlds)
        for _ in range(round(duration / dt)):
            mjw.step(m, d)
            qpos, xpos, xmat = d.qpos.numpy(), d.xpos.numpy(), d.xmat.numpy()
            bad |= _nonfinite(qpos, d.qvel.numpy(), xpos)
            with np.errstate(invalid="ignore"):
                gap = np.maximum(gap, np.where(bad, 0.0, connect_gap(mjm, xpos, xmat)))
                pen = np.maximum(pen, np.where(bad, 0.0, mujoco_limit_penetration(mjm, qpos)))
    loops = any(int(t) == 0 for t in mjm.eq_type)
    return dict(joint_residual=0.0, loop_closure=float(gap.max()) if loops else math.nan,
                limit_penetration=float(pen.max()), nonfinite=int(bad.sum()))  # fmt: skip


def scene_of(case, planar=None):
    """The case's scene, with Scene.planar set (None: a planar scene solved in its plane; False: 12
    unknowns a body)."""
    scene = CASES[case].scene()
    scene.planar = planar
    return scene


def ours_accuracy(case, num_worlds, dt, device, dtype="float32", duration=ACCURACY_DURATION, planar=None,
                  **sim_kwargs):  # fmt: skip
    """abd_gym's accuracy over ``duration`` [s] (module docstring), stepping one step at a time:
    dict of joint_residual, loop_closure [m] (NaN without a loop), limit_penetration, nonfinite."""
    c = CASES[case]
    sim = Simulator(scene_of(case, planar), num_worlds=num_worlds, dt=dt, device=device, dtype=dtype, **sim_kwargs)
    sim.set_joint_state(*c.states(num_worlds, 0))
    bad = np.zeros(num_worlds, dtype=bool)
    res, gap, pen = np.zeros(num_worlds), np.zeros(num_worlds), np.zeros(num_worlds)
    for _ in range(round(duration / dt)):
        sim.step(1)
        coords = sim.joint_coordinates()
        bad |= _nonfinite(sim.body_q(), coords)
        with np.errstate(invalid="ignore"):
            res = np.maximum(res, np.where(bad, 0.0, sim.joint_violation()))
            gap = np.maximum(gap, np.where(bad, 0.0, sim.joint_violation(c.loop_joints)))
            pen = np.maximum(pen, np.where(bad, 0.0, ours_limit_penetration(sim.scene, coords)))
    return dict(joint_residual=float(res.max()), loop_closure=float(gap.max()) if c.loop_joints else math.nan,
                limit_penetration=float(pen.max()), nonfinite=int(bad.sum()))  # fmt: skip


def fastest_run(sim, x0, steps: int, repeat: int, v0=None) -> float:
    """Seconds of the fastest of ``repeat`` runs of ``sim.step(steps)``, each restarted from the joint
    states ``x0`` (rates ``v0``, default 0) and timed between device synchronisations (a short run on
    a GPU varies with clocks and whatever ran before it)."""
    best = math.inf
    for _ in range(repeat):
        sim.set_joint_state(x0, v0)
        wp.synchronize_device(sim.device)
        t0 = time.perf_counter()
        sim.step(steps)
        wp.synchronize_device(sim.device)
        best = min(best, time.perf_counter() - t0)
    return best


def ours_steps_per_second(case, num_worlds, steps, dt, device, dtype="float32", repeat=1, planar=None, **sim_kwargs):
    """Throughput: ``steps`` steps launched back to back (a CUDA graph each on a GPU), one
    synchronisation at the end; the best of ``repeat`` such runs (each restarted from the same
    states: a short run on a GPU varies with clocks and whatever ran before it).
    Returns (world-steps/s, joint residual [m], bytes per world, the fused step's scratch layout,
    the count of worlds whose state is non-finite at the end, the unknowns a world)."""
    sim = Simulator(scene_of(case, planar), num_worlds=num_worlds, dt=dt, device=device, dtype=dtype, **sim_kwargs)
    x0, v0 = CASES[case].states(num_worlds, 0)
    sim.set_joint_state(x0, v0)
    sim.step(3)
    sps = num_worlds * steps / fastest_run(sim, x0, steps, repeat, v0)
    bad = int(_nonfinite(sim.body_q()).sum())
    with np.errstate(invalid="ignore"):
        residual = float(np.nanmax(sim.joint_violation()))
    return sps, residual, sim.memory_bytes()["total"] / num_worlds, sim.plan.scratch, bad, sim.model.num_dofs


METRICS = ("joint_residual", "loop_closure", "limit_penetration", "nonfinite")


def _accuracy(case, n, args, plan, integrator, planar=None):
    """{engine: accuracy dict} of the first n worlds: abd_gym and MuJoCo Warp per integrator (NaN
    without mujoco_warp)."""
    out = {"abd_gym": ours_accuracy(case, n, args.dt, args.device, plan=plan, planar=planar, **integrator)}
    for name in args.mjw_integrators:
        try:
            out[name] = mjw_accuracy(case, n, args.dt, args.device, integrator=name)
        except ImportError:
            out[name] = dict.fromkeys(METRICS, math.nan)
    return out


def _row(case, w, scratch, ours, theirs, acc, mem, acc_worlds, unknowns=None):
    """One result row: speeds, ratios (None against a diverged run), accuracy per engine."""
    ours_sps, residual, ours_bad = ours
    row = dict(case=case, num_worlds=w, scratch=scratch, unknowns=unknowns, abd_gym=ours_sps, joint_residual=residual,
               memory_bytes_per_world=mem, abd_gym_nonfinite=ours_bad + acc["abd_gym"]["nonfinite"],
               accuracy_worlds=acc_worlds)  # fmt: skip
    for k in METRICS[:3]:
        row[f"abd_gym_{k}"] = acc["abd_gym"][k]
    for name, (sps, bad) in theirs.items():
        key = f"mujoco_warp_{name.lower()}"
        a = acc.get(name, dict.fromkeys(METRICS, math.nan))
        nonfinite = bad + a["nonfinite"] if not math.isnan(a["nonfinite"]) else bad
        row[key] = sps
        for k in METRICS[:3]:
            row[f"{key}_{k}"] = a[k]
        row[f"{key}_nonfinite"] = nonfinite
        diverged = (nonfinite or 0) > 0 or row["abd_gym_nonfinite"] > 0
        row[f"ratio_{name.lower()}"] = None if diverged else ours_sps / sps
    first = next(iter(theirs), None)  # the first integrator's columns also under the plain names
    row["mujoco_warp"] = row[f"mujoco_warp_{first.lower()}"] if first else math.nan
    row["ratio"] = row[f"ratio_{first.lower()}"] if first else math.nan
    return row


def _num(x, fmt):
    return "—" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, fmt)


def table(result) -> str:
    """The Markdown table: one row per case × worlds × our step layout; per MuJoCo Warp integrator
    its speed (†: non-finite worlds, no ratio) and ratio; accuracy columns 'ours / Euler / RK4'."""
    names = result["mjw_integrators"]
    engines = "ours / " + " / ".join(names)
    head = ["mechanism", "worlds", "abd_gym step", "abd_gym world-steps/s"]
    for n in names:
        head += [f"MJW {n} world-steps/s", f"ratio vs {n}"]
    head += [f"joint residual [m] ({engines})", f"loop closure [m] ({engines})",
             f"limit penetration ({engines})", f"non-finite worlds ({engines})", "abd_gym memory [B/world]"]
    lines = [f"Device: {result['device_name']}, dt = {result['dt']}, abd_gym's {result['integrator']}; accuracy "
             f"over {ACCURACY_DURATION:g} s of the first {result['accuracy_worlds']} worlds; † a run whose state "
             "went non-finite (the speed of a diverged simulation; no ratio)", "",
             "| " + " | ".join(head) + " |", "|---|---:|---|" + "---:|" * (len(head) - 3)]  # fmt: skip
    for r in result["rows"]:
        flag = lambda bad: "†" if bad else ""  # noqa: E731
        ours = _num(r["abd_gym"], ",.0f") + flag(r["abd_gym_nonfinite"])
        step = r["scratch"] + (f", {r['unknowns']} unknowns" if r.get("unknowns") else "")
        cells = [r["case"], str(r["num_worlds"]), step, ours]
        for n in names:
            k = f"mujoco_warp_{n.lower()}"
            bad = r.get(f"{k}_nonfinite", math.nan)
            cells += [_num(r.get(k, math.nan), ",.0f") + flag(bad > 0), _num(r.get(f"ratio_{n.lower()}"), ".3f")]
        for metric, fmt in (("joint_residual", ".1e"), ("loop_closure", ".1e"), ("limit_penetration", ".1e"),
                            ("nonfinite", "d")):  # fmt: skip
            vals = [r[f"abd_gym_{metric}"]] + [r.get(f"mujoco_warp_{n.lower()}_{metric}", math.nan) for n in names]
            cells.append(" / ".join(_num(v, fmt) for v in vals))
        cells.append(_num(r["memory_bytes_per_world"], ",.0f"))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m abd_gym.bench compare", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--worlds", default=None)
    ap.add_argument("--steps", type=int, default=None)
    ap.add_argument("--dt", type=float, default=0.01)
    ap.add_argument("--ours-only", default=None, help="world counts run in abd_gym alone (default 1048576 on GPU)")
    ap.add_argument("--cases", default=",".join(CASES), help="cases.CASES names (default: all)")
    ap.add_argument("--scratch", default="auto", help="comma-separated layouts of our fused step: auto (the "
                    "simulator's default), global, shared, lanes (each timed against the same MuJoCo Warp run)")
    ap.add_argument("--planar", default="auto", help="comma-separated forms of our step: auto (a planar scene's 6 "
                    "unknowns a body, Scene.planar None), off (12 unknowns a body), each timed against the same "
                    "MuJoCo Warp run")
    ap.add_argument("--repeat", type=int, default=3, help="time each engine this many times and keep its fastest")
    ap.add_argument("--integrator", default=None, help="our integrator: bdf2 or implicit_euler (default: the "
                    "simulator's)")
    ap.add_argument("--mjw-integrators", default="Euler,RK4", help="MuJoCo Warp integrators, each timed and "
                    "measured (Euler, RK4, implicitfast)")
    ap.add_argument("--accuracy-worlds", type=int, default=256, help="worlds of the accuracy run (the first of the "
                    "batch; 0: none)")
    ap.add_argument("--out", default="bench_out")
    args = ap.parse_args(argv)
    args.mjw_integrators = [n for n in args.mjw_integrators.split(",") if n]
    gpu = args.device.startswith("cuda")
    worlds = [int(w) for w in args.worlds.split(",")] if args.worlds else ([1024, 16384, 131072] if gpu else [1, 8])
    alone = args.ours_only if args.ours_only is not None else ("1048576" if gpu else "")
    alone = [int(w) for w in alone.split(",") if w]
    steps = args.steps or (100 if gpu else 10)
    integrator = {} if args.integrator is None else {"integrator": args.integrator}
    rows = []
    for case in args.cases.split(","):
        accuracy = {}  # (worlds of the accuracy run, scratch) -> {engine: metrics}
        for w in worlds + alone:
            theirs = {}
            for name in args.mjw_integrators if w not in alone else []:
                try:
                    theirs[name] = mjw_steps_per_second(case, w, steps, args.dt, args.device, repeat=args.repeat,
                                                        integrator=name)  # fmt: skip
                except ImportError:
                    theirs[name] = (math.nan, math.nan)
            for scratch, form in ((k, f) for k in args.scratch.split(",") for f in args.planar.split(",")):
                plan = ExecutionPlan(scratch=None if scratch == "auto" else scratch)
                planar = {"auto": None, "off": False}[form]
                sps, residual, mem, layout, bad, unknowns = ours_steps_per_second(
                    case, w, steps, args.dt, args.device, repeat=args.repeat, plan=plan, planar=planar, **integrator)
                n = min(args.accuracy_worlds, w)
                if (n, scratch, form) not in accuracy:
                    accuracy[n, scratch, form] = _accuracy(case, n, args, plan, integrator, planar) if n else {
                        "abd_gym": dict.fromkeys(METRICS, math.nan)}  # fmt: skip
                acc = dict(accuracy[n, scratch, form])
                if math.isnan(acc["abd_gym"]["nonfinite"]):
                    acc["abd_gym"] = dict(acc["abd_gym"], nonfinite=0)
                if w in alone:  # no MuJoCo Warp run at this size
                    acc = {"abd_gym": acc["abd_gym"]}
                rows.append(_row(case, w, layout, (sps, residual, bad), theirs, acc, mem, n, unknowns))
                r = rows[-1]
                mjw = "  ".join(f"MJW {k} {v[0]:14,.0f}" for k, v in theirs.items())
                print(f"{case:28s} {w:8d} worlds  abd_gym ({layout}, {unknowns}) {sps:14,.0f}  {mjw} world-steps/s  residual "
                      f"{residual:.1e} m  non-finite {r['abd_gym_nonfinite']}  {mem:,.0f} B/world",
                      flush=True)  # fmt: skip
    result = dict(device=args.device, device_name=wp.get_device(args.device).name, dt=args.dt, steps=steps,
                  repeat=args.repeat, integrator=args.integrator or SolverSettings.integrator,
                  mjw_integrators=args.mjw_integrators, accuracy_worlds=args.accuracy_worlds, rows=rows)  # fmt: skip
    markdown = table(result)
    print(markdown)
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "compare.json"), "w") as f:
        json.dump(result, f, indent=1)
    with open(os.path.join(args.out, "compare.md"), "w") as f:
        f.write(markdown + "\n")
    return result
