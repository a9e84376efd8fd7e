"""sr-record: datasets load back offline; no silent overwrite; interrupted runs leave nothing loadable."""

from pathlib import Path

import numpy as np
import pytest

from sr_imitation.envs.needle import SKILL_NAMES
from sr_imitation.io import read_checked_json
from sr_imitation.recorders import needle as rec

SIZE = 32
pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


def _load(root: Path, skill: str):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    return LeRobotDataset(
        f"local/sr_needle_{skill}",
        root=root / skill,
        video_backend="pyav",
        delta_timestamps={"action": [i / 30 for i in range(4)]},
    )


def test_record_all_skills_and_load_back(tmp_path, capsys):
    root = tmp_path / "needle"
    rec.main([f"--root={root}", "--num_episodes=2", f"--image_size={SIZE}", "--seed=1"])
    out = capsys.readouterr().out
    for skill in SKILL_NAMES:
        assert f"wrote {(root / skill).resolve()}" in out
        ds = _load(root, skill)
        assert ds.num_episodes == 2
        assert ds.meta.total_tasks == 1 and list(ds.meta.tasks.index) == [skill]
        item = ds[0]
        assert item["observation.images.wrist"].shape == (3, SIZE, SIZE)
        assert item["observation.state"].shape == (35,)
        assert item["action"].shape == (4, 7)
        assert item["task"] == skill
        last = ds[ds.num_frames - 1]
        assert bool(last["next.success"]) and bool(last["next.done"])  # successful episodes only
    assert not [p for p in root.iterdir() if p.name.startswith(".")]  # no temporary leftovers


def test_record_video_mode_and_episode_videos(tmp_path):
    root = tmp_path / "needle"
    cfg = rec.RecordConfig(
        skills=["regrasp"],
        num_episodes=2,
        root=root,
        image_size=SIZE,
        image_width=48,
        video=True,
        episode_videos=True,
    )
    rec.record(cfg)
    ds = _load(root, "regrasp")
    assert ds.meta.video_keys == ["observation.images.wrist"]
    frame = ds[5]["observation.images.wrist"]
    assert frame.shape == (3, SIZE, 48) and float(frame.std()) > 0.0  # non-square images work
    assert sorted(p.name for p in cfg.episode_video_dir("regrasp").iterdir()) == [
        "episode_000000.mp4",
        "episode_000001.mp4",
    ]


def test_sr_record_with_video_prints_its_own_lines_not_the_encoders(tmp_path, capfd):
    """libx264 prints about 13 lines of statistics per video it closes (297 lines for a user's needle datasets);
    ``sr-record`` keeps FFmpeg below errors out of the output (captured at the file descriptor: FFmpeg writes there)."""
    from sr_imitation.recorders.cli import main

    main([f"--root={tmp_path / 'needle'}", "--skills=[regrasp]", "--num_episodes=1", f"--image_size={SIZE}",
          "--video=true"])
    out, err = capfd.readouterr()
    assert "wrote " in out and (tmp_path / "needle" / "regrasp" / "videos").is_dir()
    assert "libx264" not in out + err and "kb/s" not in err, err[-2000:]


def test_same_seed_same_data(tmp_path):
    for name in ("a", "b"):
        rec.record(
            rec.RecordConfig(skills=["approach"], num_episodes=1, root=tmp_path / name, image_size=SIZE)
        )
    a, b = _load(tmp_path / "a", "approach"), _load(tmp_path / "b", "approach")
    assert a.num_frames == b.num_frames
    np.testing.assert_array_equal(a.hf_dataset["action"], b.hf_dataset["action"])


def test_same_settings_same_bytes_whatever_the_hash_seed(tmp_path):
    """A recording in a process with another PYTHONHASHSEED than this one gives byte-identical files, so the
    dataset's content digest (inputs.datasets.<skill>) names the demos, not the process that wrote them. (This
    process's hash seed is random unless PYTHONHASHSEED is set; the other process's is chosen to differ from it.)"""
    import hashlib
    import os
    import subprocess
    import sys

    def files(root: Path) -> dict[str, str]:
        return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
                for p in sorted(root.rglob("*")) if p.is_file()}

    other_seed = "2" if os.environ.get("PYTHONHASHSEED") == "1" else "1"
    subprocess.run([sys.executable, "-m", "sr_imitation.recorders.needle", f"--root={tmp_path / 'a'}",
                    "--skills=[approach]", "--num_episodes=1", f"--image_size={SIZE}"],
                   check=True, env={**os.environ, "PYTHONHASHSEED": other_seed}, capture_output=True)
    rec.record(rec.RecordConfig(skills=["approach"], num_episodes=1, root=tmp_path / "b", image_size=SIZE))
    a, b = files(tmp_path / "a"), files(tmp_path / "b")
    assert any(k.endswith(".parquet") for k in a) and "approach/meta/stats.json" in a
    assert a == b


def test_existing_target_is_not_overwritten(tmp_path):
    target = tmp_path / "approach"
    target.mkdir()
    (target / "keep.txt").write_text("precious")
    cfg = rec.RecordConfig(skills=["approach"], num_episodes=1, root=tmp_path, image_size=SIZE)
    with pytest.raises(FileExistsError, match="overwrite"):
        rec.record(cfg)
    assert (target / "keep.txt").read_text() == "precious"
    with pytest.raises(SystemExit, match="already exist"):
        rec.main([f"--root={tmp_path}", "--skills=[approach]", "--num_episodes=1", f"--image_size={SIZE}"])
    cfg.overwrite = True  # --overwrite replaces a dataset of ours only: a folder of other files is refused
    with pytest.raises(FileExistsError, match=r"approach: --overwrite=true refused: it is not a LeRobot dataset"):
        rec.record(cfg)
    assert (target / "keep.txt").read_text() == "precious"
    (target / "keep.txt").unlink()
    rec.record(cfg)
    first = _load(tmp_path, "approach")
    assert first.num_episodes == 1
    rec.record(cfg)  # a dataset sr-record recorded: replaced
    assert _load(tmp_path, "approach").num_episodes == 1


