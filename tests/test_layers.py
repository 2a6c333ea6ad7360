"""The package's import graph: no cycle, and imports flow one way.

Layers, lowest first: the physics (every module of abd_gym not named below: scene, model, state,
constitutions, solver, fused step, plan, simulator and their helpers); the vector-env layer (the
task base and the env machinery over one Simulator); the tasks and the training code
(abd_gym.envs, abd_gym.agents); the benchmarks, which time all of them.  A module imports only from
its own layer or lower ones, and the package itself (``abd_gym/__init__``) only from the physics
and ``registration`` (whose entry points name the tasks by string).  Read from the source with
``ast``: nothing is imported to check it.
"""
import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent / "abd_gym"
ENV_LAYER = {"vector_env", "single_env", "task", "env_arrays", "env_spaces", "episodes", "outcome", "randomize", "pending",
             "device_step", "step_graph", "autoreset", "env_kernels", "render", "registration"}  # fmt: skip
BENCH = {"bench", "bench_compare", "bench_accuracy", "bench_robustness", "peer_cases"}


def modules() -> dict:
    """{dotted name below abd_gym ("" for the package): path}."""
    out = {}
    for path in ROOT.rglob("*.py"):
        parts = path.relative_to(ROOT).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def imports(name: str, path: Path, known: dict) -> set:
    """The abd_gym modules ``name`` imports (a ``from pkg import sub`` counts as sub when sub is a module)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".") if package else []
                base = base[: len(base) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            elif (node.module or "").startswith("abd_gym"):
                target = node.module[len("abd_gym."):] if node.module != "abd_gym" else ""
            else:
                continue
            subs = {f"{target}.{a.name}".lstrip(".") for a in node.names} & set(known)
            out |= subs if len(subs) == len(node.names) else subs | {target}
        elif isinstance(node, ast.Import):
            out |= {a.name[len("abd_gym."):] for a in node.names if a.name.startswith("abd_gym.")}
    return {m for m in out if m in known and m != name} | {m for m in out if m.split(".")[0] in ("envs", "agents")}


def layer(name: str) -> int:
    top = name.split(".")[0]
    return 3 if top in BENCH else 2 if top in ("envs", "agents", "configs") else 1 if top in ENV_LAYER else 0


GRAPH = {name: imports(name, path, modules()) for name, path in modules().items()}


def test_no_import_cycle():
    seen, done = set(), set()

    def visit(node, trail):
        assert node not in seen - done, f"import cycle: {' -> '.join(trail + [node])}"
        if node in done:
            return
        seen.add(node)
        for nxt in sorted(GRAPH.get(node, ())):
            visit(nxt, trail + [node])
        done.add(node)

    for node in sorted(GRAPH):
        visit(node, [])


def test_imports_flow_one_way():
    upward = [(a, b) for a, targets in GRAPH.items() if a for b in targets if layer(b) > layer(a)]
    assert not upward, f"modules importing from a higher layer: {upward}"
    package = {b for b in GRAPH[""] if layer(b) > 0}
    assert package <= {"registration"}, f"abd_gym/__init__ imports {sorted(package)}"
