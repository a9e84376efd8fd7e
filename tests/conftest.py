"""Shared test set-up: offline, deterministic, caches inside a temporary directory."""

from __future__ import annotations

import os

import numpy as np
import pytest
import torch

from sr_imitation.offscreen import setup_offscreen_rendering

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("HF_DATASETS_OFFLINE", "1")
setup_offscreen_rendering()


@pytest.fixture(autouse=True)
def _seed_everything():
    torch.manual_seed(0)
    np.random.seed(0)
    yield
