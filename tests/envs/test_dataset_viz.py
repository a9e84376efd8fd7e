"""Stock lerobot-dataset-viz (LeRobot 0.6) on a dataset recorded with --video=true, where torchcodec does not load;
sr-record prints a hint that works when pasted (a path with spaces) and writes beside the dataset, not into it."""

from __future__ import annotations

import os
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from sr_imitation.recorders import needle as rec
from sr_imitation.recorders.viz import view_hint, viz_folder

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


@pytest.fixture(scope="module")
def video_dataset(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("viz") / "needle data"  # a space: the printed hint must survive pasting
    rec.record(rec.RecordConfig(skills=["approach"], num_episodes=1, root=root, image_size=32, video=True))
    return root / "approach"


@pytest.mark.slow
def test_the_printed_hint_pasted_into_a_shell_writes_a_rerun_recording_beside_the_dataset(video_dataset):
    hint = view_hint("approach", video_dataset)
    command = hint.removeprefix("view an episode: ").split("   (then:")[0]
    argv = shlex.split(command)
    assert argv[0] == "lerobot-dataset-viz"
    script = Path(sys.executable).with_name("lerobot-dataset-viz")
    before = sorted(p.relative_to(video_dataset) for p in video_dataset.rglob("*"))
    done = subprocess.run(["bash", "-c", command], capture_output=True, text=True, timeout=300, check=False,
                          env={**os.environ, "PATH": f"{script.parent}{os.pathsep}{os.environ['PATH']}"})
    assert done.returncode == 0, done.stderr[-3000:]
    recordings = list(viz_folder(video_dataset).glob("*.rrd"))
    assert len(recordings) == 1 and recordings[0].stat().st_size > 10_000  # the frames are in it
    assert viz_folder(video_dataset).parent == video_dataset.parent  # beside, not inside
    assert sorted(p.relative_to(video_dataset) for p in video_dataset.rglob("*")) == before


def test_sr_record_says_how_to_view_a_video_dataset(tmp_path, capsys):
    rec.main([f"--root={tmp_path}", "--skills=[approach]", "--num_episodes=1", "--image_size=32", "--video=true"])
    out = capsys.readouterr().out
    assert f"lerobot-dataset-viz --repo-id approach --root {tmp_path / 'approach'}" in out
    assert f"--output-dir {tmp_path / 'approach_viz'}" in out
    rec.main([f"--root={tmp_path / 'png'}", "--skills=[approach]", "--num_episodes=1", "--image_size=32"])
    assert "lerobot-dataset-viz" not in capsys.readouterr().out  # images in parquet: nothing to decode
