"""``load_metadata`` reads a dataset's metadata through LeRobot once and hands out copies while its ``meta/`` files
stay as they were (a stream's start-up reads the same metadata several times, about 0.3 s a read): a caller's change
to its copy never reaches the next caller, and a rewritten metadata file is read again, even one rewritten to the
same size with its modification time put back."""

from __future__ import annotations

import json
import os
import shutil

from sr_imitation.substrates.act import data


def test_copies_while_unchanged_and_a_rewritten_file_is_read_again(state_datasets, tmp_path, monkeypatch):
    root = tmp_path / "approach"
    shutil.copytree(state_datasets / "approach", root)
    reads = []
    original = data.LeRobotDatasetMetadata
    monkeypatch.setattr(data, "LeRobotDatasetMetadata", lambda *a, **k: reads.append(a) or original(*a, **k))

    first = data.load_metadata(root, "local/approach")
    first.info["robot_type"] = "changed by a caller"
    first.stats["action"]["mean"][:] = 1e9
    second = data.load_metadata(root, "local/approach")
    assert len(reads) == 1 and second is not first
    assert second.info["robot_type"] != "changed by a caller" and (second.stats["action"]["mean"] < 1e9).all()
    assert second.total_frames == first.total_frames and second.episodes.num_rows == first.episodes.num_rows

    data.load_metadata(root, "local/other_name")  # another repo_id is another entry
    assert len(reads) == 2

    info = root / "meta" / "info.json"
    before = info.stat()
    text = info.read_text()
    robot = json.loads(text)["robot_type"]
    info.write_text(text.replace(f'"{robot}"', '"' + "x" * len(robot) + '"'))  # same size
    os.utime(info, ns=(before.st_atime_ns, before.st_mtime_ns))  # and the same modification time
    assert info.stat().st_size == before.st_size and info.stat().st_mtime_ns == before.st_mtime_ns
    third = data.load_metadata(root, "local/approach")
    assert len(reads) == 3 and third.info["robot_type"] == "x" * len(robot)
