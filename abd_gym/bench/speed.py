"""Benchmark: steps per second against number of worlds, with the accuracy of each run.

    python -m abd_gym.bench [--device cpu|cuda:0] [--worlds 1,16,256] [--steps 50] [--out DIR]
    python -m abd_gym.bench compare ...    (against MuJoCo Warp: compare.py)
    python -m abd_gym.bench accuracy ...   (speed against error: accuracy.py)
    python -m abd_gym.bench threads ...    (fused step's thread count and block size: sweep_threads)
    python -m abd_gym.bench robustness ... (hard cases with default settings: robustness.py)
    python -m abd_gym.bench single ...     (one gym.make env against Gymnasium's own: single.py)

For a double pendulum and a cart-pole it times ``Simulator.step`` (after warm-up, synchronised)
and reports world-steps per second, steps per second, mean Newton iterations, the largest joint
residual [m] seen in the timed window, and the relative error of the mechanism's small-oscillation
period against the closed form of its linearisation (lowest mode; the cart-pole's pole hangs
down on a free cart).  Prints a table and writes ``bench.json`` to ``--out``.
"""
import argparse
import json
import math
import os
import platform
import time

import numpy as np
import warp as wp

from ..sim import mechanisms
from ..solver.plan import ExecutionPlan
from ..sim.simulator import Simulator

G = 9.81


def _box_inertia_y(m, length, width=0.04):
    """Moment of inertia [kg·m²] of a link about its centre, for rotation about y."""
    return m / 3.0 * ((width / 2) ** 2 + (length / 2) ** 2)


def _double_pendulum_mode(L=0.5, m=1.0):
    """Lowest linearised mode of two uniform links (absolute angles φ1, φ2): period and shape."""
    ic, d = _box_inertia_y(m, L), L / 2
    M = np.array([[ic + m * d * d + m * L * L, m * L * d], [m * L * d, ic + m * d * d]])
    K = np.diag([(m * d + m * L) * G, m * d * G])
    w2, v = np.linalg.eig(np.linalg.solve(M, K))
    k = int(np.argmin(w2.real))
    phi = v[:, k].real / np.abs(v[:, k].real).max()
    return 2 * math.pi / math.sqrt(w2[k].real), np.array([phi[0], phi[1] - phi[0]])  # joint coordinates


def _cartpole_mode(pole_length=1.0, pole_mass=0.1, cart_mass=1.0):
    """Pole hanging on a free cart: ω² = m g d (M + m) / ((M + m) I_c + M m d²)."""
    ic, d, m, M = _box_inertia_y(pole_mass, pole_length, 0.02), pole_length / 2, pole_mass, cart_mass
    w2 = m * G * d * (M + m) / ((M + m) * ic + M * m * d * d)
    return 2 * math.pi / math.sqrt(w2)


CASES = {
    "double_pendulum": dict(scene=mechanisms.double_pendulum, mode=lambda: _double_pendulum_mode(), pole=0, rest=(0.0, 0.0)),
    "cartpole": dict(scene=mechanisms.cartpole, mode=lambda: (_cartpole_mode(), np.array([0.0, 1.0])), pole=1,
                     rest=(0.0, math.pi)),
    # the same cart-pole without its track limit, and without limit or drive: what the scene does
    # not have is not compiled, so these show what each constitution costs
    "cartpole_nolimit": dict(scene=lambda: mechanisms.cartpole(track=None), mode=lambda: (_cartpole_mode(), np.array([0.0, 1.0])),
                             pole=1, rest=(0.0, math.pi)),
    "cartpole_bare": dict(scene=lambda: mechanisms.cartpole(track=None, force=None),
                          mode=lambda: (_cartpole_mode(), np.array([0.0, 1.0])), pole=1, rest=(0.0, math.pi)),
    # 5- and 10-link chains (60 and 120 unknowns): their Hessians are block-banded, factored on
    # their envelopes; no closed-form period (mode None)
    "chain5": dict(scene=lambda: mechanisms.chain(5, length=0.1), mode=None, pole=0, rest=(0.0,) * 5),
    "chain10": dict(scene=lambda: mechanisms.chain(10, length=0.1), mode=None, pole=0, rest=(0.0,) * 10),
}  # fmt: skip


