"""No leftovers (issue 87 item 5): what a killed command leaves beside or in its output folder (``sr-sleep``'s
staging folder ``.<out>.XXXXXXXX`` with a whole ``pretrained_model``, ``sr-record``'s ``.<skill>.tmp-XXXXXXXX``,
``sr-eval``'s ``.<video>.partial.mp4``) is removed by the next run of the same command, in one log line each, or
named in one warning line if it cannot be; only by the holder of the folder's lock (a live writer's staging folder
is never touched), and never a lock file."""

from __future__ import annotations

import logging
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import sr_imitation.infra.folder_lock as folder_lock
from sr_imitation.infra.folder_lock import FolderBusyError, hold_folder, remove_staging_beside
from sr_imitation.substrates.act import cli

HOLDER = textwrap.dedent("""
    import sys, time
    from sr_imitation.infra.folder_lock import hold_folder
    with hold_folder(sys.argv[1], "sr-sleep"):
        print("held", flush=True)
        time.sleep(300)
""")


def killed_sleep(parent: Path, name: str = "slept") -> Path:
    """What ``kill -9`` of ``sr-sleep --output_dir=<parent>/<name>`` leaves: its staging folder, a checkpoint in it."""
    staging = parent / f".{name}.k3_x9a0q"
    (staging / "pretrained_model").mkdir(parents=True)
    (staging / "pretrained_model" / "model.safetensors").write_bytes(b"\0" * 64)
    return staging


def test_the_next_sr_sleep_removes_a_killed_ones_staging_folder_in_one_line(tmp_path, caplog):
    staging = killed_sleep(tmp_path)
    others = [tmp_path / ".other.lock", tmp_path / ".slept.replaced-1", tmp_path / ".slept.tmp", tmp_path / "slept2"]
    for other in others:
        other.write_text("not sr-sleep's staging")
    (tmp_path / ".slept2.ab12cd34").mkdir()  # another output folder's staging: not this command's
    caplog.set_level(logging.INFO)
    with pytest.raises(FileNotFoundError):  # refused for its missing policy, after the clean-up
        cli.sleep_main([f"--policy.path={tmp_path / 'no_model'}", f"--output_dir={tmp_path / 'slept'}",
                        f"--memories=[{tmp_path / 'm.safetensors'}]"])
    assert not staging.exists()
    assert all(other.exists() for other in others) and (tmp_path / ".slept2.ab12cd34").is_dir()
    lines = [r.getMessage() for r in caplog.records if str(staging) in r.getMessage()]
    assert lines == [f"{staging}: removed, left by a killed earlier sr-sleep"]


def test_a_live_sr_sleeps_staging_folder_is_left_alone(tmp_path):
    staging = killed_sleep(tmp_path)
    holder = subprocess.Popen([sys.executable, "-c", HOLDER, str(tmp_path / "slept")], stdout=subprocess.PIPE,
                              text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(FolderBusyError):
            cli.sleep_main([f"--policy.path={tmp_path / 'no_model'}", f"--output_dir={tmp_path / 'slept'}",
                            f"--memories=[{tmp_path / 'm.safetensors'}]"])
        assert remove_staging_beside(tmp_path / "slept", "sr-sleep") == []  # without the lock: nothing touched
        assert (staging / "pretrained_model" / "model.safetensors").is_file()
    finally:
        holder.kill()
        holder.wait()


def test_a_leftover_that_cannot_be_removed_is_one_warning_line(tmp_path, monkeypatch, caplog):
    staging = killed_sleep(tmp_path)

    def refuse(path, *args, **kwargs):
        raise PermissionError(13, "Permission denied", str(path))

    monkeypatch.setattr(folder_lock.shutil, "rmtree", refuse)
    caplog.set_level(logging.INFO)
    with hold_folder(tmp_path / "slept"):
        assert remove_staging_beside(tmp_path / "slept", "sr-sleep") == []
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert [r.getMessage() for r in warnings] == [
        f"{staging}: cannot remove what a killed earlier sr-sleep left (Permission denied); remove it yourself"]
    assert staging.is_dir()


def test_sr_record_removes_a_killed_recordings_staging_folders(tmp_path, monkeypatch, caplog):
    from sr_imitation.recorders import needle

    root = tmp_path / "datasets"
    leftover = root / ".approach.tmp-0a1b2c3d"
    (leftover / "dataset" / "data").mkdir(parents=True)
    (root / "place").mkdir()
    monkeypatch.setattr(needle, "record_skill", lambda cfg, skill, index: cfg.target(skill))
    caplog.set_level(logging.INFO)
    needle.record(needle.RecordConfig(root=root, skills=["approach"]))
    assert sorted(p.name for p in root.iterdir()) == ["place"]
    assert any(f"{leftover}: removed, left by a killed earlier sr-record" in r.getMessage() for r in caplog.records)


def test_sr_eval_removes_a_killed_evaluations_partial_videos(tmp_path, caplog):
    out = tmp_path / "eval"
    (out / "videos").mkdir(parents=True)
    partial = out / "videos" / ".insert_episode0_failure.partial.mp4"
    partial.write_bytes(b"\0" * 16)
    (out / "videos" / "approach_episode0_success.mp4").write_bytes(b"\0" * 16)  # an earlier evaluation's: kept
    caplog.set_level(logging.INFO)
    with pytest.raises(FileNotFoundError):  # refused for its missing policy, after the clean-up
        cli.eval_main([f"--policy.path={tmp_path / 'no_model'}", f"--output_dir={out}", "--skills=[approach]"])
    assert sorted(p.name for p in (out / "videos").iterdir()) == ["approach_episode0_success.mp4"]
    assert any(f"{partial}: removed, left by a killed earlier sr-eval" in r.getMessage() for r in caplog.records)
