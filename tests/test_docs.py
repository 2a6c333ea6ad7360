"""The documents and ``results/`` cite each other both ways, and the code they name exists.

Every ``results/...`` path named in README.md or docs/ exists, and every file under ``results/``
is named there (directly, by its folder, or by a ``*`` pattern), so that each figure traces to its
raw output and ``results/`` holds nothing the documents do not use.  Every source file the
documents name (``path/like.py``, ``scene.py``, ``configs/x.yaml``) and every ``abd_gym.x.y``
module or attribute exists, so that a module moved or renamed leaves no stale pointer.
"""

import ast
import fnmatch
import pathlib
import re

ROOT = pathlib.Path(__file__).resolve().parents[1]
RESULTS = ROOT / "results"
PATH = re.compile(r"results/[A-Za-z0-9_./*-]*[A-Za-z0-9_/*-]")
PERFORMANCE_MAX_LINES = 400
# a source path: folders and a file name, or a bare module file name (not a URL's tail)
SOURCE = re.compile(r"(?<![\w/.:-])((?:[A-Za-z0-9_.-]+/)*[A-Za-z0-9_]+\.py|(?:[A-Za-z0-9_.-]+/)+[A-Za-z0-9_]+\.yaml)\b")
DOTTED = re.compile(r"\babd_gym(?:\.[A-Za-z_][A-Za-z0-9_]*)+")


def _documents():
    return [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def _cited():
    cited = set()
    for doc in _documents():
        cited.update(m.group(0).rstrip("/") for m in PATH.finditer(doc.read_text()))
    return cited


def _result_files():
    return {p.relative_to(ROOT).as_posix() for p in RESULTS.rglob("*") if p.is_file()}


def _covers(citation, path):
    return (path == citation or path.startswith(citation + "/")
            or ("*" in citation and fnmatch.fnmatch(path, citation)))


def test_every_cited_result_exists():
    files = _result_files()
    missing = sorted(c for c in _cited() if not any(_covers(c, f) for f in files))
    assert not missing, f"cited in README.md or docs/ but not in results/: {missing}"


def test_every_result_is_cited():
    cited = _cited()
    uncited = sorted(f for f in _result_files() if not any(_covers(c, f) for c in cited))
    assert not uncited, f"in results/ but cited nowhere in README.md or docs/: {uncited}"


def test_performance_reads_in_ten_minutes():
    lines = (ROOT / "docs" / "performance.md").read_text().splitlines()
    assert len(lines) <= PERFORMANCE_MAX_LINES, f"docs/performance.md has {len(lines)} lines"


def _sources():
    return {p.relative_to(ROOT).as_posix() for pattern in ("*.py", "*.yaml") for p in ROOT.rglob(pattern)
            if ".git" not in p.parts}


def _names_file(path, files):
    """``path`` is a file of the repository or its path's tail (``fused/newton.py``, ``plan.py``)."""
    return any(f == path or f.endswith("/" + path) for f in files)


def test_every_named_source_file_exists():
    files = _sources()
    stale = sorted({f"{doc.name}: {m.group(1)}" for doc in _documents() for m in SOURCE.finditer(doc.read_text())
                    if not _names_file(m.group(1), files)})
    assert not stale, f"source files named in README.md or docs/ that do not exist: {stale}"


PACKAGES = {"envs": ROOT / "envs", "agents": ROOT / "agents", "configs": ROOT / "configs"}


def _defined(source):
    """The names a module's source binds at its top level."""
    names = set()
    for node in ast.parse(source).body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            names.update((a.asname or a.name).split(".")[0] for a in node.names)
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            names.update(n.id for t in targets for n in ast.walk(t) if isinstance(n, ast.Name))
    return names


def _resolves(dotted):
    """``abd_gym.a.b.C`` names a module of the tree, and its first name after the module is bound
    there (read from the source, nothing imported)."""
    parts = dotted.split(".")[1:]
    folder, module, rest = ROOT / "abd_gym", ROOT / "abd_gym" / "__init__.py", parts
    if parts and parts[0] in PACKAGES:
        folder, module, rest = PACKAGES[parts[0]], PACKAGES[parts[0]] / "__init__.py", parts[1:]
    while rest:
        if (folder / rest[0] / "__init__.py").is_file():
            folder, module, rest = folder / rest[0], folder / rest[0] / "__init__.py", rest[1:]
        elif (folder / f"{rest[0]}.py").is_file():
            module, rest = folder / f"{rest[0]}.py", rest[1:]
            break
        else:
            break
    return not rest or rest[0] in _defined(module.read_text())


def test_every_named_module_exists():
    names = {m.group(0) for doc in _documents() for m in DOTTED.finditer(doc.read_text())}
    stale = sorted(n for n in names if not _resolves(n))
    assert not stale, f"abd_gym names in README.md or docs/ that are not in the tree: {stale}"


def test_module_map_names_every_module():
    """design.md §7 places every module of the package (constitutions/ as one module a
    constitution, named by its folder)."""
    text = (ROOT / "docs" / "design.md").read_text()
    table = text[text.index("## 7. Module map"):text.index("### 7.1")]
    modules = [p for p in (ROOT / "abd_gym").rglob("*.py")
               if p.name not in ("__init__.py", "__main__.py") and p.parent.name != "constitutions"]
    missing = sorted(p.relative_to(ROOT).as_posix() for p in modules if f"`{p.name}`" not in table)
    assert not missing, f"modules design.md's module map does not place: {missing}"
