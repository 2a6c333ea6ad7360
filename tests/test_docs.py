"""The documents and ``results/`` cite each other both ways.

Every ``results/...`` path named in README.md or docs/ exists, and every file under ``results/``
is named there (directly, by its folder, or by a ``*`` pattern), so that each figure traces to its
raw output and ``results/`` holds nothing the documents do not use.
"""

import fnmatch
import pathlib
import re

ROOT = pathlib.Path(__file__).resolve().parents[1]
RESULTS = ROOT / "results"
PATH = re.compile(r"results/[A-Za-z0-9_./*-]*[A-Za-z0-9_/*-]")
PERFORMANCE_MAX_LINES = 400


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
