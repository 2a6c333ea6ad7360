#!/usr/bin/env python3
"""The code Warp generates for the kernels built from Python factories, in a form to compare
across a refactoring: each kernel's C++ (CPU) and CUDA source with the comments and line
directives (which carry the Python source and its line numbers) removed and the generated
functions renamed in order of appearance (Warp names a function by its Python qualified name and
a creation counter, which moving a function into another factory changes).  Equal digests mean
the compiler is given the same code.  No GPU is needed.

    python scripts/generated_code.py --out DIR            # one normalised file a kernel and target, and digests.txt
    python scripts/generated_code.py --out DIR --sass     # also the sm_90 machine code's digest (NVRTC, slower)

Kernels: the constitutions' and the step's bracketing kernels and the staged step's kernels
(float32 and float64), and the fused step for a few tasks and bench cases in its lane-split,
thread-per-world shared and global forms.
"""
import argparse
import hashlib
import os
import re
import struct
import tempfile

import warp as wp


class _Source(Exception):
    """Carries a module's generated source out of Warp's build (which then compiles nothing)."""

    def __init__(self, source):
        super().__init__("source")
        self.source = source


def generated_source(kernel, target: str, block_dim: int = 0) -> str:
    """The source Warp generates for ``kernel``'s module for ``target`` ("cpu" or "cuda")."""
    module = kernel.module
    if block_dim:
        module.options["block_dim"] = block_dim
    original = type(module)._run_codegen

    def capture(self, options, is_cpu):
        source = original(self, options, is_cpu)[0]
        raise _Source(source)

    type(module)._run_codegen = capture
    try:
        with tempfile.TemporaryDirectory() as out:
            args = dict(device="cpu") if target == "cpu" else dict(arch=90, use_ptx=False)
            wp.compile_aot_module(module, module_dir=out, strip_hash=True, **args)
    except _Source as s:
        return s.source
    finally:
        type(module)._run_codegen = original
    raise RuntimeError("Warp generated no source")


_QUALIFIED = re.compile(r"\b(?:[A-Za-z0-9_]+?__locals__)+([A-Za-z0-9_]+?)(_\d+)?\b")


def normalised(source: str) -> str:
    """``source`` without comments, line directives and blank lines, its generated names numbered
    in order of first appearance (the short Python name kept)."""
    source = re.sub(r"/\*.*?\*/", "", source, flags=re.S)
    lines = []
    for line in source.splitlines():
        line = re.sub(r"//.*", "", line).rstrip()
        if line.strip() and not line.lstrip().startswith("#line"):
            lines.append(line)
    names = {}

    def rename(m):
        key = m.group(0)
        if key not in names:
            names[key] = f"F{len(names)}_{m.group(1)}"
        return names[key]

    return _QUALIFIED.sub(rename, "\n".join(lines)) + "\n"


def sass_digest(kernel, block_dim: int = 0) -> str:
    """SHA-256 of the sm_90 cubin's code sections (.text*), in order, for ``kernel``'s module."""
    module = kernel.module
    if block_dim:
        module.options["block_dim"] = block_dim
    with tempfile.TemporaryDirectory() as out:
        (cubin,) = wp.compile_aot_module(module, arch=90, module_dir=out, use_ptx=False, strip_hash=True)
        data = open(cubin, "rb").read()
    shoff, = struct.unpack_from("<Q", data, 0x28)
    shentsize, shnum, shstrndx = struct.unpack_from("<HHH", data, 0x3A)
    sections = [struct.unpack_from("<IIQQQQIIQQ", data, shoff + i * shentsize) for i in range(shnum)]
    names = sections[shstrndx]
    digest = hashlib.sha256()
    for name, _, _, _, offset, size, *_ in sections:
        label = data[names[4] + name: data.index(b"\0", names[4] + name)]
        if label.startswith(b".text"):
            digest.update(data[offset: offset + size])
    return digest.hexdigest()


