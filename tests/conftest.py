"""Shared test set-up: offline, deterministic, caches inside a temporary directory."""

from __future__ import annotations

import os
import tempfile

import numpy as np
import pytest
import torch

from sr_imitation.offscreen import setup_offscreen_rendering

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("HF_DATASETS_OFFLINE", "1")
# The datasets' digest cache (substrates/act/dataset_identity.py) of this test process, not the user's: the suite
# hashes thousands of throwaway datasets. Subprocesses inherit it.
os.environ.setdefault("SR_DIGEST_CACHE", os.path.join(tempfile.mkdtemp(prefix="sr_digest_cache_"), "file_digests.json"))
setup_offscreen_rendering()


@pytest.fixture(autouse=True)
def _seed_everything():
    torch.manual_seed(0)
    np.random.seed(0)
    yield
