"""The comparison drivers' archive of finished runs (sr_imitation.experiments.archive), on synthetic run folders."""

from __future__ import annotations

import json
import logging

import pytest

from sr_imitation.experiments.archive import archive_run, archived_run
from sr_imitation.infra.fingerprint import SettingsMismatchError, settings_fingerprint, write_fingerprint
from sr_imitation.infra.weight_store import WEIGHTS_FILE, verify_weights, weight_store
from sr_imitation.io import CorruptFileError, read_checked_json

SETTINGS = {"seed": 0, "sleep": {"lr": 1e-5, "enabled": True}, "output_dir": "x"}
ALLOW = ("output_dir",)


def _run(path, settings=SETTINGS, finished=True):
    path.mkdir(parents=True)
    write_fingerprint(path / "settings_fingerprint.json", settings_fingerprint(settings, ALLOW))
    (path / "progress.json").write_text("{}")
    (path / "model.safetensors").write_bytes(b"weights")
    if finished:
        (path / "results.json").write_text(json.dumps({"metrics": {}}))
    return path


def test_a_finished_run_with_the_same_settings_is_found(tmp_path):
    _run(tmp_path / "a" / "sr_seed0")
    current = settings_fingerprint({**SETTINGS, "output_dir": "elsewhere"}, ALLOW)  # location is not a setting
    assert archived_run(tmp_path / "a", "sr_seed0", current) == tmp_path / "a" / "sr_seed0"
    assert archived_run(None, "sr_seed0", current) is None
    assert archived_run(tmp_path / "a", "sr_seed1", current) is None  # not there
    _run(tmp_path / "a" / "sr_seed2", finished=False)
    assert archived_run(tmp_path / "a", "sr_seed2", current) is None  # killed: not finished


def test_other_values_refuse_and_added_settings_warn(tmp_path, caplog):
    _run(tmp_path / "sr_seed0")
    changed = settings_fingerprint({**SETTINGS, "sleep": {"lr": 1e-4, "enabled": True}}, ALLOW)
    with pytest.raises(SettingsMismatchError, match=r"sr_seed0/settings_fingerprint.json.*sleep.lr: 1e-05 -> 0.0001"):
        archived_run(tmp_path, "sr_seed0", changed)
    removed = settings_fingerprint({"seed": 0, "sleep": {"lr": 1e-5}}, ALLOW)  # the run has a key the code lost
    with pytest.raises(SettingsMismatchError, match="sleep.enabled"):
        archived_run(tmp_path, "sr_seed0", removed)
    added = settings_fingerprint({**SETTINGS, "policy": {"backbone_norm": "auto"}}, ALLOW)
    with caplog.at_level(logging.WARNING):
        assert archived_run(tmp_path, "sr_seed0", added) == tmp_path / "sr_seed0"
    assert "predates the settings policy.backbone_norm" in caplog.text


def test_an_edited_fingerprint_is_refused(tmp_path):
    run = _run(tmp_path / "sr_seed0")
    data = json.loads((run / "settings_fingerprint.json").read_text())
    data["settings"]["seed"] = 1
    (run / "settings_fingerprint.json").write_text(json.dumps(data))
    with pytest.raises(CorruptFileError, match="settings_fingerprint.json"):
        archived_run(tmp_path, "sr_seed0", settings_fingerprint({**SETTINGS, "seed": 1}, ALLOW))


def test_archiving_copies_the_report_files_and_replaces_an_older_copy(tmp_path):
    run = _run(tmp_path / "runs" / "sr_seed0")
    kept = archive_run(run, tmp_path / "archive", "sr_seed0")
    assert sorted(p.name for p in kept.iterdir()) == ["progress.json", "results.json", "settings_fingerprint.json"]
    (run / "results.json").write_text(json.dumps({"metrics": {"afsr": 1}}))
    archive_run(run, tmp_path / "archive", "sr_seed0")
    assert json.loads((kept / "results.json").read_text()) == {"metrics": {"afsr": 1}}
    assert [p.name for p in (tmp_path / "archive").iterdir()] == ["sr_seed0"]  # no temporary or old folder left
    with pytest.raises(FileNotFoundError, match="has not finished"):
        archive_run(_run(tmp_path / "runs" / "sr_seed1", finished=False), tmp_path / "archive", "sr_seed1")
    assert not (tmp_path / "archive" / "sr_seed1").exists()
    # A folder of that name holding anything an archived run does not is never replaced.
    (kept / "notes.md").write_text("mine")
    with pytest.raises(ValueError, match=r"sr_seed0: not replaced by the archived run: it holds notes.md"):
        archive_run(run, tmp_path / "archive", "sr_seed0")
    assert (kept / "notes.md").read_text() == "mine" and (kept / "results.json").is_file()


def test_a_kept_run_stores_its_weights_beside_the_archive_with_checksums_in_it(tmp_path):
    run = _run(tmp_path / "runs" / "sr_seed0")
    (run / "stages" / "01_reach" / "wake").mkdir(parents=True)
    (run / "stages" / "01_reach" / "wake" / "agent.safetensors").write_bytes(b"actor after wake")
    (run / "stages" / "01_reach" / "memory.safetensors").write_bytes(b"memory")
    (run / "videos").mkdir()
    (run / "videos" / "reach.mp4").write_bytes(b"video")
    (run / "log.jsonl").write_text("{}\n")
    (run / "stages" / "01_reach" / ".agent.safetensors.1.tmp").write_bytes(b"half")
    kept = archive_run(run, tmp_path / "archive", "sr_seed0", keep_weights=True)
    store = weight_store(tmp_path / "archive") / "sr_seed0"
    assert store == tmp_path / "archive.weights" / "sr_seed0"
    listing = read_checked_json(kept / WEIGHTS_FILE)
    assert sorted(listing["files"]) == ["model.safetensors", "progress.json", "results.json",
                                        "settings_fingerprint.json", "stages/01_reach/memory.safetensors",
                                        "stages/01_reach/wake/agent.safetensors"]  # no video, log or temp file
    assert listing["files"]["stages/01_reach/memory.safetensors"]["bytes"] == 6
    assert (store / "stages/01_reach/wake/agent.safetensors").read_bytes() == b"actor after wake"
    assert verify_weights(kept) == store
    # A damaged or missing stored file is named; the tracked list is what it is checked against.
    (store / "stages/01_reach/memory.safetensors").write_bytes(b"memorY")
    with pytest.raises(CorruptFileError, match=r"memory.safetensors.*differs from its checksum in .*weights.json"):
        verify_weights(kept)
    (store / "stages/01_reach/memory.safetensors").unlink()
    with pytest.raises(CorruptFileError, match=r"memory.safetensors.*missing from the weight store"):
        verify_weights(kept)
    # Archiving again replaces the store as a whole; no temporary or old folder is left beside it.
    archive_run(run, tmp_path / "archive", "sr_seed0", keep_weights=True)
    assert verify_weights(kept) == store
    assert sorted(p.name for p in (tmp_path / "archive.weights").iterdir()) == ["sr_seed0"]
