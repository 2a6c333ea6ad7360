"""``python -m abd_gym.bench accuracy``: speed against error.

For dt in {0.02, 0.01, 0.005, 0.002, 0.001}, each integrator (implicit Euler, BDF2), float32 and
float64, and two Newton tolerances, a
batch of double pendulums and cart-poles (random initial angles, the same in every run) is
stepped for 1 s.  Reported per run: the joint-angle error against a reference (MuJoCo's RK4 at
dt = 1e-4 when ``mujoco`` is installed, else our own float64 run at dt = 1e-4 and tol 1e-10),
at t = 1 s and the largest over the second (sampled every 0.02 s); the largest joint residual;
the energy drift E(1 s) − E(0) [J] (implicit Euler only loses energy); and world-steps per
second, the throughput of a separate run of the same batch (1 s of steps launched back to back,
as ``bench compare`` times them; the trajectory run reads the angles back every 0.02 s).  With
``mujoco_warp`` installed its semi-implicit Euler is measured the same way.  ``--reuse-factors``
adds the Newton factor-reuse setting as a dimension (default: each dtype's default).
With MuJoCo Warp rows, the run ends with the comparison at equal error (:func:`equal_error`):
simulated world-seconds per second (world-steps/s × dt) of each of our settings against MuJoCo
Warp's at the same error.  Writes ``accuracy.json`` and, with matplotlib, ``accuracy.png`` (error
against simulated world-seconds per second) to --out.
"""
import argparse
import json
import os

import numpy as np
import warp as wp

from .bench_compare import mjw_steps_per_second, ours_steps_per_second, random_states
from .peer_cases import CASES, with_integrator
from .simulator import Simulator

DTS = (0.02, 0.01, 0.005, 0.002, 0.001)
T_END, SAMPLE = 1.0, 0.02


def _samples(dt):
    every = int(round(SAMPLE / dt))
    return every, int(round(T_END / dt))


