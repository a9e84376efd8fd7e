"""docs/ARCHITECTURE.md's recipes are true as written (issue 88 item 1): in a copy of the tree, a method file and a
substrate folder are added exactly as the recipes show them, and nothing else is edited; the architecture, CLI and
recipe tests pass there, on the copy's code."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import recipe_init, recipe_method

REPO = Path(__file__).resolve().parents[2]
SKIPPED = shutil.ignore_patterns("__pycache__", "*.egg-info", "results", "*.weights", ".venv", "build")
"""Not copied: caches, installs, and docs/results (archived runs: 85 MB no test here reads)."""
DATA_FOLDERS = ("datasets",)
"""Top-level folders of which only the tracked files are copied (the recorded datasets beside them are ignored)."""
TESTS = ("tests/test_architecture.py", "tests/test_architecture_doc.py", "tests/test_cli.py",
         "tests/stream/test_recipes.py")
"""The tests that list files, methods or substrates, and the recipes' own."""


def _tracked() -> list[str]:
    """The repository's tracked files (``git ls-files``), relative to it."""
    listed = subprocess.run(["git", "ls-files", "-z"], cwd=REPO, capture_output=True, text=True, check=True).stdout
    return [path for path in listed.split("\0") if path]


def _copy_tree(root: Path) -> Path:
    """The repository under ``root``: every top-level entry git tracks, as the working tree holds it (edits not yet
    committed included), less :data:`SKIPPED`; of :data:`DATA_FOLDERS` only the tracked files."""
    tracked = _tracked()
    for name in sorted({path.split("/", 1)[0] for path in tracked}):
        source = REPO / name
        if name in DATA_FOLDERS:
            for path in (p for p in tracked if p.startswith(f"{name}/")):
                (root / path).parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(REPO / path, root / path)
        elif source.is_dir():
            shutil.copytree(source, root / name, ignore=SKIPPED)
        elif source.is_file():
            root.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, root / name)
    return root


def _environment(root: Path) -> dict[str, str]:
    """The environment that imports the copy's code: its folders first on the path (``python -P`` adds no other
    folder; the clone's editable installs come after the path), no pytest settings of this session."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTEST_", "COV_"))}
    paths = [root, root / "policies" / "lerobot_policy_act_sr", root / "policies" / "lerobot_env_sr"]
    env["PYTHONPATH"] = os.pathsep.join(str(p) for p in paths)
    return env


def _add_as_the_recipes_say(root: Path) -> None:
    """A method file (the recipe's, named ``l2_pull``, as a contributor names theirs) and a substrate folder (the
    recipe's ``__init__.py``, as written)."""
    method = recipe_method().replace("l2_anchor", "l2_pull").replace("L2Anchor", "L2Pull")
    (root / "sr_imitation" / "stream" / "methods" / "l2_pull.py").write_text(method)
    (root / "sr_imitation" / "substrates" / "toy").mkdir()
    (root / "sr_imitation" / "substrates" / "toy" / "__init__.py").write_text(recipe_init())


@pytest.mark.slow
def test_a_method_file_and_a_substrate_folder_added_as_the_recipes_say_pass_the_tests_with_nothing_else_edited(
        tmp_path):
    root = _copy_tree(tmp_path / "tree")
    _add_as_the_recipes_say(root)
    env = _environment(root)
    probe = ("import sr_imitation, tests, lerobot_policy_act_sr, sr_imitation.stream as s\n"
             "from sr_imitation.substrates import discover\n"
             "print(sr_imitation.__file__, tests.__file__, lerobot_policy_act_sr.__file__)\n"
             "print(sorted(discover()), 'l2_pull' in s.METHODS)\n")
    where = subprocess.run([sys.executable, "-P", "-c", probe], cwd=root, env=env, capture_output=True, text=True,
                           check=True, timeout=300).stdout.splitlines()
    assert all(Path(path).is_relative_to(root) for path in where[0].split()), where  # the copy's code, not the clone's
    assert "'toy'" in where[1] and where[1].endswith("True"), where  # the folder and the file registered themselves
    run = subprocess.run([sys.executable, "-P", "-m", "pytest", "-q", "-p", "no:cacheprovider", *TESTS], cwd=root,
                         env=env, capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stdout[-4000:] + run.stderr[-2000:]
    assert f"rootdir: {root}" in run.stdout or " passed" in run.stdout.splitlines()[-1], run.stdout[-2000:]
