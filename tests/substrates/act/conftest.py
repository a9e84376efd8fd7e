"""Fixtures: tiny synthetic skill datasets, made once per test session (nothing is downloaded)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from tests.substrates.act.helpers import make_skill_dataset

SKILLS = ["approach", "place", "insert"]


@pytest.fixture(scope="session", autouse=True)
def _hf_cache(tmp_path_factory):
    os.environ["HF_HOME"] = str(tmp_path_factory.mktemp("hf_home"))
    os.environ["HF_DATASETS_CACHE"] = str(tmp_path_factory.mktemp("hf_datasets"))


@pytest.fixture(scope="session")
def image_datasets(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("needle_images")
    for i, skill in enumerate(SKILLS):
        make_skill_dataset(root, skill, i)
    return root


@pytest.fixture(scope="session")
def state_datasets(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("needle_states")
    for i, skill in enumerate(SKILLS):
        make_skill_dataset(root, skill, i, image=False)
    return root


@pytest.fixture(scope="session")
def video_datasets(tmp_path_factory) -> Path:
    """The first two skills with their camera as video (``sr-record --video=true``)."""
    root = tmp_path_factory.mktemp("needle_videos")
    for i, skill in enumerate(SKILLS[:2]):
        make_skill_dataset(root, skill, i, video=True)
    return root