def period_error(case, dt, dtype, device, amplitude=0.02):
    """Relative error of the measured small-oscillation period against the closed form."""
    c = CASES[case]
    period, shape = c["mode"]()
    sim = Simulator(c["scene"](), num_worlds=1, dt=dt, device=device, dtype=dtype)
    rest = np.array(c["rest"])
    sim.set_joint_state([rest + amplitude * shape])
    steps = int(math.ceil(2.6 * period / dt))
    xs = np.empty(steps)
    for i in range(steps):
        sim.step()
        xs[i] = sim.joint_angles_unwrapped()[0, c["pole"]] - rest[c["pole"]]
    k = np.flatnonzero((xs[:-1] > 0) & (xs[1:] <= 0))
    if len(k) < 2:
        return float("nan")
    t = (k + 1 + xs[k] / (xs[k] - xs[k + 1])) * dt
    return float((np.diff(t).mean() - period) / period)


def time_steps(case, num_worlds, steps, dt, dtype, device, seed=0, planar=None, **sim_kwargs):
    """Time ``steps`` steps of ``num_worlds`` worlds (``planar``: Scene.planar; ``sim_kwargs``: more
    Simulator options, e.g. ``plan``, an ExecutionPlan; the row records the resolved plan's choices)."""
    c = CASES[case]
    scene = c["scene"]()
    scene.planar = planar
    sim = Simulator(scene, num_worlds=num_worlds, dt=dt, device=device, dtype=dtype, **sim_kwargs)
    rng = np.random.default_rng(seed)
    x0 = np.array(c["rest"]) + rng.uniform(-0.3, 0.3, size=(num_worlds, len(c["rest"])))
    if case.startswith("cartpole"):
        x0 = np.stack([rng.uniform(-0.5, 0.5, num_worlds), rng.uniform(-0.3, 0.3, num_worlds)], 1)
    sim.set_joint_state(x0)
    # sim.step(k) calls of k steps each (k = steps_per_launch where a launch can take several)
    k = sim.plan.steps_per_launch if sim.solver.multi_step else 1
    steps = -(-steps // k) * k
    sim.step(3)  # compile and warm up
    sim.step(k)  # (and capture the k-step launch)
    wp.synchronize_device(sim.device)
    t0 = time.perf_counter()
    for _ in range(steps // k):
        sim.step(k)
    wp.synchronize_device(sim.device)
    elapsed = time.perf_counter() - t0
    residual = float(sim.joint_violation().max())
    return dict(
        case=case, num_worlds=num_worlds, steps=steps, dt=dt, dtype=dtype, device=str(sim.device),
        tol=sim.solver.settings.tol, integrator=sim.solver.settings.integrator, scratch=sim.plan.scratch,
        seconds=elapsed, steps_per_second=steps / elapsed, world_steps_per_second=num_worlds * steps / elapsed,
        newton_iterations=float(sim.newton_iterations().mean()),
        newton_factorizations=float(sim.newton_factorizations().mean()), joint_residual=residual,
        reuse_factor=sim.solver.reuse_factor, envelope=sim.plan.envelope,
        converged_fraction=float(sim.converged().mean()), failed_worlds=int(sim.failed_worlds().size),
        threads=sim.plan.threads, block_dim=sim.plan.block_dim, cpu_workers=len(sim.solver.newton_launches),
        lane_groups=sim.plan.lane_groups, steps_per_launch=k, lockstep_warps=sim.plan.lockstep_warps,
        memory_bytes_per_world=sim.memory_bytes()["total"] / num_worlds,
        unknowns=sim.model.num_dofs, constitutions=[c.name for c in sim.solver.parts],
    )  # fmt: skip


def main(argv=None):
    import sys

    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] == "compare":
        from .compare import main as compare

        return compare(argv[1:])
    if argv and argv[0] == "threads":
        return sweep_threads(argv[1:])
    if argv and argv[0] == "accuracy":
        from .accuracy import main as accuracy

        return accuracy(argv[1:])
    if argv and argv[0] == "single":
        from .single import main as single

        return single(argv[1:])
    if argv and argv[0] == "robustness":
        from .robustness import main as robustness

        return robustness(argv[1:])
    ap = argparse.ArgumentParser(prog="python -m abd_gym.bench", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--worlds", default=None, help="comma-separated world counts (default: 1..64 on CPU, 1..65536 on GPU)")
    ap.add_argument("--steps", type=int, default=None)
    ap.add_argument("--dt", type=float, default=0.01)
    ap.add_argument("--dtype", default="float32")
    ap.add_argument("--tol", default="1e-5", help="comma-separated Newton tolerances ‖Δq‖∞/h [m/s] to time")
    ap.add_argument("--integrator", default="implicit_euler")
    ap.add_argument("--scratch", default="auto",
                    help="comma-separated fused-step layouts: auto (the simulator's default), global (a thread per "
                         "world), shared (a thread per world, its system in shared memory), lanes (a block per world)")
    ap.add_argument("--planar", default="auto", help="comma-separated forms: auto (a planar scene's 6 unknowns a "
                    "body, Scene.planar None), off (12 unknowns a body)")
    ap.add_argument("--block-dim", type=int, default=None, help="CUDA block size (default: per solver)")
    ap.add_argument("--repeat", type=int, default=1, help="time each row this many times and keep the fastest")
    ap.add_argument("--threads", default=None, help="fused-step threads: all (one per world), Nsm (N per SM) or a count")
    ap.add_argument("--reuse-factor", default="0",
                    help="comma-separated 0/1: reuse the Cholesky factor after a full Newton step (default 0)")
    ap.add_argument("--envelope", default="auto",
                    help="comma-separated auto/0/1: factor the Hessian's envelope only, as the block band where "
                         "the scene is banded (default: when the scene has one; see ExecutionPlan.envelope)")
    ap.add_argument("--cpu-workers", default="auto",
                    help="comma-separated auto/N: concurrent launches of the fused step on the CPU (auto: one per core)")
    ap.add_argument("--lane-groups", default="auto",
                    help="comma-separated lane groups a world for scratch=lanes (auto: the solver's default)")
    ap.add_argument("--steps-per-launch", default="auto",
                    help="comma-separated auto/N: steps a launch where a step is one launch (sim.step(k) calls of k "
                         "steps; auto: the solver's default)")
    ap.add_argument("--lockstep-warps", default="auto",
                    help="comma-separated auto/N: warps a lockstep block of the lane-split step (auto: the "
                         "solver's default)")
    ap.add_argument("--cases", default="double_pendulum,cartpole")
    ap.add_argument("--out", default="bench_out")
    ap.add_argument("--envs", action="store_true", help="also time each task's vector env")
    ap.add_argument("--tasks", default=None, help="comma-separated task names for --envs (default: all)")
    ap.add_argument("--env-worlds", default=None, help="world counts for --envs (default: --worlds)")
    args = ap.parse_args(argv)
    gpu = args.device.startswith("cuda")
    worlds = [int(w) for w in args.worlds.split(",")] if args.worlds else (
        [1, 16, 256, 1024, 4096, 16384, 65536] if gpu else [1, 4, 16, 64])  # fmt: skip
    steps = args.steps or (50 if gpu else 20)
    rows, accuracy = [], []
    for case in args.cases.split(","):
        if CASES[case]["mode"] is not None:
            accuracy.append(dict(case=case, dt=args.dt, dtype=args.dtype,
                                 period_error=period_error(case, args.dt, args.dtype, args.device)))  # fmt: skip
        reuse_choice = {"0": False, "1": True}
        envelope_choice = {"auto": None, "0": False, "1": True}
        variants = [(k, float(t), reuse_choice[ru], envelope_choice[en],
                     None if cw == "auto" else int(cw), None if lg == "auto" else int(lg),
                     None if spl == "auto" else int(spl), None if lw == "auto" else int(lw), {"auto": None, "off": False}[pf])
                    for pf in args.planar.split(",") for k in args.scratch.split(",") for t in args.tol.split(",") for ru in args.reuse_factor.split(",")
                    for en in args.envelope.split(",") for cw in args.cpu_workers.split(",")
                    for lg in args.lane_groups.split(",") for spl in args.steps_per_launch.split(",")
                    for lw in args.lockstep_warps.split(",")]  # fmt: skip
        for (scratch, tol, reuse, env, cw, lg, spl, lw, planar), w in ((v, w) for v in variants for w in worlds):
            plan = ExecutionPlan(scratch=None if scratch == "auto" else scratch, block_dim=args.block_dim,
                                 envelope=env, cpu_workers=cw, lane_groups=lg, steps_per_launch=spl,
                                 lockstep_warps=lw, threads=_thread_count(args.threads, w, args.device))  # fmt: skip
            runs = [time_steps(case, w, steps, args.dt, args.dtype, args.device, tol=tol, integrator=args.integrator,
                               reuse_factor=reuse, plan=plan, planar=planar)
                    for _ in range(max(args.repeat, 1))]  # fmt: skip
            rows.append(max(runs, key=lambda r: r["world_steps_per_second"]))
            rows[-1]["repeats"] = len(runs)
            r = rows[-1]
            print(f"{case:16s} worlds {w:6d} unknowns {r['unknowns']:3d} tol {tol:g} {_solver(r):9s} {r['world_steps_per_second']:12.0f} world-steps/s  "
                  f"{r['steps_per_second']:8.1f} steps/s  iters {r['newton_iterations']:.2f}  "
                  f"factorisations {r['newton_factorizations']:.2f}  "
                  f"residual {r['joint_residual']:.2e}", flush=True)  # fmt: skip
    env_rows = []
    if args.envs:
        from ..envs.bench_envs import env_steps_per_second

        import abd_gym.vector.registration as reg

        backend = "torch" if gpu else "numpy"  # on the GPU the batch never leaves the device
        tasks = args.tasks.split(",") if args.tasks else list(reg.TASKS)
        env_worlds = [int(w) for w in args.env_worlds.split(",")] if args.env_worlds else worlds
        for task in tasks:
            for w in env_worlds:
                env_sps, raw_sps, physics_sps = env_steps_per_second(task, w, steps, args.device, backend=backend,
                                                                     raw=True, repeat=args.repeat)  # fmt: skip
                env_rows.append(dict(task=task, num_envs=w, backend=backend, env_steps_per_second=env_sps,
                                     raw_steps_per_second=raw_sps, env_over_raw=env_sps / raw_sps,
                                     physics_steps_per_second=physics_sps, env_over_physics=env_sps / physics_sps))  # fmt: skip
                print(f"{task:28s} envs {w:6d}  {env_sps:12.0f} env-steps/s  simulator alone {raw_sps:12.0f} "
                      f"({env_sps / raw_sps:.2f})  physics time {physics_sps:12.0f} ({env_sps / physics_sps:.2f})",
                      flush=True)  # fmt: skip
    device_name = wp.get_device(args.device).name if gpu else platform.processor() or platform.machine()
    result = dict(device=args.device, device_name=device_name, warp=wp.config.version, simulator=rows,
                  accuracy=accuracy, envs=env_rows)  # fmt: skip
    print()
    print(table(result))
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "bench.json"), "w") as f:
        json.dump(result, f, indent=1)
    return result