def kernels():
    """(label, kernel, block_dim) of every kernel compared."""
    from abd_gym.constitutions import affine_body, drive
    from abd_gym.sim import coordinates

    out = []
    for dtype in (wp.float32, wp.float64):
        t = "f32" if dtype == wp.float32 else "f64"
        ab = affine_body.kernels(dtype)
        out += [(f"affine_body.body_terms.{t}", ab.body_terms, 0), (f"affine_body.body_report.{t}", ab.body_report, 0),
                (f"drive.{t}", drive.kernel(dtype).kernel, 0),
                (f"coordinates.restart_engaged.{t}", coordinates.restart_funcs(dtype)[1], 0)]  # fmt: skip
        for passive in (False, True):
            begin, coords = coordinates.kernels(dtype, passive)
            out += [(f"coordinates.begin_step.{t}.passive{int(passive)}", begin, 0),
                    (f"coordinates.coordinates.{t}.passive{int(passive)}", coords, 0)]  # fmt: skip
    return out + staged_kernels() + fused_kernels()


def staged_kernels():
    """The staged (reference) step's kernels, dense (its prediction, Newton direction, line search
    and finalisation), float32 and float64."""
    from abd_gym.solver import kernels as staged

    out = []
    for dtype in (wp.float32, wp.float64):
        t = "f32" if dtype == wp.float32 else "f64"
        for name, kernel in staged.kernels(dtype).items():
            if isinstance(kernel, wp.Kernel):
                out.append((f"staged.{name}.{t}", kernel, 0))
    return out


def fused_kernels():
    """The fused step of a few scenes, as the solver builds it: lane-split (one launch), a thread
    per world in shared memory and in global memory."""
    import gymnasium as gym

    import abd_gym  # noqa: F401 -- registers the ids
    from abd_gym.bench.speed import CASES
    from abd_gym.sim.model import Model
    from abd_gym.solver.fused import fused_kernel
    from abd_gym.solver.solver import SolverSettings
    from abd_gym.solver.terms import fused_flags

    scenes = {}
    for task in ("CartPole-v0", "Acrobot-v0", "InvertedPendulum-v5", "FourBar-v0"):
        env = gym.make_vec(f"abd_gym/{task}", num_envs=1, vectorization_mode="vector_entry_point", device="cpu")
        scenes[task] = env.unwrapped.scene
        env.close()
    scenes["chain5"] = CASES["chain5"]["scene"]()
    out = []
    for name, scene in scenes.items():
        m = Model(scene, num_worlds=1, device="cpu")
        own, folds = fused_flags(m)
        common = dict(n=m.system_size, axis=m.axis, quadratic=float(SolverSettings.quadratic_stop), exact=m.stiff,
                      limits=tuple(len(m.limit_joints[kind]) for kind in ("revolute", "prismatic")))  # fmt: skip
        forms = {"lanes": dict(scratch="lanes", cuda=True, block=32, bracket=True),
                 "shared": dict(scratch="shared", cuda=True, block=24, bracket=False, band=m.banded, secant=True),
                 "global": dict(scratch="global", bracket=False, envelope=m.envelope)}  # fmt: skip
        for form, kw in forms.items():
            kernel = fused_kernel(wp.float32, own, folds, **common, **kw)[0]
            out.append((f"fused.{name}.{form}", kernel, kw.get("block", 0)))
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True, help="folder for the normalised sources and digests.txt")
    parser.add_argument("--sass", action="store_true", help="also digest the sm_90 machine code")
    parser.add_argument("--only", default="", help="comma-separated label prefixes to keep")
    args = parser.parse_args()
    wp.config.quiet = True
    wp.init()
    os.makedirs(args.out, exist_ok=True)
    keep = [p for p in args.only.split(",") if p]
    rows = []
    for label, kernel, block in kernels():
        if keep and not any(label.startswith(p) for p in keep):
            continue
        for target in ("cpu", "cuda"):
            text = normalised(generated_source(kernel, target, block))
            with open(os.path.join(args.out, f"{label}.{target}.txt"), "w") as f:
                f.write(text)
            rows.append(f"{label} {target} {hashlib.sha256(text.encode()).hexdigest()}")
        if args.sass:
            rows.append(f"{label} sm_90 {sass_digest(kernel, block)}")
        print(rows[-1], flush=True)
    with open(os.path.join(args.out, "digests.txt"), "w") as f:
        f.write("\n".join(rows) + "\n")


if __name__ == "__main__":
    main()
