"""Train several configs at once, one process each (one torch thread each), on a many-core machine.

    python scripts/train_parallel.py configs/acrobot_ppo.yaml configs/reacher_sac.yaml ... \
        [--root runs] [--timeout SECONDS] [-- extra abd_gym.agents.train arguments]

Each run goes to ``ROOT/<config>-<seed>/`` with its log in ``ROOT/<config>.log``; a run still going
after ``--timeout`` seconds is stopped (and leaves no summary).  Prints each run's last log line.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    extra = argv[argv.index("--") + 1 :] if "--" in argv else []
    argv = argv[: argv.index("--")] if "--" in argv else argv
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("configs", nargs="+")
    p.add_argument("--root", default="runs")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--timeout", type=float, default=None)
    args = p.parse_args(argv)
    root = Path(args.root)
    root.mkdir(parents=True, exist_ok=True)
    procs = {}
    for cfg in args.configs:
        name = Path(cfg).stem
        cmd = [sys.executable, "-m", "abd_gym.agents.train", cfg, "--seed", str(args.seed), "--no-progress",
               "--torch-threads", "1", "--run-dir", str(root / f"{name}-{args.seed}"), *extra]  # fmt: skip
        log = open(root / f"{name}.log", "w")
        procs[name] = (subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT), log, time.perf_counter())
    status = 0
    for name, (proc, log, t0) in procs.items():
        try:
            left = None if args.timeout is None else max(args.timeout - (time.perf_counter() - t0), 1.0)
            rc = proc.wait(timeout=left)
        except subprocess.TimeoutExpired:
            proc.kill()
            rc = "timeout"
        log.close()
        lines = (root / f"{name}.log").read_text().strip().splitlines() or [""]
        summary = [ln for ln in lines if " steps in " in ln]
        print(f"{name}: rc {rc}: {(summary or lines)[-1]}", flush=True)
        status = status or (rc != 0)
    return int(bool(status))


if __name__ == "__main__":
    sys.exit(main())
