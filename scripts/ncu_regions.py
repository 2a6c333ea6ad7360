#!/usr/bin/env python3
"""Where the fused step's time goes, by code region: Nsight Compute's per-instruction samples of the
lane-split kernel joined with the line table of the same kernel compiled here.

1. On the GPU, profile one launch with source counters and export the SASS page:

       ncu --clock-control none -k regex:newton -s 2 -c 1 --import-source yes --section WarpStateStats \\
           --section SourceCounters -o rep python3 scripts/profile_step.py --device cuda:0 --case cartpole \\
           --worlds 1024 --steps 2 --warmup 3 --lineinfo
       ncu -i rep.ncu-rep --page source --csv --print-source sass | gzip > source.csv.gz

2. Here (no GPU: NVRTC compiles for sm_90; nvdisasm from a CUDA toolkit or Triton's wheel):

       python scripts/ncu_regions.py source.csv.gz --case cartpole --nvdisasm PATH/nvdisasm

The kernel is rebuilt with line information and without ``#line`` directives, so each instruction's
inline chain names the generated functions (``fused_kernel__locals__drive_term_0``, the native
``regs_ldl_solve``, …) instead of Python lines; the SASS is the profiled kernel's (checked opcode by
opcode).  Each instruction goes to the first region of REGIONS on its chain.  Prints per region the
stall samples by reason, the warp-instructions executed and the code executed (bytes).
"""
import argparse
import collections
import csv
import gzip
import os
import re
import subprocess
import tempfile

# a region: the first of these (substrings of generated function names) on an instruction's inline chain
REGIONS = ("open_world", "close_world", "regs_ldl_solve", "ldl_lanes", "solve_lanes", "body_rows", "point_term",
           "prismatic_term", "angle_term", "rlim_term", "plim_term", "drive_term", "trial", "end_iteration", "noise_floor",
           "reductions", "search", "assemble", "take_step", "solve_world", "step_world")  # fmt: skip
REASONS = ("no_inst", "long_sb", "wait", "selected", "imc", "short_sb", "branch_resolving", "not_selected", "lg",
           "dispatch", "math", "barrier", "mio")  # fmt: skip


def build(case, out, groups=1):
    """The lane-split kernel of ``case`` compiled for sm_90 with line info and no #line directives,
    as the solver builds it (scripts/sass_size.py's build)."""
    from sass_size import build as build_kernel  # (scripts/ is this script's folder on sys.path)

    return build_kernel(case, 32, lineinfo=True, groups=groups, out=out)


def functions(source):
    """The generated function each line of the .cu file is in (scripts/sass_size.py's)."""
    from sass_size import functions as owners

    return owners(source)


def opcode(sass):
    """The opcode of a SASS line, without its predicate and modifiers."""
    words = sass.replace(";", " ").split()
    if words and words[0].startswith("@"):
        words = words[1:]
    return words[0].split(".")[0] if words else ""


def chains(nvdisasm, cubin, owner):
    """offset -> (opcode, the instruction's inline chain of generated functions, outermost first)."""
    text = subprocess.run([nvdisasm, "-gi", "-c", cubin], check=True, capture_output=True, text=True).stdout
    out, lines, fresh = {}, [], True
    for s in text.splitlines():
        if s.lstrip().startswith("//## File"):
            if not fresh:
                lines, fresh = [], True
            lines += [int(n) for n in re.findall(r'", line (\d+)', s)]
            continue
        m = re.match(r"\s*/\*([0-9a-f]{4,})\*/\s*(.*)", s)
        if m:
            fresh = False
            names = []
            for n in reversed(lines):  # innermost first in the listing
                f = owner[n - 1] if 0 < n <= len(owner) else "?"
                if not names or names[-1] != f:
                    names.append(f)
            out[int(m.group(1), 16)] = (opcode(m.group(2)), tuple(names))
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("source_csv", help="ncu --page source --csv --print-source sass output (.csv or .csv.gz)")
    ap.add_argument("--case", default="cartpole")
    ap.add_argument("--nvdisasm", default="nvdisasm")
    args = ap.parse_args()
    opener = gzip.open if args.source_csv.endswith(".gz") else open
    rows = list(csv.reader(opener(args.source_csv, "rt")))
    head = next(r for r in rows if r and r[0] == "Address")
    data = rows[rows.index(head) + 1:]
    col = {h: i for i, h in enumerate(head)}
    base = int(data[0][col["Address"]], 16)
    with tempfile.TemporaryDirectory() as tmp:
        cubin, source = build(args.case, tmp)
        local = chains(args.nvdisasm, cubin, functions(source))
    mismatch = sum(1 for r in data if local.get(int(r[col["Address"]], 16) - base, ("",))[0] != opcode(r[col["Source"]]))
    print(f"{len(data)} profiled instructions, {len(local)} compiled here, {mismatch} opcodes differ")
    samples = collections.defaultdict(collections.Counter)
    executed, footprint = collections.Counter(), collections.Counter()
    for r in data:
        names = local.get(int(r[col["Address"]], 16) - base, ("", ()))[1]
        region = next((x for x in REGIONS for n in names if x in n), names[-1] if names else "?")
        for reason in REASONS:
            samples[region][reason] += int(r[col.get(f"stall_{reason}", -1)] or 0) if f"stall_{reason}" in col else 0
        ex = int(r[col["Instructions Executed"]] or 0)
        executed[region] += ex
        footprint[region] += 16 if ex else 0
    total = sum(sum(c.values()) for c in samples.values())
    print(f"{'region':16s} {'samples':>8s} {'%':>5s} " + " ".join(f"{x[:8]:>8s}" for x in REASONS)
          + f" {'warp-inst':>10s} {'code run':>9s}")  # fmt: skip
    for region in sorted(samples, key=lambda k: -sum(samples[k].values())):
        s = samples[region]
        print(f"{region[:16]:16s} {sum(s.values()):8d} {100 * sum(s.values()) / total:5.1f} "
              + " ".join(f"{s[x]:8d}" for x in REASONS) + f" {executed[region]:10d} {footprint[region] / 1024:7.1f} KB")
    print(f"code run in the launch: {sum(footprint.values()) / 1024:.1f} KB")


if __name__ == "__main__":
    main()
