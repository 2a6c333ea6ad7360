"""What the failed-step retry (solver/retry.py) costs a batch whose worlds all converge: the
bench's physics step with ``retry`` on and off, in alternating processes, one row a mechanism
and batch.  Prints a table and writes JSON.

    python scripts/retry_cost.py --device cuda:0 --worlds 1024,16384 --rounds 2 --out retry_cost.json
"""
import argparse
import json
import subprocess
import sys

CASES = "cartpole,double_pendulum,chain5"


def one(case, worlds, retry, device, steps):
    """World-steps/s of one process's run (bench.speed.time_steps)."""
    code = ("import json; from abd_gym.bench.speed import time_steps; "
            f"r = time_steps({case!r}, {worlds}, {steps}, 0.01, 'float32', {device!r}, retry={retry}); "
            "print(json.dumps(r))")  # fmt: skip
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python scripts/retry_cost.py", description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--cases", default=CASES)
    ap.add_argument("--worlds", default="1024,16384")
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--out", default="retry_cost.json")
    a = ap.parse_args(argv)
    rows = []
    print("| case | worlds | retry off [M world-steps/s] | retry on | on / off |\n|---|---:|---:|---:|---:|")
    for case in a.cases.split(","):
        for worlds in (int(w) for w in a.worlds.split(",")):
            rate = {True: [], False: []}
            for _ in range(a.rounds):
                for retry in (False, True):
                    rate[retry].append(one(case, worlds, retry, a.device, a.steps)["world_steps_per_second"])
            off, on = max(rate[False]), max(rate[True])
            rows.append(dict(case=case, num_worlds=worlds, off=rate[False], on=rate[True], ratio=on / off))
            print(f"| {case} | {worlds:,} | {off / 1e6:.2f} | {on / 1e6:.2f} | {on / off:.3f} |", flush=True)
    json.dump(dict(device=a.device, rows=rows), open(a.out, "w"), indent=1)


if __name__ == "__main__":
    main()
