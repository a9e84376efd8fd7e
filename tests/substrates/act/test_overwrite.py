"""``sr-train --overwrite=true`` on the ACT substrate never deletes a user's data: not the datasets (given as the
output folder, or inside it), not a folder of foreign files; a run of this package is replaced, and a replaced run
comes back when the new one fails to start.

Before: ``--stream.dataset_root=D --output_dir=D --overwrite=true`` logged "removing D", then failed with "not a
LeRobot dataset": the recorded datasets were gone."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import pytest

from sr_imitation.stream.rundir import REPLACED_MARK, OverwriteRefusedError
from sr_imitation.substrates.act.trainer import ACTTrainer
from tests.infra.test_fingerprint import tree_state
from tests.substrates.act.helpers import damage, fake_env_factory, tiny_stream_config

STREAM = ["approach", "place"]


@pytest.fixture
def datasets(state_datasets, tmp_path) -> Path:
    root = tmp_path / "data"
    shutil.copytree(state_datasets, root)
    return root


def _trainer(datasets: Path, out: Path, **changes) -> ACTTrainer:
    cfg = tiny_stream_config(datasets, out, STREAM, use_images=False)
    cfg.overwrite = True
    for key, value in changes.items():
        setattr(cfg, key, value)
    return ACTTrainer(cfg, fake_env_factory)


def _no_training(monkeypatch):
    def tripwire(*args, **kwargs):
        raise AssertionError("training started")

    monkeypatch.setattr("sr_imitation.substrates.act.substrate.wake_train", tripwire)


def test_overwrite_never_deletes_the_datasets_or_foreign_files(datasets, tmp_path, monkeypatch):
    _no_training(monkeypatch)
    before = tree_state(datasets)
    # the datasets' root as the output folder, a folder above it, one skill's dataset
    for out, match in ((datasets, "it holds the input"), (tmp_path, "it holds the input"),
                       (datasets / "approach", "lies inside the input")):
        with pytest.raises(OverwriteRefusedError, match=match):
            _trainer(datasets, out).run()
        assert tree_state(datasets) == before, out
    # a folder of the user's own files
    thesis = tmp_path / "thesis"
    thesis.mkdir()
    (thesis / "thesis.txt").write_text("four years")
    with pytest.raises(OverwriteRefusedError, match=r"thesis: --overwrite=true refused: it holds no settings_fin"):
        _trainer(datasets, thesis).run()
    assert (thesis / "thesis.txt").read_text() == "four years"
    assert not [p for p in tmp_path.iterdir() if REPLACED_MARK in p.name]


def test_overwrite_replaces_an_act_run_and_restores_it_when_the_new_one_fails(datasets, tmp_path, monkeypatch):
    out = tmp_path / "run"
    _trainer(datasets, out, overwrite=False).run(stop_after=1)
    _trainer(datasets, out).run(stop_after=1)  # every file an ACT run writes is recognised as the run's
    assert not [p for p in tmp_path.iterdir() if REPLACED_MARK in p.name]
    before = tree_state(out)
    _no_training(monkeypatch)
    with pytest.raises(AssertionError, match="training started"):
        _trainer(datasets, out).run(stop_after=1)
    assert tree_state(out) == before
    assert not [p for p in tmp_path.iterdir() if REPLACED_MARK in p.name]


def test_overwrite_keeps_the_earlier_run_when_a_video_of_the_new_one_is_truncated(video_datasets, tmp_path):
    """Before: ``--overwrite=true`` over a finished run, on video datasets with one skill's mp4 truncated: the earlier
    run was deleted once stage 1 was recorded, then ``IndexError: min(): Expected reduction dim 1`` at stage 2. Now
    every input is read through before the old run is set aside: one line naming the mp4, the earlier run
    byte-identical and nothing set aside."""
    from sr_imitation.substrates.act.data import DatasetMismatchError

    datasets = tmp_path / "data"
    shutil.copytree(video_datasets, datasets)
    out = tmp_path / "run"
    _trainer(datasets, out, overwrite=False).run()
    before = tree_state(out)
    video = next((datasets / "place" / "videos").rglob("*.mp4"))
    damage(video, "truncated")
    with pytest.raises(DatasetMismatchError, match=f"^{re.escape(str(video))}: .*episode \\d, frame ") as info:
        _trainer(datasets, out).run()
    assert "\n" not in str(info.value)
    assert tree_state(out) == before
    assert not [p for p in tmp_path.iterdir() if REPLACED_MARK in p.name]
