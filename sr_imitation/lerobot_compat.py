"""The one place that names LeRobot internals which moved between releases (written for LeRobot 0.6.x).

Every other module imports these names from here, so that a later LeRobot release that moves them again changes
this file only. :data:`SUPPORTED` is the range this file was written for (``tests/test_lerobot_compat.py`` checks
the installed LeRobot lies in it and that every name resolves); LeRobot 0.4.4 on Python 3.11 is tag ``v0.1.0``.
"""

from __future__ import annotations

import importlib.metadata
from pathlib import Path
from typing import Any

from lerobot.configs.video import RGBEncoderConfig
from lerobot.datasets import dataset_metadata as _dataset_metadata
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.utils.device_utils import is_torch_device_available
from lerobot.utils.feature_utils import dataset_to_policy_features

__all__ = ["SUPPORTED", "LEGACY_TAG", "create_dataset", "dataset_to_policy_features", "is_torch_device_available",
           "lerobot_home", "lerobot_version"]

SUPPORTED = (">=0.6.1", "<0.7")
"""The LeRobot releases this package is written and tested for (pyproject.toml's range)."""

LEGACY_TAG = "v0.1.0"
"""The git tag of the last commit on LeRobot 0.4.4 / Python 3.11: runs made there resume only there."""


def lerobot_version() -> str:
    """The installed LeRobot's version string (``0.6.1``)."""
    return importlib.metadata.version("lerobot")


def lerobot_home() -> Path:
    """``$HF_LEROBOT_HOME``, as LeRobot itself resolves ``LeRobotDataset(repo_id)`` without a ``root``: the value
    its dataset metadata module holds (tests patch it there)."""
    return Path(_dataset_metadata.HF_LEROBOT_HOME)


def create_dataset(*, vcodec: str, **kwargs: Any) -> LeRobotDataset:
    """``LeRobotDataset.create`` with videos encoded by ``vcodec`` (0.6 takes it inside an ``RGBEncoderConfig``).

    Args:
        vcodec: the video codec of camera streams (``h264``, ...).
        **kwargs: ``LeRobotDataset.create``'s other arguments (repo_id, fps, features, root, robot_type, use_videos).

    Returns:
        The dataset in write mode.
    """
    return LeRobotDataset.create(rgb_encoder=RGBEncoderConfig(vcodec=vcodec), **kwargs)