def sweep_threads(argv=None):
    """World-steps per second of the fused step against its thread count and CUDA block size.

    ``--threads`` are thread counts, or ``Nsm`` for N per streaming multiprocessor, or ``all``
    (one thread per world, the scratch then as large as the batch).  Writes ``threads.json``.
    """
    ap = argparse.ArgumentParser(prog="python -m abd_gym.bench threads", description=sweep_threads.__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--cases", default="cartpole,double_pendulum")
    ap.add_argument("--worlds", default="1024,131072")
    ap.add_argument("--threads", default="all,64sm,128sm,256sm")
    ap.add_argument("--block-dims", default="32,64,128,256")
    ap.add_argument("--scratch", default="auto", help="the fused step's layout: auto, global, shared or lanes")
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--dt", type=float, default=0.01)
    ap.add_argument("--dtype", default="float32")
    ap.add_argument("--out", default="bench_out")
    args = ap.parse_args(argv)
    dev = wp.get_device(args.device)
    sms = dev.sm_count if dev.is_cuda else 1

    def count(spec, worlds):
        if spec == "all":
            return worlds
        return int(spec[:-2]) * sms if spec.endswith("sm") else int(spec)

    rows = []
    for case in args.cases.split(","):
        for w in (int(x) for x in args.worlds.split(",")):
            for spec in args.threads.split(","):
                T = min(count(spec, w), w)
                if any(r["case"] == case and r["num_worlds"] == w and r["threads"] == T and spec != "all" for r in rows):
                    continue
                for bd in (int(b) for b in args.block_dims.split(",")):
                    scratch = None if args.scratch == "auto" else args.scratch
                    plan = ExecutionPlan(threads=T, block_dim=bd, scratch=scratch)
                    r = time_steps(case, w, args.steps, args.dt, args.dtype, args.device, plan=plan)
                    rows.append(r)
                    print(f"{case:16s} {args.scratch} worlds {w:8d} threads {T:8d} block {bd:4d}  "
                          f"{r['world_steps_per_second']:14,.0f} world-steps/s  iters {r['newton_iterations']:.2f}  "
                          f"{r['memory_bytes_per_world']:.0f} B/world", flush=True)  # fmt: skip
    result = dict(device=args.device, device_name=dev.name, sm_count=sms, warp=wp.config.version, rows=rows)
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "threads.json"), "w") as f:
        json.dump(result, f, indent=1)
    return result


