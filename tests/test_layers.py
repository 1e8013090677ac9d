"""The package's floors: every import goes down or sideways, never up, and no import is a cycle.

Every import of ``mrta_rl`` is read from the source with ``ast``: at module level, inside
functions and under ``if TYPE_CHECKING:`` alike, absolute or relative. ``from pkg import name``
points at the submodule ``pkg.name`` where there is one, else at ``pkg``. A module's floor is
that of its package below ``mrta_rl`` (``mrta_rl.learners.tabular.dql``: ``learners``), or its
own for a top-level module (``mrta_rl.rules``: the core).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "mrta_rl"

# the floors, bottom to top: a module imports its own floor and the floors below it
FLOORS: tuple[tuple[str, ...], ...] = (
    # the core: settings and their checks, errors, shared types, where the configs are, the
    # allocation rules, the loops by name and a run dir's files; none imports a floor above
    (
        "mrta_rl",
        "types",
        "config",
        "errors",
        "logs",
        "checked_files",
        "config_guard",
        "conf_paths",
        "splits",
        "rules",
        "loops",
        "run_layout",
    ),
    ("systems",),  # robot teams
    ("partition",),  # the subG partition of a team
    ("envs",),  # the auction dynamics and its views
    ("metrics", "priors"),  # what is measured of an env's episodes; the priors' rules on an env
    ("learners",),  # act on an env; never build one, never load a run
    ("cluster",),  # a learner's work on Ray workers; never build a run
    ("runners",),  # build env and learner from a config, train, evaluate, write the run dir
    ("reports", "bench"),  # read run dirs; time runs
    ("commands",),  # the console scripts
)
CORE = FLOORS[0]
# reports read run dirs as data: the core's files and checks, nothing that runs a learner
REPORTS_ALLOWED = {*CORE, "reports"}
TORCH = ("torch", "torchrl", "tensordict")


def modules(root: Path = ROOT) -> dict[str, Path]:
    """Every module of the package: dotted name -> file (a package is its ``__init__.py``)."""
    found = {}
    for path in sorted((root / PACKAGE).rglob("*.py")):
        parts = list(path.relative_to(root).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        found[".".join(parts)] = path
    return found


def imports(name: str, path: Path, known: dict[str, Path]) -> set[str]:
    """The names a module imports (every ``import`` node of its source), resolved.

    A name of the package resolves to its module (the longest known prefix); any other is
    kept as written (``torch``, ``numpy.random``).
    """
    base = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    targets: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                source = ".".join(base[: len(base) - node.level + 1] + [node.module or ""])
                source = source.rstrip(".")
            else:
                source = node.module or ""
            for alias in node.names:
                full = f"{source}.{alias.name}"
                targets.add(full if full in known else source)
    resolved = set()
    for target in targets:
        if target.split(".")[0] != PACKAGE:
            resolved.add(target)
            continue
        while target not in known:
            target = target.rpartition(".")[0]
        if target != name:
            resolved.add(target)
    return resolved


def graph(root: Path = ROOT) -> dict[str, set[str]]:
    """Module -> the names it imports (modules of the package, and outside names)."""
    known = modules(root)
    return {name: imports(name, path, known) for name, path in known.items()}


def floor_of(module: str) -> int:
    """The floor of a module of the package (:data:`FLOORS`).

    Raises:
        KeyError: for a module of no floor (a new top-level module or package: give it one).
    """
    parts = module.split(".")
    key = parts[1] if len(parts) > 1 else parts[0]
    for level, names in enumerate(FLOORS):
        if key in names:
            return level
    raise KeyError(f"{module}: no floor; add {key!r} to FLOORS in tests/test_layers.py")


def floor_name(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else parts[0]


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The import cycles: strongly connected sets of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for other in sorted(edges[node] & edges.keys()):
            if other not in index:
                visit(other)
                low[node] = min(low[node], low[other])
            elif other in on_stack:
                low[node] = min(low[node], index[other])
        if low[node] == index[node]:
            component = []
            while True:
                other = stack.pop()
                on_stack.discard(other)
                component.append(other)
                if other == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(edges):
        if node not in index:
            visit(node)
    return found


def upward(edges: dict[str, set[str]]) -> list[str]:
    """``a -> b`` for every import of a module ``b`` on a floor above ``a``'s."""
    return sorted(
        f"{a} -> {b}"
        for a, targets in edges.items()
        for b in targets
        if b in edges and floor_of(b) > floor_of(a)
    )


def reports_reach(edges: dict[str, set[str]]) -> list[str]:
    """Imports of the reports beyond the core, and of torch."""
    return sorted(
        f"{a} -> {b}"
        for a, targets in edges.items()
        if floor_name(a) == "reports"
        for b in targets
        if (b in edges and floor_name(b) not in REPORTS_ALLOWED) or b.split(".")[0] in TORCH
    )


EDGES = graph()


def test_every_module_has_a_floor():
    assert [m for m in EDGES if floor_name(m) not in {n for f in FLOORS for n in f}] == []


def test_no_import_cycle():
    assert cycles(EDGES) == []


def test_no_import_goes_up_a_floor():
    assert upward(EDGES) == []


def test_reports_import_the_core_only_and_no_torch():
    assert reports_reach(EDGES) == []


# ------------------------------------------------------------------ the walk itself, by hand
@pytest.fixture
def tiny(tmp_path: Path) -> Path:
    """A package of three floors written by hand: mrta_rl.{rules, envs.view, learners.act}."""
    files = {
        "__init__.py": "",
        "rules.py": "import numpy\n",
        "envs/__init__.py": "from mrta_rl.envs.view import View\n",
        "envs/view.py": (
            "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
            "    from mrta_rl.learners.act import act\n"
        ),
        "learners/__init__.py": "",
        "learners/act.py": (
            "from .. import rules\n\ndef act():\n    from mrta_rl.envs import view\n"
        ),
        "reports/__init__.py": "import torch\nfrom mrta_rl.learners import act\n",
    }
    for name, text in files.items():
        path = tmp_path / PACKAGE / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return tmp_path


def test_the_walk_reads_function_level_relative_and_type_checking_imports(tiny):
    edges = graph(tiny)
    assert edges["mrta_rl.rules"] == {"numpy"}
    assert edges["mrta_rl.learners.act"] == {"mrta_rl.rules", "mrta_rl.envs.view"}
    assert edges["mrta_rl.envs.view"] == {"typing", "mrta_rl.learners.act"}  # TYPE_CHECKING
    assert edges["mrta_rl.reports"] == {"torch", "mrta_rl.learners.act"}
    assert cycles(edges) == [["mrta_rl.envs.view", "mrta_rl.learners.act"]]
    assert upward(edges) == ["mrta_rl.envs.view -> mrta_rl.learners.act"]
    assert reports_reach(edges) == [
        "mrta_rl.reports -> mrta_rl.learners.act",
        "mrta_rl.reports -> torch",
    ]
