#!/usr/bin/env python3
"""Size of the lane-split fused kernel's machine code for an H100, built here without a GPU.

    python scripts/sass_size.py cartpole double_pendulum FourBar-v0 [--lanes 32] [--by-function]

Each argument is a bench case (abd_gym.bench.CASES) or a registered task id.  The kernel is built
as the solver builds it for a GPU (fused_kernel with scratch="lanes", the scene's fused terms) and
compiled by NVRTC for sm_90 (``wp.compile_aot_module``, no driver needed); printed: the bytes of
SASS (the ELF's .text sections), registers a thread and the stack frame (from .nv.info).  At 1,024
worlds a world's step is a chain that runs its code about once, so code bytes track its time.  ``--by-function`` (needs pyelftools) splits the bytes by the
generated function each instruction's line is in, built with line information: the innermost
function only (Warp's array and arithmetic helpers count as array.h, builtin.h, …), not the inline
chain (nvdisasm on the cubin gives that)."""
import argparse
import collections
import os
import re
import struct
import tempfile

import warp as wp


def build(case: str, lanes: int = 32, lineinfo: bool = False, groups: int = 1, out: str | None = None):
    """The compiled cubin's path and the generated .cu source of ``case``'s lane-split kernel, as
    the solver builds it for a GPU (terms.fused_flags, the default SolverSettings), for sm_90, in
    ``out`` (a new temporary folder when None); ``lineinfo``: with line information and without
    #line directives (for a profiler's source view)."""
    if lineinfo:
        wp.config.lineinfo = True
        wp.config.line_directives = False
    from abd_gym.bench.speed import CASES
    from abd_gym.solver.fused import fused_kernel
    from abd_gym.sim.model import Model
    from abd_gym.solver.solver import SolverSettings
    from abd_gym.solver.terms import fused_flags

    if case in CASES:
        scene = CASES[case]["scene"]()
    else:
        import gymnasium as gym

        import abd_gym  # noqa: F401 -- registers the ids

        env = gym.make_vec(case if "/" in case else f"abd_gym/{case}", num_envs=1, vectorization_mode="vector_entry_point",
                           device="cpu")  # fmt: skip
        scene = env.unwrapped.scene
        env.close()
    m = Model(scene, num_worlds=1, device="cpu")
    own, folds = fused_flags(m)
    limits = tuple(len(m.limit_joints[kind]) for kind in ("revolute", "prismatic"))
    kernel = fused_kernel(wp.float32, own, folds, scratch="lanes", n=m.system_size, axis=m.axis, cuda=True, block=lanes, bracket=True,
                          groups=groups, quadratic=float(SolverSettings.quadratic_stop), limits=limits)[0]  # fmt: skip
    kernel.module.options["block_dim"] = lanes
    out = tempfile.mkdtemp() if out is None else out
    (cubin,) = wp.compile_aot_module(kernel.module, arch=90, module_dir=out, use_ptx=False)
    (source,) = [os.path.join(out, f) for f in os.listdir(out) if f.endswith(".cu")]
    return str(cubin), source


def sections(data: bytes):
    """(name, offset, size) of an ELF64's sections."""
    shoff = struct.unpack_from("<Q", data, 0x28)[0]
    shentsize, shnum, shstrndx = struct.unpack_from("<HHH", data, 0x3A)
    raw = [struct.unpack_from("<IIQQQQ", data, shoff + i * shentsize) for i in range(shnum)]
    strtab = raw[shstrndx][4]

    def name(n):
        return data[strtab + n : data.index(b"\0", strtab + n)].decode()

    return [(name(r[0]), r[4], r[5]) for r in raw]


def summary(cubin: str):
    """(SASS bytes, registers, stack frame bytes) of the cubin's kernel."""
    data = open(cubin, "rb").read()
    secs = sections(data)
    text = sum(size for name, _, size in secs if name.startswith(".text."))
    regs = frame = None
    for name, off, size in secs:
        if not name.startswith(".nv.info"):
            continue
        p = off
        while p < off + size:  # EIATTR records: format byte, attribute byte, payload
            fmt, attr = data[p], data[p + 1]
            if fmt == 0x04:
                n = struct.unpack_from("<H", data, p + 2)[0]
                val = data[p + 4 : p + 4 + n]
                if attr == 0x2F:  # EIATTR_REGCOUNT
                    regs = struct.unpack_from("<I", val, 4)[0]
                if attr == 0x11:  # EIATTR_FRAME_SIZE
                    frame = struct.unpack_from("<I", val, 4)[0]
                p += 4 + n
            elif fmt == 0x03:
                p += 4
            elif fmt == 0x02:
                p += 3
            elif fmt == 0x01:
                p += 2
            else:
                break
    return text, regs, frame


def functions(source):
    """The generated function each line of the generated .cu file is in (its name, per line)."""
    owner, name = [], "?"
    with open(source) as f:
        text = f.read().splitlines()
    for line in text:
        m = re.match(r"\s*(?:static\s+)?(?:CUDA_CALLABLE|extern \"C\" __global__)[^(]*?\b(\w+)\s*\(", line)
        if m:
            name = m.group(1)
        owner.append(name)
    return owner


def by_function(cubin: str, source: str):
    """SASS bytes per generated function (the innermost one of each instruction's source line)."""
    from elftools.elf.elffile import ELFFile

    owner = functions(source)
    elf = ELFFile(open(cubin, "rb"))
    dwarf = elf.get_dwarf_info(relocate_dwarf_sections=False)
    size, off, sizes = elf.get_section_by_name(".debug_line").data_size, 0, collections.Counter()
    while off < size:  # the line programs, one after another (the cubin has no .debug_info to list them)
        prog = dwarf._parse_line_program_at_offset(off, dwarf.structs)
        off += prog.header["unit_length"] + 4
        files = prog["file_entry"]
        rows = [e.state for e in prog.get_entries() if e.state is not None]
        for a, b in zip(rows, rows[1:]):
            if a.end_sequence:
                continue
            fname = files[a.file - 1].name.decode() if 0 < a.file <= len(files) else "?"
            key = owner[a.line - 1] if fname.endswith(".cu") and 0 < a.line <= len(owner) else os.path.basename(fname)
            sizes[key] += b.address - a.address
    return sizes


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("cases", nargs="+")
    ap.add_argument("--lanes", type=int, default=32)
    ap.add_argument("--by-function", action="store_true")
    ap.add_argument("--top", type=int, default=25)
    args = ap.parse_args()
    wp.config.quiet = True
    for case in args.cases:
        cubin, source = build(case, args.lanes, args.by_function)
        text, regs, frame = summary(cubin)
        print(f"{case}: {text / 1024:.1f} KB of SASS, {regs} registers, {frame} B stack frame ({args.lanes} lanes)")
        if args.by_function:
            for fn, n in by_function(cubin, source).most_common(args.top):
                print(f"  {n / 1024:7.1f} KB  {fn}")


if __name__ == "__main__":
    main()