def test_overwrite_refuses_a_dataset_holding_foreign_files_or_recorded_by_another_program(tmp_path):
    cfg = rec.RecordConfig(skills=["approach"], num_episodes=1, root=tmp_path, image_size=SIZE)
    rec.record(cfg)
    target = tmp_path / "approach"
    cfg.overwrite = True
    (target / "notes.txt").write_text("mine")
    before = {p: p.read_bytes() for p in target.rglob("*") if p.is_file()}
    with pytest.raises(FileExistsError, match="it holds notes.txt, which no dataset holds"):
        rec.record(cfg)
    (target / "notes.txt").unlink()
    (target / rec.RECORD_SETTINGS_FILE).unlink()  # LeRobot's info.json names another robot
    info = target / "meta" / "info.json"
    info.write_text(info.read_text().replace(rec.ROBOT_TYPE, "so100"))
    with pytest.raises(FileExistsError, match="a dataset sr-record did not record"):
        rec.record(cfg)
    assert all(p.is_file() for p in before if p.name not in ("notes.txt", "sr_record.json"))


def test_interrupted_run_leaves_no_dataset(tmp_path, monkeypatch):
    calls = {"n": 0}
    real = rec.run_demo

    def flaky(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(rec, "run_demo", flaky)
    cfg = rec.RecordConfig(skills=["approach"], num_episodes=3, root=tmp_path, image_size=SIZE)
    with pytest.raises(KeyboardInterrupt):
        rec.record(cfg)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "kwargs",
    [
        {"skills": ["suture"]},
        {"skills": []},
        {"num_episodes": 0},
        {"image_size": 4},
        {"image_width": 2000},
        {"vcodec": "mp3"},
        {"demo_threshold_scale": 0.0},
        {"demo_threshold_scale": 1.5},
        {"expert_jaw_close_mm": 0.0},
    ],
)
def test_invalid_record_config(kwargs):
    with pytest.raises(ValueError):
        rec.RecordConfig(**kwargs)


def test_demo_margins_end_demos_inside_the_success_region_and_datasets_remember_them(tmp_path):
    """--demo_threshold_scale ends place demos well inside the rotation threshold (1: on its boundary) and
    --expert_jaw_close_mm makes the expert close later; the recorded settings are stored with the dataset and a
    dataset of other settings is refused by name (one from before the file existed: compared on the old defaults)."""
    from sr_imitation.envs.needle.env import NeedleEnv
    from sr_imitation.envs.needle.expert import ExpertSettings

    final = {}
    for scale in (1.0, 0.5):
        env = NeedleEnv(skill="place", image_height=SIZE, image_width=SIZE, threshold_scale=scale)
        final[scale] = [rec.run_demo(env, seed, False)[0][-1] for seed in range(4)]
        assert all(f["next.success"][0] for f in final[scale])
    rotation = {s: max(abs(f["observation.state"][17:20]).max() for f in final[s]) for s in final}  # delta rpy
    assert env.threshold.rotation_deg == 5.0 and rotation[0.5] < rotation[1.0]
    env = NeedleEnv(skill="regrasp", image_height=SIZE, image_width=SIZE)
    steps = {mm: len(rec.run_demo(env, 3, False, ExpertSettings(jaw_close_cm=mm / 10))[0]) for mm in (1.5, 0.5)}
    assert steps[0.5] > steps[1.5]
    from sr_imitation.benchmarks.demo_endings import demo_ending  # the measurement docs/RESULTS.md reports

    ending = demo_ending("regrasp", 0.5, 0.5, 3)
    assert ending["success"] == 1.0 and ending["steps"] == steps[0.5] and ending["jaw_close_at_mm"] <= 0.5
    assert 5.0 < demo_ending("place", 1.0, 1.5, 0)["rotation_deg"] <= 10.0 and demo_ending("place", 0.5, 0.5, 0)[
        "rotation_deg"] <= 5.0

    cfg = rec.RecordConfig(skills=["approach"], num_episodes=1, root=tmp_path, image_size=SIZE,
                           demo_threshold_scale=0.5, expert_jaw_close_mm=0.5)
    rec.record(cfg)
    stored = tmp_path / "approach" / rec.RECORD_SETTINGS_FILE
    assert read_checked_json(stored)["demo_threshold_scale"] == 0.5
    rec.check_recorded(cfg, ["approach", "place"])  # same settings (place not recorded): nothing to refuse
    other = rec.RecordConfig(skills=["approach"], num_episodes=1, root=tmp_path, image_size=SIZE)
    with pytest.raises(ValueError, match=r"sr_record.json: recorded with demo_threshold_scale=0.5 \(config: 1.0\)"):
        rec.check_recorded(other, ["approach"])
    stored.unlink()  # a dataset recorded before the settings were stored: SurgicAI's demo endings
    rec.check_recorded(other, ["approach"])
    with pytest.raises(ValueError, match="recorded before meta/sr_record.json existed"):
        rec.check_recorded(cfg, ["approach"])
