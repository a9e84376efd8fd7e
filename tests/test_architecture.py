"""The package's walls: no import cycles, not even through imports inside functions or under
``TYPE_CHECKING``, and no upward imports between the layers (io, progress < core < infra < stream < substrates <
drivers). Every substrate folder (``sr_imitation/substrates/<name>/``) is a layer of its own with the same allowed
imports, and none imports another. No module of the package is over :data:`MAX_LINES` lines."""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1] / "sr_imitation"

BELOW_SUBSTRATES = {"core", "io", "progress", "infra", "stream", "reporting", "envs", "recorders", "offscreen", "video",
                    "lerobot_compat"}
"""Every layer a substrate may import."""

ALLOWED: dict[str, set[str]] = {
    # atomic writes and checked files: everything is saved through them
    "io": set(),
    # progress bars / log lines of long loops (the sleep's included)
    "progress": set(),
    # the one place that names LeRobot internals which moved between releases
    "lerobot_compat": set(),
    # formulas: memories, aggregation, sleep, excitability, metrics
    "core": {"io", "progress"},
    # run infrastructure: settings fingerprints, run log, provenance, command-line parsing and errors
    "infra": {"core", "io", "progress"},
    # Algorithm 1 and the method plugins: substrate-free
    "stream": {"core", "io", "progress", "infra"},
    # what reads run directories: the shared results schema, summaries, comparisons, paired tests, status
    "reporting": {"core", "io", "progress", "infra", "stream"},
    # the needle world and what records it
    "offscreen": set(),
    "video": {"core", "io", "progress", "infra"},
    "envs": {"core", "io", "progress", "infra", "offscreen", "video"},
    "recorders": {"core", "io", "progress", "infra", "envs", "offscreen", "video", "lerobot_compat"},
    # the substrate registry (sr_imitation/substrates/__init__.py, registry.py): what sr-train looks substrates up in
    "substrates": {"core", "io", "progress", "infra", "stream"},
    # every substrate folder, sr_imitation/substrates/<name>/, is a layer of its own with these imports (its methods
    # and configs with it); none imports another, so a new folder needs no entry here
    "substrates.*": BELOW_SUBSTRATES | {"substrates"},
    # drivers: commands, experiments, benchmarks (anything below them)
    "cli": {"core", "io", "progress", "infra", "stream", "substrates"},
    "main_job": BELOW_SUBSTRATES | {"substrates", "substrates.*"},
    "benchmarks": BELOW_SUBSTRATES | {"substrates", "substrates.*"},
    "experiments": BELOW_SUBSTRATES | {"substrates", "substrates.*", "main_job"},  # grid_benchmark times the runner
}
"""Which top-level parts of ``sr_imitation`` each part may import."""

KNOWN_UPWARD: set[tuple[str, str]] = set()  # none left: a new exception needs its reason here

PLUGINS = ROOT.parent / "policies"

PLUGIN_ALLOWED = {"io", "progress", "core", "infra", "envs", "offscreen", "video", "lerobot_compat"}
"""What of ``sr_imitation`` a LeRobot plugin under ``policies/`` may import: the layers below the substrates (the
ACT substrate, ``substrates/act``, imports the plugin, so the plugin imports nothing of it)."""


def _modules() -> dict[str, Path]:
    out = {}
    for path in ROOT.rglob("*.py"):
        name = ".".join(path.relative_to(ROOT.parent).with_suffix("").parts)
        out[name.removesuffix(".__init__")] = path
    return out


def import_graph() -> dict[str, set[str]]:
    """Module -> the modules of the package it imports anywhere in its file (top level, functions, TYPE_CHECKING).
    ``from package import name`` counts as importing the submodule ``package.name`` when there is one."""
    modules = _modules()
    graph: dict[str, set[str]] = defaultdict(set)
    for name, path in modules.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                targets = [f"{node.module}.{a.name}" if f"{node.module}.{a.name}" in modules else node.module
                           for a in node.names]
            else:
                continue
            for target in targets:
                while target and target not in modules:
                    target = target.rpartition(".")[0]
                if target.startswith("sr_imitation") and target != name:
                    graph[name].add(target)
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def _part(module: str) -> str:
    """The part of the package a module belongs to: its top-level module or folder (``stream``), or for a substrate
    folder's modules the folder (``substrates.act``)."""
    parts = module.split(".")
    if len(parts) > 2 and parts[1] == "substrates" and (ROOT / "substrates" / parts[2]).is_dir():
        return f"substrates.{parts[2]}"
    return parts[1] if len(parts) > 1 else ""


