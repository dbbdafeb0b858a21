"""The layer rules and the shape of the tree (issue 20; docs/architecture.md).

- ``lint-imports`` with the contracts of pyproject.toml's ``[tool.importlinter]``: drivers and estimation import
  nothing else of ours; simulators import drivers' codecs and estimation only; no cycles among the sub-packages of
  drivers, estimation and simulators.
- No import cycle between any two modules of the four packages (imports inside functions count; imports under
  ``if TYPE_CHECKING:`` do not: they never run).
- No module over 800 lines (the packages, tests, benchmarks, hil), except the ones listed below, which may only shrink (each is waiting for its split).
"""
from __future__ import annotations

import os
from pathlib import Path

import grimp
import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("drivers", "estimation", "simulators", "rig")
MAX_LINES = 800
#: modules over MAX_LINES still to be split (issue 20), with their length when listed: they may only shrink
LONG_MODULES = {"rig/capture_folder.py": 1144, "estimation/diffusion.py": 1361, "estimation/gradients.py": 1205}


def test_the_import_contracts_hold() -> None:
    from importlinter.cli import lint_imports

    cwd = os.getcwd()
    os.chdir(ROOT)
    try:
        code = lint_imports(config_filename=str(ROOT / "pyproject.toml"), no_cache=True, no_logo=True)
    finally:
        os.chdir(cwd)
    assert code == 0, "lint-imports: a layer contract is broken (its report is above)"


def _strongly_connected(edges: dict[str, set[str]]) -> list[list[str]]:
    """Tarjan's strongly connected components with more than one module (iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    out: list[list[str]] = []
    counter = 0
    for root in sorted(edges):
        if root in index:
            continue
        work = [(root, iter(sorted(edges[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            v, it = work[-1]
            for w in it:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(edges.get(w, ())))))
                    break
                if w in on_stack:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on_stack.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        out.append(sorted(comp))
    return out


def test_the_cycle_finder_finds_a_cycle() -> None:
    assert _strongly_connected({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _strongly_connected({"a": {"b"}, "b": set()}) == []


def test_no_import_cycle_between_modules() -> None:
    graph = grimp.build_graph(*PACKAGES, exclude_type_checking_imports=True)
    edges = {m: set(graph.find_modules_directly_imported_by(m)) for m in graph.modules}
    assert _strongly_connected(edges) == []


def test_no_module_over_800_lines() -> None:
    too_long = {}
    for pkg in PACKAGES + ("tests", "benchmarks", "hil"):
        for path in sorted((ROOT / pkg).rglob("*.py")):
            rel = path.relative_to(ROOT).as_posix()
            n = len(path.read_text().splitlines())
            if n > LONG_MODULES.get(rel, MAX_LINES):
                too_long[rel] = n
    assert not too_long, f"modules over {MAX_LINES} lines (or grown while waiting for their split): {too_long}"


@pytest.mark.parametrize("rel", sorted(LONG_MODULES))
def test_listed_long_modules_still_exist(rel: str) -> None:
    """A listed module that was split or removed must leave the list (so the list cannot hide a new one)."""
    path = ROOT / rel
    assert path.is_file() and len(path.read_text().splitlines()) > MAX_LINES, f"{rel}: take it off LONG_MODULES"