def _thread_count(spec, worlds, device):
    """None (the solver's default), or a count from "all", "Nsm" (N per streaming multiprocessor) or "N"."""
    if spec is None:
        return None
    if spec == "all":
        return worlds
    dev = wp.get_device(device)
    return min(worlds, int(spec[:-2]) * (dev.sm_count if dev.is_cuda else 1) if spec.endswith("sm") else int(spec))


def _solver(r) -> str:
    """The fused step's layout ("global", "lanes"; "tiled", "local" in older results) and CUDA block size."""
    scratch = r.get("scratch") or ("tiled" if r.get("tiled") else "global")
    extra = "" if r.get("reuse_factor", False) else " full"  # every iteration factors (older results: all)
    extra += " envelope" if r.get("envelope", False) else ""
    extra += f" W{r['cpu_workers']}" if r.get("cpu_workers", 1) > 1 else ""  # concurrent CPU launches
    extra += f" G{r['lane_groups']}" if r.get("lane_groups", 1) > 1 else ""  # lane groups a world
    extra += f" S{r['steps_per_launch']}" if r.get("steps_per_launch", 1) > 1 else ""  # steps a launch
    extra += f" K{r['lockstep_warps']}" if r.get("lockstep_warps", 1) > 1 else ""  # warps a lockstep block
    return f"{scratch}/{r['block_dim']}{extra} T{r['threads']}"


