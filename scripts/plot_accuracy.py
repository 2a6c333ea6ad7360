#!/usr/bin/env python3
"""Plot a saved speed-against-error result (``bench accuracy``'s ``accuracy.json``, or a merged
file such as ``results/accuracy_own_reference.json``).

    python scripts/plot_accuracy.py RESULT.json OUT.png [--key own_error_max|error_max] [--title TEXT]

One log-log panel per mechanism (:func:`abd_gym.bench.accuracy.plot`): for each setting of each
engine, the error over 1 s [rad] against simulated world-seconds per wall second, over dt.  The
title names the device and batch of the rates: the result's own, or ``--title`` for a merged file
whose rates come from another run.
"""
from __future__ import annotations

import argparse
import json
import sys

from abd_gym.bench.accuracy import plot


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("result")
    p.add_argument("out")
    p.add_argument("--key", default="own_error_max", choices=("own_error_max", "error_max"))
    p.add_argument("--title", help="the device and batch of the rates (default: the result's)")
    args = p.parse_args(argv)
    with open(args.result) as f:
        result = json.load(f)
    if args.title is None and "device_name" not in result:
        p.error(f"{args.result} names no device (a merged file): give --title")
    if not plot(result, args.out, key=args.key, title=args.title):
        print("plot_accuracy: matplotlib is not installed (pip install matplotlib)", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
