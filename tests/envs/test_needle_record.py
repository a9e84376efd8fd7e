"""sr-record: datasets load back offline; no silent overwrite; interrupted runs leave nothing loadable."""

from pathlib import Path

import numpy as np
import pytest

from sr_imitation import record as rec
from sr_imitation.envs.needle import SKILL_NAMES

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


def test_same_seed_same_data(tmp_path):
    for name in ("a", "b"):
        rec.record(
            rec.RecordConfig(skills=["approach"], num_episodes=1, root=tmp_path / name, image_size=SIZE)
        )
    a, b = _load(tmp_path / "a", "approach"), _load(tmp_path / "b", "approach")
    assert a.num_frames == b.num_frames
    np.testing.assert_array_equal(a.hf_dataset["action"], b.hf_dataset["action"])


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
    cfg.overwrite = True
    rec.record(cfg)
    assert not (target / "keep.txt").exists()
    assert _load(tmp_path, "approach").num_episodes == 1


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
    ],
)
def test_invalid_record_config(kwargs):
    with pytest.raises(ValueError):
        rec.RecordConfig(**kwargs)