def table(result) -> str:
    """Markdown tables of a bench result."""
    lines = [f"Device: {result['device_name']} ({result['device']}), warp {result['warp']}", "",
             "| mechanism | worlds | unknowns | step | tol [m/s] | world-steps/s | steps/s | Newton iters | factorisations | "
             "joint residual [m] |", "|---|---:|---:|---|---:|---:|---:|---:|---:|---:|"]  # fmt: skip
    for r in result["simulator"]:
        lines.append(f"| {r['case']} | {r['num_worlds']} | {r.get('unknowns', '')} | {_solver(r)} | {r.get('tol', 1e-5):g} | "
                     f"{r['world_steps_per_second']:,.0f} | "
                     f"{r['steps_per_second']:,.1f} | {r['newton_iterations']:.2f} | "
                     f"{r.get('newton_factorizations', r['newton_iterations']):.2f} | "
                     f"{r['joint_residual']:.1e} |")  # fmt: skip
    if result["accuracy"]:
        lines += ["", "| mechanism | dt [s] | dtype | period error (lowest mode) |", "|---|---:|---|---:|"]
    for a in result["accuracy"]:
        lines.append(f"| {a['case']} | {a['dt']} | {a['dtype']} | {a['period_error']:+.3%} |")
    if result.get("envs"):
        lines += ["", "| task | envs | env-steps/s | simulator alone, steps/s | env / alone | physics device time, steps/s "
                  "| env / physics |", "|---|---:|---:|---:|---:|---:|---:|"]  # fmt: skip
        for e in result["envs"]:
            lines.append(f"| {e['task']} | {e['num_envs']} | {e['env_steps_per_second']:,.0f} | "
                         f"{e['raw_steps_per_second']:,.0f} | {e['env_over_raw']:.2f} | "
                         f"{e['physics_steps_per_second']:,.0f} | {e['env_over_physics']:.2f} |")  # fmt: skip
    return "\n".join(lines)

