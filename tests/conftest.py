"""Shared test set-up: offline, deterministic, caches inside a temporary directory."""

from __future__ import annotations

import atexit
import json
import os
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch

from sr_imitation.offscreen import setup_offscreen_rendering

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("HF_DATASETS_OFFLINE", "1")
# The datasets' digest cache (substrates/act/dataset_identity.py) of this test process, not the user's: the suite
# hashes thousands of throwaway datasets. Subprocesses (and xdist's workers) inherit it; the process that made the
# folder removes it when it exits.
if "SR_DIGEST_CACHE" not in os.environ:
    _digest_dir = tempfile.mkdtemp(prefix="sr_digest_cache_")
    atexit.register(shutil.rmtree, _digest_dir, ignore_errors=True)
    os.environ["SR_DIGEST_CACHE"] = os.path.join(_digest_dir, "file_digests.json")
setup_offscreen_rendering()


@pytest.fixture(autouse=True)
def _seed_everything():
    torch.manual_seed(0)
    np.random.seed(0)
    yield


_DURATIONS = Path(__file__).with_name("durations.json")
"""Seconds each test file took in a measured run (tools/test_durations.py writes it)."""


def pytest_collection_modifyitems(config, items):
    """The heaviest test files first (:func:`heaviest_files_first`): .ci/test.sh gives whole files to the two workers
    in this order (``--dist loadfile --no-loadscope-reorder``), so neither ends up alone with a long file at the end."""
    seconds = json.loads(_DURATIONS.read_text()) if _DURATIONS.is_file() else {}
    items[:] = heaviest_files_first(items, seconds)


def heaviest_files_first(items: list, seconds: dict[str, float]) -> list:
    """``items`` (anything with a pytest ``nodeid``) ordered by their file's ``seconds``, heaviest first, each file's
    items in their own order and files of equal weight in collection order. A file not in ``seconds`` counts as 0 s:
    the order changes how long the suite takes, never what it checks."""
    first_seen: dict[str, int] = {}
    for index, item in enumerate(items):
        first_seen.setdefault(item.nodeid.split("::", 1)[0], index)

    def key(item) -> tuple[float, int]:
        name = item.nodeid.split("::", 1)[0]
        return -seconds.get(name, 0.0), first_seen[name]

    return sorted(items, key=key)


ARCHITECTURE = Path(__file__).resolve().parents[1] / "docs" / "ARCHITECTURE.md"


def recipe_code(heading: str) -> str:
    """The first python block of docs/ARCHITECTURE.md's section ``### <heading>``.

    Args:
        heading: the recipe's heading (``Adding a method``, ``Adding a substrate``).

    Returns:
        The block's text, as a file holds it.
    """
    recipe = ARCHITECTURE.read_text().split(f"### {heading}", 1)[1].split("\n## ", 1)[0]
    return recipe.split("```python\n", 1)[1].split("\n```", 1)[0] + "\n"


def recipe_init() -> str:
    """The substrate folder's ``__init__.py``: the first python block of docs/ARCHITECTURE.md's recipe "Adding a
    substrate" (the toy's, ``module = "tests.stream.toy"``)."""
    return recipe_code("Adding a substrate")


def recipe_method() -> str:
    """The method file of docs/ARCHITECTURE.md's recipe "Adding a method" (``tests/stream/l2_anchor.py``, whole)."""
    return recipe_code("Adding a method")


@pytest.fixture
def sr_train(tmp_path_factory, monkeypatch):
    """``sr-train`` (:func:`sr_imitation.cli.train_main`) with the toy substrate added as the recipe says: a folder
    ``toy/`` of the substrates package whose ``__init__.py`` is the recipe's, in a temporary folder on
    ``sr_imitation.substrates.__path__`` (so that the test writes nothing into the package); nothing else is
    registered or edited. A tree that holds the folder already (the recipe done for real) uses its own."""
    import sr_imitation.substrates as substrates_package
    from sr_imitation import cli

    if "toy" not in substrates_package.discover():
        root = tmp_path_factory.mktemp("substrates")
        (root / "toy").mkdir()
        (root / "toy" / "__init__.py").write_text(recipe_init())
        monkeypatch.setattr(substrates_package, "__path__", [*substrates_package.__path__, str(root)])
    yield cli.train_main
    substrates_package.SUBSTRATES.pop("toy", None)
    sys.modules.pop("sr_imitation.substrates.toy", None)