def _layer(part: str) -> str:
    """The layer of ``ALLOWED`` a part is in: every substrate folder is in ``substrates.*``."""
    return "substrates.*" if part.startswith("substrates.") else part


def upward_imports(graph: dict[str, set[str]]) -> list[tuple[str, str]]:
    """The (module, imported module) pairs of ``graph`` that ``ALLOWED`` does not allow (between different parts)."""
    return sorted((m, t) for m, targets in graph.items() for t in targets
                  if _part(m) != _part(t) and _layer(_part(t)) not in ALLOWED[_layer(_part(m))]
                  and (m, t) not in KNOWN_UPWARD)


def _imported_names(path: Path) -> set[str]:
    """Every absolute module (or ``module.name``) the file imports, anywhere in it."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out |= {f"{node.module}.{alias.name}" for alias in node.names}
    return out


def test_plugins_import_only_below_the_substrates():
    files = sorted(PLUGINS.glob("*/*/*.py"))
    assert files  # the plugins are where this test looks
    upward = sorted((str(path.relative_to(PLUGINS)), name) for path in files for name in _imported_names(path)
                    if name.split(".")[0] == "sr_imitation" and _part(name) not in PLUGIN_ALLOWED)
    assert upward == []


def test_no_import_cycles():
    assert _cycles(import_graph()) == []


def test_the_cycle_finder_finds_cycles():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_upward_imports():
    graph = import_graph()
    layers = {_layer(_part(m)) for m in graph} | {_layer(_part(t)) for targets in graph.values() for t in targets}
    assert layers - {""} <= set(ALLOWED), sorted(layers - set(ALLOWED))  # a new part must be placed in a layer
    assert upward_imports(graph) == []
    assert {(m, t) for m, targets in graph.items() for t in targets} >= KNOWN_UPWARD  # stale exceptions go


def test_every_substrate_folder_is_a_layer_of_its_own_that_imports_no_other():
    """A substrate folder is placed by the folder alone (no entry of its own in ALLOWED), and one substrate importing
    another is an upward import."""
    assert _part("sr_imitation.substrates.act.cli") == "substrates.act"
    assert _part("sr_imitation.substrates.sac.methods.componet") == "substrates.sac"
    assert _part("sr_imitation.substrates.registry") == _part("sr_imitation.substrates") == "substrates"
    assert [p for p in ALLOWED if p.startswith("substrates.") and p != "substrates.*"] == []
    folders = sorted(p.name for p in (ROOT / "substrates").iterdir() if (p / "__init__.py").is_file())
    assert {"act", "sac"} <= set(folders)
    graph = {"sr_imitation.substrates.act.cli": {"sr_imitation.substrates.sac.config",
                                                 "sr_imitation.substrates.act.config",
                                                 "sr_imitation.substrates.registry", "sr_imitation.stream.run"},
             "sr_imitation.stream.run": {"sr_imitation.substrates.act.config"},
             "sr_imitation.cli": {"sr_imitation.substrates", "sr_imitation.substrates.sac.cli"}}
    assert upward_imports(graph) == [("sr_imitation.cli", "sr_imitation.substrates.sac.cli"),
                                     ("sr_imitation.stream.run", "sr_imitation.substrates.act.config"),
                                     ("sr_imitation.substrates.act.cli", "sr_imitation.substrates.sac.config")]


MAX_LINES = 600
"""The most lines a module of the package may have (our choice: a file longer than this does several jobs; split it
by job, each file with a one-sentence docstring)."""


def test_no_module_of_the_package_is_over_max_lines():
    long = {str(p.relative_to(ROOT)): n for p in sorted(ROOT.rglob("*.py"))
            if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert long == {}


def test_nothing_installed_imports_the_repository_s_experiments_folder():
    """``experiments/`` (one protocol's analyses, run as ``python -m experiments.<name>`` from the repository root)
    is not installed, so no module of the package, nor of a plugin, may import it."""
    files = [*sorted(ROOT.rglob("*.py")), *sorted(PLUGINS.glob("*/*/*.py"))]
    importing = sorted(str(path) for path in files for name in _imported_names(path)
                       if name == "experiments" or name.startswith("experiments."))
    assert importing == []
