"""docs/ARCHITECTURE.md's maps against the code, so that moving or adding a file without updating them fails here.

The maps are the fenced blocks of the document that list files: a line's first word names a file (``engine.py``) or a
folder (``methods/``, ``sr_imitation/stream/``), relative to the folder above it in the same block (a line indented
less), or to the package (``envs/needle/``) or the repository (``sr_imitation/...``, ``policies/...``) when it has a
slash. Checked: every file and folder a map names exists; the folders whose every module a map lists (the package's
top level, ``core``, ``infra``, ``stream``, ``stream/methods``, ``reporting``, ``substrates`` and the two
substrates' folders) list all of theirs, except what the registries know (a method file that registers a method, a
substrate folder that registers a substrate: adding either is one file or folder and no edit here, the recipes of
the document); every method file the stream's method list names registers a method; the results schema version the
document states is the code's; the layer table is tests/test_architecture.py's.
"""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DOC = REPO / "docs" / "ARCHITECTURE.md"
COMPLETE = ("sr_imitation", "sr_imitation/core", "sr_imitation/infra", "sr_imitation/stream",
            "sr_imitation/stream/methods", "sr_imitation/reporting", "sr_imitation/substrates",
            "sr_imitation/substrates/act", "sr_imitation/substrates/sac", "sr_imitation/substrates/sac/methods")
"""Folders whose every module (and subfolder) the maps must list."""
ROOTS = ("sr_imitation/", "policies/", "tests/", "docs/", "configs/", "datasets/", ".ci/", "tools/")


def _blocks(text: str) -> list[list[str]]:
    """The lines of every fenced block opened by a bare fence (not ```bash and the like: commands, not maps)."""
    blocks, current, bare = [], None, False
    for line in text.splitlines():
        if line.startswith("```"):
            if current is None:
                current, bare = [], line.strip() == "```"
            else:
                if bare:
                    blocks.append(current)
                current = None
        elif current is not None:
            current.append(line)
    return blocks


def _names(word: str) -> list[str]:
    """The file or folder names a line's first word holds (``a.py,`` and ``a.py, b.py`` lists: the first)."""
    word = word.rstrip(",")
    return [word] if word.endswith((".py", "/")) else []


def mapped_paths(text: str) -> set[str]:
    """Every file and folder the document's maps name, as repository paths."""
    found: set[str] = set()
    for block in _blocks(text):
        stack: list[tuple[int, str]] = []  # (indent, folder) of the enclosing folders
        for line in block:
            if not line.strip():
                continue
            indent = len(line) - len(line.lstrip())
            first = line.split()[0]
            names = _names(first)
            # a line's further names joined by ", " (``nash_mtl.py, pcgrad.py``)
            rest = line.split()[1:]
            while first.endswith(",") and rest and _names(rest[0]):
                names += _names(rest[0])
                first, rest = rest[0], rest[1:]
            if not names:
                continue
            while stack and stack[-1][0] >= indent:
                stack.pop()
            for name in names:
                if name.startswith(ROOTS) or name == "pyproject.toml":
                    path = name
                elif "/" in name.rstrip("/") and not stack:
                    path = f"sr_imitation/{name}"
                elif stack:
                    path = f"{stack[-1][1]}{name}"
                else:
                    path = name
                found.add(path.rstrip("/"))
                if name.endswith("/"):
                    stack.append((indent, path))
    return found


def test_every_file_and_folder_the_maps_name_exists():
    missing = sorted(p for p in mapped_paths(DOC.read_text()) if not (REPO / p).exists())
    assert missing == [], f"docs/ARCHITECTURE.md names what is not there: {missing}"


def registered_paths() -> set[str]:
    """The repository paths the registries know: every method's module file under ``sr_imitation/`` and every
    substrate folder of ``sr_imitation/substrates/``."""
    from sr_imitation.stream import METHODS
    from sr_imitation.substrates import discover

    substrates = discover()  # every substrate folder, with the methods of its own
    methods = {cls.__module__.replace(".", "/") + ".py" for cls in METHODS.values()
               if cls.__module__.startswith("sr_imitation.")}
    folders = {cmd.__module__.replace(".", "/") for cmd in substrates.values()
               if cmd.__module__.startswith("sr_imitation.substrates.")}
    return methods | folders


def test_the_maps_list_every_module_of_the_folders_they_cover():
    mapped = mapped_paths(DOC.read_text())
    known = registered_paths()
    unlisted = []
    for folder in COMPLETE:
        for entry in sorted((REPO / folder).iterdir()):
            if entry.name.startswith(("_", ".")) or (entry.is_file() and entry.suffix != ".py"):
                continue
            if entry.is_dir() and not any(entry.glob("*.py")):
                continue
            path = f"{folder}/{entry.name}"
            if path in known:
                continue  # the registries list it (sr-train --help, its errors): the recipes need no edit here
            if path not in mapped and not any(m.startswith(f"{path}/") for m in mapped):
                unlisted.append(path)
    assert unlisted == [], f"docs/ARCHITECTURE.md's maps do not list {unlisted}"


def test_the_registries_know_the_package_s_methods_and_substrates():
    """What :func:`registered_paths` lets the maps leave out is what the registries hold: the package's method files
    and its two substrates (so that the exemption above cannot hide a file)."""
    known = registered_paths()
    assert {"sr_imitation/stream/methods/ewc.py", "sr_imitation/substrates/sac/methods/componet.py",
            "sr_imitation/substrates/act", "sr_imitation/substrates/sac"} <= known
    assert all((REPO / path).exists() for path in known), known


def test_every_method_file_the_method_list_names_registers_a_method():
    """The stream's method list is checked for what it states by name: each file it names is a method file (a
    new method needs no line here: the registry lists it)."""
    from sr_imitation.stream import METHODS
    from sr_imitation.substrates import discover

    discover()  # a substrate's own methods (componet) register with its folder
    stream = DOC.read_text().split("## The stream engine", 1)[1].split("\n## ", 1)[0]
    listing = stream.split("  methods/", 1)[1].split("\n  rundir.py", 1)[0]
    listed = set(re.findall(r"\b([a-z][a-z0-9_]*)\.py\b", listing)) - {"base", "registry", "composed_actor"}
    modules = {cls.__module__.rsplit(".", 1)[-1] for cls in METHODS.values()}
    assert listed and sorted(listed - modules) == []


def test_the_stated_results_version_is_the_code_s():
    from sr_imitation.reporting.results import RESULTS_VERSION

    stated = set(re.findall(r"RESULTS_VERSION (\d+)", DOC.read_text()))
    assert stated == {str(RESULTS_VERSION)}


def test_the_parser_reads_nested_maps():
    text = "```\nsr_imitation/stream/\n  engine.py  x\n  methods/  y\n    ewc.py, der.py  z\nrl/sac.py  w\n```\n"
    assert mapped_paths(text) == {"sr_imitation/stream", "sr_imitation/stream/engine.py",
                                  "sr_imitation/stream/methods", "sr_imitation/stream/methods/ewc.py",
                                  "sr_imitation/stream/methods/der.py", "sr_imitation/rl/sac.py"}


def test_the_layer_table_is_the_enforced_one():
    from tests.test_architecture import ALLOWED

    section = DOC.read_text().split("### Layers", 1)[1].split("\n#", 1)[0]
    rows = re.findall(r"^\| `([a-z_.*]+)` \| (.*) \|$", section, flags=re.M)
    table = {part: set(re.findall(r"`([a-z_.*]+)`", allowed)) for part, allowed in rows}
    assert table == ALLOWED
