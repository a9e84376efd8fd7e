"""Shared test set-up: offline, deterministic, caches inside a temporary directory."""

from __future__ import annotations

import atexit
import json
import os
import shutil
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
