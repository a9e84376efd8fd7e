"""A kill -9 during a run's start-up writes (settings fingerprint, then ``train_config.json``), through ``sr-train``'s
run entry on the toy substrate (milliseconds a run): every state such a kill leaves (made from an uninterrupted run's
own start-up files by :func:`sr_imitation.experiments.kill_resume.start_states`) is either started again by a plain
rerun or resumed, and ends with the uninterrupted run's files, ``train_config.json`` included.

Before: a start killed while writing ``train_config.json`` left the fingerprint only; ``--resume=true`` finished with
rc 0 and no ``train_config.json`` (its results' config then came from the resuming invocation, and ``status``
printed ``? | None | 0/0``)."""

from __future__ import annotations

from pathlib import Path

import torch

from sr_imitation.experiments.kill_resume import START_FILES, compare_start_files, start_states
from sr_imitation.infra.fingerprint import FINGERPRINT_FILE
from sr_imitation.stream import RunDirectory
from sr_imitation.stream.rundir import RUN_CONFIG_FILE
from tests.stream import toy

ARGS = ["--stream.skills=[a,b]", "--progress=false", "--wake_steps=10"]


def run(out: Path, resume: bool = False) -> dict:
    return toy.main([*ARGS, f"--output_dir={out}", *(["--resume=true"] if resume else [])])


def test_every_state_a_kill_during_the_start_up_writes_leaves_ends_like_an_uninterrupted_run(tmp_path):
    reference = run(tmp_path / "reference")
    assert START_FILES == (FINGERPRINT_FILE, RUN_CONFIG_FILE)
    states = start_states(tmp_path / "reference")
    assert [where for where, _ in states] == [
        "after the folder was made", f"inside the write of {FINGERPRINT_FILE}", f"after {FINGERPRINT_FILE}",
        f"inside the write of {RUN_CONFIG_FILE}", f"after {RUN_CONFIG_FILE}"]
    plain = []
    for i, (where, files) in enumerate(states):
        out = tmp_path / f"start_{i}"
        out.mkdir()
        for name, data in files.items():
            (out / name).write_bytes(data)
        resume = RunDirectory.occupied(out)  # what the kill/resume harness (and a person) does
        plain.append(not resume)
        result = run(out, resume=resume)
        assert compare_start_files(tmp_path / "reference", out) == [], where
        assert result["evals"] == reference["evals"], where
        assert all(torch.equal(a, b) for a, b in zip(result["weights"], reference["weights"], strict=True)), where
        assert not list(out.glob(".*.tmp")), where
    assert plain == [True, True, False, False, False]  # a kill before the fingerprint leaves no run


def test_a_run_that_recorded_a_phase_without_its_config_is_not_given_one(tmp_path):
    """Only a start that recorded no phase gets its config on resume: a run with phases and no config (one from
    before the file existed) keeps its layout."""
    out = tmp_path / "run"
    run(out)
    (out / RUN_CONFIG_FILE).unlink()
    run(out, resume=True)
    assert not (out / RUN_CONFIG_FILE).exists()
