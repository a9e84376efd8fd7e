"""Every dataset of a stream is opened and matched to the policy before the first gradient, and before anything
is written: a bad later dataset fails at once with one message naming the file, and leaves no run directory."""

from __future__ import annotations

import shutil

import pytest

from sr_imitation.imitation.data import DatasetMismatchError
from sr_imitation.imitation.stream import train_stream
from tests.imitation.helpers import fake_env_factory, make_skill_dataset, tiny_stream_config

SKILLS = ["approach", "place", "insert"]


def _copy(state_datasets, root):
    for skill in SKILLS:
        shutil.copytree(state_datasets / skill, root / skill)
    return root


def _fails_before_writing(root, out, match, monkeypatch):
    # Training must not start: the wake loop is replaced by a tripwire.
    def tripwire(*args, **kwargs):
        raise AssertionError("training started before the inputs were checked")

    monkeypatch.setattr("sr_imitation.imitation.substrate.wake_train", tripwire)
    with pytest.raises(DatasetMismatchError, match=match) as info:
        train_stream(tiny_stream_config(root, out, SKILLS, use_images=False), fake_env_factory)
    assert "\n" not in str(info.value)  # one line
    assert not out.exists()  # nothing written


def test_deleted_data_file_of_the_last_skill_is_named_before_training(state_datasets, tmp_path, monkeypatch):
    root = _copy(state_datasets, tmp_path / "d")
    parquet = next((root / "insert" / "data").rglob("*.parquet"))
    parquet.unlink()
    _fails_before_writing(root, tmp_path / "out", r"insert: missing or empty data files \['data/chunk-000", monkeypatch)


def test_deleted_episode_metadata_is_named_instead_of_a_hub_error(state_datasets, tmp_path, monkeypatch):
    root = _copy(state_datasets, tmp_path / "d")
    shutil.rmtree(root / "place" / "meta" / "episodes")
    _fails_before_writing(root, tmp_path / "out", r"place: incomplete LeRobot dataset, missing meta/episodes",
                          monkeypatch)


def test_missing_later_dataset_and_other_action_size_fail_before_training(state_datasets, tmp_path, monkeypatch):
    root = _copy(state_datasets, tmp_path / "d")
    shutil.rmtree(root / "insert")
    _fails_before_writing(root, tmp_path / "o1", r"insert: not a LeRobot dataset", monkeypatch)
    make_skill_dataset(root, "insert", 2, image=False, action_dim=5)
    _fails_before_writing(root, tmp_path / "o2", r"insert/meta/info.json: feature 'action' has shape \(5,\)",
                          monkeypatch)


def test_other_fps_is_refused(state_datasets, tmp_path, monkeypatch):
    import json

    root = _copy(state_datasets, tmp_path / "d")
    info = root / "place" / "meta" / "info.json"
    data = json.loads(info.read_text())
    data["fps"] = 30
    info.write_text(json.dumps(data))
    _fails_before_writing(root, tmp_path / "out", r"place/meta/info.json: fps 30 differs from the first skill's 10",
                          monkeypatch)
