#!/usr/bin/env python3
"""A/B of the fused step's code variants on one device: world-steps/s and the trajectory each gives.

    python scripts/ab_step.py --device cuda:0 --variants new,new_s3 --cases cartpole --worlds 1024 --rounds 3

Each variant runs in a process of its own (``--variant NAME``; the Warp kernel caches are per
process), the variants alternating over ``--rounds`` rounds, so clock drift and whatever ran
before touch each alike.  A variant is a patch applied before the simulator is built (VARIANTS);
"new" is the tree as it is.  (Session 17 A/B'd a rolled register factor this way,
results/ldl_rolled_h100_dropped.md.)  Every process steps the same random states and saves the final body
positions and rotations; the report says whether each variant's trajectory equals the first's bit
for bit, and prints each variant's best world-steps/s with its ratio to the first.
"""
import argparse
import json
import os
import subprocess
import sys


def _steps(n):
    return lambda: dict(steps_per_launch=n)


# name -> a patch applied before anything is built; it may return keyword arguments for the Simulator
def _kw(**kw):
    return lambda: kw


def _unfused():
    import abd_gym.solver

    abd_gym.solver.FUSE_PRISMATIC = False  # a prismatic joint's limit and drive in terms of their own


def _defer():
    import abd_gym.solver

    abd_gym.solver.DEFER_ARMIJO = True  # the Armijo test of a first Newton step on the next assembly's energy


VARIANTS = {"new": lambda: None, "defer": _defer, "new_s1": _steps(1), "new_s3": _steps(3), "new_s4": _steps(4), "unfused": _unfused,
            "new_s6": _steps(6), "b16": _kw(block_dim=16), "b8": _kw(block_dim=8),
            "lanes": _kw(scratch="lanes"), "lanes_b16": _kw(scratch="lanes", block_dim=16),
            "lanes_b8": _kw(scratch="lanes", block_dim=8), "qs0": _kw(quadratic_stop=0.0),
            "chord_stop": _kw(chord_stop=True)}  # fmt: skip


def variant(name):
    """VARIANTS[name], or "lockK_sS": lockstep_warps=K, steps_per_launch=S."""
    if name in VARIANTS:
        return VARIANTS[name]
    k, s = name[len("lock"):].split("_s")
    return _kw(lockstep_warps=int(k), steps_per_launch=int(s))


def one(args):
    import numpy as np
    import warp as wp

    kwargs = variant(args.variant)() or {}
    from abd_gym.bench import CASES
    from abd_gym.bench_compare import fastest_run, random_states
    from abd_gym.simulator import Simulator

    sim = Simulator(CASES[args.case]["scene"](), num_worlds=args.worlds, dt=args.dt, device=args.device,
                    **kwargs)  # fmt: skip
    if args.case in ("cartpole", "double_pendulum"):
        x0 = random_states(args.case, args.worlds)
    else:  # (e.g. chains: their rest pose and up to 0.3 off it, as abd_gym.bench times them)
        rest = np.array(CASES[args.case]["rest"])
        x0 = rest + np.random.default_rng(0).uniform(-0.3, 0.3, (args.worlds, rest.size))
    sim.set_joint_state(x0)
    sim.step(args.steps)  # compile, capture, and the trajectory compared between variants
    wp.synchronize_device(sim.device)
    q = np.concatenate([sim.body_positions().reshape(args.worlds, -1), sim.body_rotations().reshape(args.worlds, -1)], 1)
    np.save(args.save, q)
    best = fastest_run(sim, x0, args.steps, args.repeat)
    print(json.dumps(dict(variant=args.variant, case=args.case, worlds=args.worlds,
                          world_steps_per_second=args.worlds * args.steps / best,
                          newton_iterations=float(sim.newton_iterations().mean()),
                          scratch=sim.solver.scratch, steps_per_launch=sim.solver.steps_per_launch)))  # fmt: skip


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--variants", default="new,new_s3")
    ap.add_argument("--variant", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--save", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--cases", default="cartpole,double_pendulum")
    ap.add_argument("--case", default="cartpole", help=argparse.SUPPRESS)
    ap.add_argument("--worlds", type=int, default=1024)
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--dt", type=float, default=0.01)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--out", default="ab_out")
    args = ap.parse_args()
    if args.variant:
        return one(args)
    import numpy as np

    os.makedirs(args.out, exist_ok=True)
    rows = []
    for case in args.cases.split(","):
        for r in range(args.rounds):
            for v in args.variants.split(","):
                save = os.path.join(args.out, f"q_{case}_{v}.npy")
                cmd = [sys.executable, __file__, "--variant", v, "--case", case, "--save", save, "--device", args.device,
                       "--worlds", str(args.worlds), "--steps", str(args.steps), "--dt", str(args.dt),
                       "--repeat", str(args.repeat)]  # fmt: skip
                out = subprocess.run(cmd, check=False, capture_output=True, text=True)  # a failed variant is reported
                line = [x for x in out.stdout.splitlines() if x.startswith("{")]
                if out.returncode or not line:
                    print(out.stdout[-2000:], out.stderr[-4000:], flush=True)
                    continue
                row = json.loads(line[-1])
                row["round"] = r
                rows.append(row)
                print(json.dumps(row), flush=True)
        names = args.variants.split(",")
        ref = np.load(os.path.join(args.out, f"q_{case}_{names[0]}.npy"))
        base = max(x["world_steps_per_second"] for x in rows if x["case"] == case and x["variant"] == names[0])
        for v in names:
            q = np.load(os.path.join(args.out, f"q_{case}_{v}.npy"))
            best = max(x["world_steps_per_second"] for x in rows if x["case"] == case and x["variant"] == v)
            same = bool(np.array_equal(q, ref))
            print(f"{case:16s} {v:10s} best {best / 1e6:8.2f} M world-steps/s  x{best / base:.3f} vs {names[0]}  "
                  f"trajectory {'bit-identical' if same else f'differs (max {np.abs(q - ref).max():.2e})'}", flush=True)
    with open(os.path.join(args.out, "ab.json"), "w") as f:
        json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
