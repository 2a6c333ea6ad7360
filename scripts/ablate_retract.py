"""Newton along rotations or along lines (``SolverSettings.retract``) in the vector envs: env
steps per second, the simulator alone, and the physics' device time, each with the retraction
on and off, in one process (ratios in one run; see envs/bench_envs.py for the three rates).

    python scripts/ablate_retract.py [--device cuda:0] [--worlds 1024,131072] [--steps 50] [--out DIR]
"""
import argparse
import json
import os

from abd_gym.envs.bench_envs import env_steps_per_second


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--worlds", default="1024,131072")
    ap.add_argument("--tasks", default="CartPole-v0,Pendulum-v0,DoublePendulumCart-v0")
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--out", default="ablate_out")
    args = ap.parse_args(argv)
    backend = "torch" if args.device.startswith("cuda") else "numpy"
    rows = []
    print(f"{'task':24s} {'envs':>7s} {'retract':>8s} {'env-steps/s':>12s} {'alone':>12s} {'physics':>12s} {'iters':>6s}")
    for task in args.tasks.split(","):
        for n in (int(w) for w in args.worlds.split(",")):
            for retract in (True, False):
                seen = {}

                def configure(u, retract=retract, seen=seen):
                    u.sim.solver.settings.retract = retract
                    seen["sim"] = u.sim

                env, alone, physics = env_steps_per_second(task, n, args.steps, args.device, backend, raw=True,
                                                           configure=configure)  # fmt: skip
                iters = float(seen["sim"].newton_iterations().mean())
                rows.append(dict(task=task, num_envs=n, retract=retract, env_steps_per_second=env,
                                 alone_steps_per_second=alone, physics_steps_per_second=physics,
                                 newton_iterations_last_step=iters))  # fmt: skip
                print(f"{task:24s} {n:7d} {str(retract):>8s} {env:12.0f} {alone:12.0f} {physics:12.0f} {iters:6.2f}",
                      flush=True)  # fmt: skip
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "ablate_retract.json"), "w") as f:
        json.dump(dict(device=args.device, rows=rows), f, indent=1)


if __name__ == "__main__":
    main()
