"""The package's import graph: no cycle, and imports flow one way.

Layers, lowest first, one folder of abd_gym or more each: the physics (``core``, ``constitutions``,
``sim``, ``solver``, ``mjcf``); the vector-env layer (``vector``: the task base and the env
machinery over one Simulator); the tasks and the training code (abd_gym.envs, abd_gym.agents); the
benchmarks (``bench``), which time all of them.  A module imports only from its own layer or lower
ones, and the package itself (``abd_gym/__init__``) only from the physics and
``vector.registration`` (whose entry points name the tasks by string).  Every module lives in a
layer's folder.  Read from the source with ``ast``: nothing is imported to check it.
"""
import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent / "abd_gym"
LAYERS = {"core": 0, "constitutions": 0, "sim": 0, "solver": 0, "mjcf": 0, "vector": 1, "envs": 2, "agents": 2,
          "configs": 2, "bench": 3}  # fmt: skip


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
    return LAYERS[name.split(".")[0]]


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
    assert package <= {"vector.registration"}, f"abd_gym/__init__ imports {sorted(package)}"


def test_every_module_lives_in_a_layer_folder():
    loose = [name for name in GRAPH if name and name.split(".")[0] not in LAYERS]
    assert not loose, f"modules outside the layers' folders: {loose}"


# the modules of the vector env's device step, which reach the simulator through its public calls
ENV_STEP = ("vector.device_step", "vector.step_graph", "vector.outcome")
SIMULATOR_INSIDES = {"state", "solver", "model"}


def _is_simulator(node) -> bool:
    return (isinstance(node, ast.Name) and node.id == "sim") or (isinstance(node, ast.Attribute) and node.attr == "sim")


def test_the_env_step_calls_the_simulator_through_its_public_calls():
    paths = modules()
    reached = sorted({f"{name}: sim.{node.attr}" for name in ENV_STEP
                      for node in ast.walk(ast.parse(paths[name].read_text()))
                      if isinstance(node, ast.Attribute) and _is_simulator(node.value)
                      and (node.attr in SIMULATOR_INSIDES or node.attr.startswith("_"))})  # fmt: skip
    assert not reached, f"the env step reaches into the simulator: {reached}"


def test_the_physics_never_holds_an_env():
    held = sorted({f"{name}: {getattr(node, 'id', None) or getattr(node, 'attr', None) or node.arg}"
                   for name, path in modules().items() if name and layer(name) == 0
                   for node in ast.walk(ast.parse(path.read_text()))
                   if (isinstance(node, ast.Name) and node.id == "env")
                   or (isinstance(node, ast.Attribute) and node.attr == "env")
                   or (isinstance(node, ast.arg) and node.arg == "env")})  # fmt: skip
    assert not held, f"physics modules that hold an env: {held}"