def mujoco_reference(case, x0, v0=None, dt=1e-4, integrator="RK4"):
    """Joint angles (samples, worlds, joints) of MuJoCo's RK4 from x0 (worlds, joints)."""
    import mujoco

    xml = with_integrator(CASES[case].xml(dt), integrator)
    mjm = mujoco.MjModel.from_xml_string(xml)
    mjd = mujoco.MjData(mjm)
    every, n = _samples(dt)
    out = np.zeros((n // every + 1, len(x0), mjm.nq))
    for w, x in enumerate(x0):
        mujoco.mj_resetData(mjm, mjd)
        mjd.qpos[:] = x
        out[0, w] = mjd.qpos
        for i in range(1, n + 1):
            mujoco.mj_step(mjm, mjd)
            if i % every == 0:
                out[i // every, w] = mjd.qpos
    return out


def run_ours(case, x0, dt, dtype, tol, device, integrator="implicit_euler", reuse_factor=None, **options):
    """Joint angles (samples, worlds, joints) over 1 s from x0, the largest joint residual [m], the
    largest energy drift [J] and whether Newton reused its factors (``options``: more Simulator
    settings)."""
    sim = Simulator(CASES[case].scene(), num_worlds=len(x0), dt=dt, device=device, dtype=dtype, tol=tol,
                    integrator=integrator, reuse_factor=reuse_factor, **options)  # fmt: skip
    sim.set_joint_state(x0)
    e0 = sum(sim.energies().values())
    every, n = _samples(dt)
    out = np.zeros((n // every + 1,) + x0.shape)
    out[0] = sim.joint_angles_unwrapped()
    residual = 0.0
    for i in range(1, n + 1):
        sim.step()
        if i % every == 0:
            out[i // every] = sim.joint_angles_unwrapped()
            residual = max(residual, float(sim.joint_violation().max()))
    drift = float(np.max(sum(sim.energies().values()) - e0))
    return out, residual, drift, sim.solver.reuse_factor


def run_mjw(case, x0, dt, device):
    """MuJoCo Warp's joint angles (samples, worlds, joints) over 1 s from x0."""
    import mujoco
    import mujoco_warp as mjw

    mjm = mujoco.MjModel.from_xml_string(CASES[case].xml(dt))
    every, n = _samples(dt)
    out = np.zeros((n // every + 1,) + x0.shape)
    with wp.ScopedDevice(device):
        m = mjw.put_model(mjm)
        d = mjw.put_data(mjm, mujoco.MjData(mjm), nworld=len(x0))
        d.qpos.assign(x0.astype(np.float32))
        out[0] = x0
        for i in range(1, n + 1):
            mjw.step(m, d)
            if i % every == 0:
                out[i // every] = d.qpos.numpy()
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m abd_gym.bench accuracy", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--worlds", type=int, default=None, help="worlds per run (default 8 on CPU, 4096 on GPU)")
    ap.add_argument("--dts", default=",".join(str(d) for d in DTS))
    ap.add_argument("--dtypes", default="float32,float64")
    ap.add_argument("--tols", default="1e-5,1e-3")
    ap.add_argument("--integrators", default="implicit_euler,bdf2")
    ap.add_argument("--reuse-factors", default="auto", help="comma-separated auto/0/1 (Simulator reuse_factor)")
    ap.add_argument("--cases", default="double_pendulum,cartpole")
    ap.add_argument("--reference-worlds", type=int, default=8, help="worlds the error is measured on")
    ap.add_argument("--reference-dt", type=float, default=1e-4, help="step of the reference run [s]")
    ap.add_argument("--repeat", type=int, default=3, help="throughput: best of this many timed runs")
    ap.add_argument("--out", default="bench_out")
    args = ap.parse_args(argv)
    W = args.worlds or (4096 if args.device.startswith("cuda") else 8)
    dts = [float(d) for d in args.dts.split(",")]
    rows = []
    for case in args.cases.split(","):
        x0 = random_states(case, W, seed=1)
        nref = min(args.reference_worlds, W)
        try:
            ref, ref_name = mujoco_reference(case, x0[:nref], dt=args.reference_dt), f"mujoco_rk4_dt{args.reference_dt:g}"
        except ImportError:
            ref = run_ours(case, x0[:nref], args.reference_dt, "float64", 1e-10, "cpu")[0]
            ref_name = f"abd_gym_float64_dt{args.reference_dt:g}"
        reuse_choice = {"auto": None, "0": False, "1": True}
        settings = [(i, d, float(t), reuse_choice[r]) for i in args.integrators.split(",")
                    for d in args.dtypes.split(",") for t in args.tols.split(",") for r in args.reuse_factors.split(",")]
        for dt in dts:
            steps = _samples(dt)[1]
            for integrator, dtype, tol, reuse in settings:
                traj, residual, drift, reused = run_ours(case, x0, dt, dtype, tol, args.device, integrator, reuse)
                sps = ours_steps_per_second(case, W, steps, dt, args.device, dtype, repeat=args.repeat, tol=tol,
                                            integrator=integrator, reuse_factor=reuse)[0]  # fmt: skip
                err = np.abs(traj[:, :nref] - ref)
                rows.append(dict(engine="abd_gym", integrator=integrator, case=case, dt=dt, dtype=dtype,
                                 tol=tol, reuse_factor=reused, error_final=float(err[-1].max()),
                                 error_max=float(err.max()), joint_residual=residual, energy_drift=drift,
                                 world_steps_per_second=sps))  # fmt: skip
                print(_fmt(rows[-1]), flush=True)
            try:
                traj = run_mjw(case, x0, dt, args.device)
                sps = mjw_steps_per_second(case, W, steps, dt, args.device, repeat=args.repeat)[0]
                err = np.abs(traj[:, :nref] - ref)
                rows.append(dict(engine="mujoco_warp", integrator="semi_implicit_euler", case=case, dt=dt,
                                 dtype="float32", tol=None, reuse_factor=None, error_final=float(err[-1].max()), error_max=float(err.max()),
                                 joint_residual=0.0, energy_drift=None, world_steps_per_second=sps))  # fmt: skip
                print(_fmt(rows[-1]), flush=True)
            except ImportError:
                pass
    for r in rows:
        r["world_seconds_per_second"] = r["world_steps_per_second"] * r["dt"]
    result = dict(device=args.device, device_name=wp.get_device(args.device).name, worlds=W, reference=ref_name,
                  rows=rows, equal_error=equal_error(rows))  # fmt: skip
    if result["equal_error"]:
        print(equal_error_table(result["equal_error"]))
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "accuracy.json"), "w") as f:
        json.dump(result, f, indent=1)
    _plot(result, os.path.join(args.out, "accuracy.png"))
    return result


def equal_error(rows):
    """Per abd_gym row: MuJoCo Warp's simulated world-seconds per second at the same error
    (``error_max``), and our rate over it.

    The rate that matters at equal error is simulated time per wall time, world-steps/s × dt: a
    more accurate step lets a larger dt reach the same error.  MuJoCo Warp's rate at our error is
    interpolated log-log between its two nearest dt points; below its smallest error it is
    extrapolated as first order (error ∝ dt ∝ its rate at a fixed world-steps/s), and
    ``extrapolated`` says so; above its largest error its largest-dt point is used (``beyond``:
    the ratio then overstates ours, as MuJoCo Warp could take a larger step).  Empty without
    MuJoCo Warp rows."""
    out = []
    for case in sorted({r["case"] for r in rows}):
        mjw = sorted((r["error_max"], r["world_steps_per_second"] * r["dt"]) for r in rows
                     if r["case"] == case and r["engine"] == "mujoco_warp")  # fmt: skip
        if not mjw:
            continue
        errs, rates = np.log([m[0] for m in mjw]), np.log([m[1] for m in mjw])
        for r in rows:
            if r["case"] != case or r["engine"] != "abd_gym":
                continue
            e = r["error_max"]
            note = ""
            if e < mjw[0][0]:
                rate, note = mjw[0][1] * e / mjw[0][0], "extrapolated"
            elif e > mjw[-1][0]:
                rate, note = mjw[-1][1], "beyond"
            else:
                rate = float(np.exp(np.interp(np.log(e), errs, rates)))
            ours = r["world_steps_per_second"] * r["dt"]
            out.append(dict(case=case, integrator=r["integrator"], dt=r["dt"], dtype=r["dtype"], tol=r["tol"],
                            reuse_factor=r["reuse_factor"], error_max=e, world_seconds_per_second=ours,
                            mujoco_warp_world_seconds_per_second=rate, ratio=ours / rate, note=note))  # fmt: skip
    return out


def equal_error_table(rows):
    lines = ["| mechanism | integrator | dt [s] | dtype | reuse | max error [rad] | abd_gym world-s/s | "
             "MuJoCo Warp world-s/s at that error | ratio |", "|---|---|---:|---|---|---:|---:|---:|---:|"]
    for r in rows:
        note = f" ({r['note']})" if r["note"] else ""
        lines.append(f"| {r['case']} | {r['integrator']} | {r['dt']:g} | {r['dtype']} | {'yes' if r['reuse_factor'] else 'no'} | "
                     f"{r['error_max']:.2e} | {r['world_seconds_per_second']:,.0f} | "
                     f"{r['mujoco_warp_world_seconds_per_second']:,.0f}{note} | {r['ratio']:.2f} |")  # fmt: skip
    return "\n".join(lines)


def _fmt(r):
    drift = "" if r["energy_drift"] is None else f"  drift {r['energy_drift']:+.2e} J"
    reuse = " reuse" if r.get("reuse_factor") else ""
    return (f"{r['engine']:11s} {r['integrator']:19s} {r['case']:16s} dt {r['dt']:<6} {r['dtype']:8s} tol {str(r['tol']):6s}{reuse} "
            f"err(1s) {r['error_final']:.2e}  err(max) {r['error_max']:.2e}  residual {r['joint_residual']:.1e}"
            f"{drift}  {r['world_steps_per_second']:,.0f} world-steps/s")  # fmt: skip


def _plot(result, path):
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    cases = sorted({r["case"] for r in result["rows"]})
    fig, axes = plt.subplots(1, len(cases), figsize=(6 * len(cases), 4.5), squeeze=False)
    for ax, case in zip(axes[0], cases):
        series = {}
        for r in result["rows"]:
            if r["case"] == case:
                key = (r["engine"], r["integrator"], r["dtype"], r["tol"], bool(r.get("reuse_factor")))
                series.setdefault(key, []).append(r)
        for (engine, integrator, dtype, tol, reuse), rs in series.items():
            rs = sorted(rs, key=lambda r: r["dt"])
            label = f"{engine} {integrator} {dtype}" + (f" tol {tol}" if tol is not None else "") + (" reuse" if reuse else "")
            x = [r["world_steps_per_second"] * r["dt"] for r in rs]
            ax.loglog(x, [r["error_max"] for r in rs], "o-", label=label)
            for xi, r in zip(x, rs):
                ax.annotate(f"{r['dt']}", (xi, r["error_max"]), fontsize=6)
        ax.set_xlabel("simulated world-seconds per wall second (world-steps/s × dt)")
        ax.set_ylabel("max joint-angle error over 1 s [rad]")
        ax.set_title(f"{case} ({result['device_name']}, {result['worlds']} worlds)")
        ax.legend(fontsize=7)
        ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
