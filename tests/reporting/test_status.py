"""sr_imitation.reporting.status: where runs stand, read from their files (stages done, last phase, compute, a rough
time left that grows with the stage, finished runs' final metric)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from sr_imitation.infra.fingerprint import settings_fingerprint, write_fingerprint
from sr_imitation.io import write_checked_json
from sr_imitation.reporting.status import find_runs, main, run_status

SKILLS = ["a", "b", "c", "d", "e"]


def _run(root: Path, name: str, completed: dict[str, float], sleep: bool = True, **config) -> Path:
    run = root / name
    run.mkdir(parents=True)
    write_checked_json(run / "progress.json", {"version": 2, "completed": {k: {"seconds": v}
                                                                          for k, v in completed.items()}})
    (run / "train_config.json").write_text(json.dumps({"method": "sr", "seed": 3, "sleep": {"enabled": sleep},
                                                      "stream": {"skills": SKILLS}, **config}))
    return run


def _stage(k: int, seconds: float, sleep: bool) -> dict[str, float]:
    phases = {f"{k}.wake": seconds, f"{k}.memory": 0.0, f"{k}.wake.eval": 0.0}
    if sleep and k >= 2:  # the sleep and its evaluation take no time here: the stage's seconds are its wake's
        phases |= {f"{k}.sleep": 0.0, f"{k}.sleep.eval": 0.0}
    return phases


def test_an_unfinished_run_extrapolates_its_stage_times(tmp_path):
    # stages 1-3 took 60, 120, 180 s (linear), stage 4 has its wake (200 s) but not yet its sleep
    completed = {**_stage(1, 60, True), **_stage(2, 120, True), **_stage(3, 180, True), "4.wake": 200.0}
    status = run_status(_run(tmp_path, "sr_seed3", completed), now=None)
    assert (status["variant"], status["done"], status["stages"], status["last_phase"]) == ("sr", 3, 5, "4.wake")
    assert status["left"] == pytest.approx(240 + 300 - 200)  # stages 4 and 5 predicted, less stage 4's 200 s
    assert status["seconds"] == pytest.approx(560) and not status["finished"]
    # without sleep a stage ends with its wake's evaluation; one complete stage gives no estimate
    wake_only = run_status(_run(tmp_path, "wake_only_seed3", _stage(1, 60, False) | {"2.wake": 10.0}, sleep=False))
    assert (wake_only["variant"], wake_only["done"], wake_only["left"]) == ("wake_only", 1, None)


def test_finished_runs_folders_of_runs_and_the_table(tmp_path, capsys):
    done = _run(tmp_path / "grid", "sr_seed0", {k: v for s in range(1, 6) for k, v in _stage(s, 10, True).items()})
    write_checked_json(done / "results.json", {"results_version": 5, "metrics": {"afsr": {"final": 0.9333}}})
    oracle = _run(tmp_path / "grid", "mt_joint_seed0", {"1.wake": 50.0, "1.wake.eval": 5.0}, sleep=False,
                  mt_joint=True)
    assert run_status(oracle)["variant"] == "mt_joint" and run_status(oracle)["done"] == 1
    assert find_runs([tmp_path / "grid", done]) == [oracle, done]  # one level down, each once
    assert find_runs([tmp_path]) == [oracle, done]  # two levels down when nothing is one level down
    main([str(tmp_path / "grid")])
    out = capsys.readouterr().out
    assert "| sr | 3 | 5/5 | 5.sleep.eval (" in out and "finished: AFSR 0.933 |" in out
    assert "| mt_joint | 3 | 1/1 | 1.wake.eval (" in out
    with pytest.raises(FileNotFoundError, match="no run here"):
        find_runs([tmp_path / "nothing"])


def test_a_run_that_has_started_and_recorded_no_phase_is_listed_as_started(tmp_path, capsys):
    """An MT-Joint oracle's one wake records nothing for an hour: its settings fingerprint says it exists."""
    run = tmp_path / "grid" / "mt_joint_0" / "mt_joint_seed0"
    run.mkdir(parents=True)
    config = {"mt_joint": True, "seed": 0, "stream": {"skills": SKILLS}}
    write_fingerprint(run / "settings_fingerprint.json", settings_fingerprint(config))  # (status checks it)
    (run / "train_config.json").write_text(json.dumps(config))
    assert find_runs([tmp_path / "grid"]) == [run]
    status = run_status(run)
    assert (status["done"], status["stages"], status["last_phase"], status["variant"]) == (0, 1, None, "mt_joint")
    main([str(tmp_path / "grid")])
    assert "| 0/1 | started (" in capsys.readouterr().out


def test_a_results_file_that_does_not_match_its_seal_is_not_shown_as_a_result(tmp_path, capsys):
    """Before: "finished: AFSR 0.999" after the seal was removed and AFSR edited, "AFSR 0.100" (truly 0.000) after
    one flipped byte."""
    run = _run(tmp_path, "sr_seed0", {k: v for s in range(1, 6) for k, v in _stage(s, 10, True).items()})
    path = run / "results.json"
    write_checked_json(path, {"results_version": 5, "metrics": {"afsr": {"final": 0.0}}})
    good = path.read_text()
    path.write_text(good.replace('"final": 0.0', '"final": 0.1'))  # one flipped digit
    assert run_status(run)["final"].startswith("results.json not trusted (contents do not match its sha256")
    data = json.loads(good)
    del data["sha256"]
    data["metrics"]["afsr"]["final"] = 0.999
    path.write_text(json.dumps(data))  # the seal removed: schema 5 must carry it
    assert run_status(run)["final"].startswith("results.json not trusted (has no sha256")
    main([str(run)])
    assert "AFSR" not in capsys.readouterr().out


def test_a_config_that_does_not_match_its_seal_gives_no_labels(tmp_path, capsys):
    run = _run(tmp_path, "sr_seed0", _stage(1, 10, True))
    write_checked_json(run / "train_config.json", {"method": "sr", "seed": 3, "sleep": {"enabled": True},
                                                   "stream": {"skills": SKILLS}})
    assert run_status(run)["seed"] == 3 and run_status(run)["config_problem"] is None
    path = run / "train_config.json"
    path.write_text(path.read_text().replace('"seed": 3', '"seed": 4'))  # edited after it was sealed
    status = run_status(run)
    assert status["seed"] is None and status["config_problem"].startswith("train_config.json not trusted")
    main([str(run)])
    assert "train_config.json not trusted" in capsys.readouterr().out
