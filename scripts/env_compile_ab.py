"""compile_outcome off and on, alternating in one process: the vector env's env-steps/s with the
task's outcome eager and compiled by torch.compile, two rounds each (the fastest of three windows
of 200 steps), then one raw run (env, simulator alone, physics device time) with the default.

    python scripts/env_compile_ab.py [TASKS] [ENVS] [DEVICE]
    python scripts/env_compile_ab.py CartPole-v0,Pendulum-v0 1024 cuda:0   (results/envstep_h100.md)
"""
import sys

from abd_gym.envs.bench_envs import env_steps_per_second


def main(argv):
    tasks = (argv[0] if argv else "CartPole-v0,Pendulum-v0").split(",")
    worlds = [int(w) for w in (argv[1] if len(argv) > 1 else "1024").split(",")]
    device = argv[2] if len(argv) > 2 else "cuda:0"
    for task in tasks:
        for n in worlds:
            for rnd in range(2):
                for comp in (False, True):
                    def configure(u, comp=comp):  # read at the env's first step
                        u._compile_outcome = comp

                    sps = env_steps_per_second(task, n, 200, device, "torch", repeat=3, configure=configure)
                    print(f"{task} {n} round {rnd} compile {comp}: {sps / 1e6:.3f} M env-steps/s", flush=True)
            e, a, p = env_steps_per_second(task, n, 200, device, "torch", repeat=3, raw=True)
            print(f"{task} {n} raw (compile default): env {e / 1e6:.3f} M, alone {a / 1e6:.3f} M, physics {p / 1e6:.3f} M, "
                  f"env/physics {e / p:.2f}", flush=True)  # fmt: skip


if __name__ == "__main__":
    main(sys.argv[1:])
