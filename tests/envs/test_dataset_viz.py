"""sr-dataset-viz: LeRobot's lerobot-dataset-viz on a dataset recorded with --video=true, where torchcodec does not
load (this set-up has no FFmpeg shared libraries for it); sr-record says how to view a video dataset."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from sr_imitation.recorders import needle as rec
from sr_imitation.recorders.viz import torchcodec_loads

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


@pytest.fixture(scope="module")
def video_dataset(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("viz") / "needle"
    rec.record(rec.RecordConfig(skills=["approach"], num_episodes=1, root=root, image_size=32, video=True))
    return root / "approach"


def _viz(module: str, dataset: Path, out: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", module, "--repo-id", "approach", "--root", str(dataset),
                           "--episode-index", "0", "--save", "1", "--output-dir", str(out)],
                          capture_output=True, text=True, timeout=300, check=False)


def test_sr_dataset_viz_writes_a_rerun_recording_of_a_video_dataset(video_dataset, tmp_path):
    done = _viz("sr_imitation.recorders.viz", video_dataset, tmp_path / "viz")
    assert done.returncode == 0, done.stderr[-3000:]
    recordings = list((tmp_path / "viz").glob("*.rrd"))
    assert len(recordings) == 1 and recordings[0].stat().st_size > 10_000  # the frames are in it


@pytest.mark.skipif(torchcodec_loads(), reason="torchcodec loads on this machine: stock lerobot-dataset-viz works")
def test_stock_lerobot_dataset_viz_is_what_fails_here(video_dataset, tmp_path):
    """The reason the command exists: stock lerobot-dataset-viz picks torchcodec because it is installed, and
    torchcodec cannot load its libraries here."""
    done = _viz("lerobot.scripts.lerobot_dataset_viz", video_dataset, tmp_path / "viz")
    assert done.returncode != 0 and "torchcodec" in done.stderr


def test_sr_record_says_how_to_view_a_video_dataset(tmp_path, capsys):
    rec.main([f"--root={tmp_path}", "--skills=[approach]", "--num_episodes=1", "--image_size=32", "--video=true"])
    out = capsys.readouterr().out
    assert f"sr-dataset-viz --repo-id approach --root {tmp_path / 'approach'}" in out
    rec.main([f"--root={tmp_path / 'png'}", "--skills=[approach]", "--num_episodes=1", "--image_size=32"])
    assert "sr-dataset-viz" not in capsys.readouterr().out  # images in parquet: nothing to decode
