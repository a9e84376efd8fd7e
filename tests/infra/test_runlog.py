"""The run log: JSON lines flushed per record, appended on resume, read back with re-run phases replacing the
interrupted ones; wandb in offline mode writes locally; the sleep loop reports every iteration."""

from __future__ import annotations

import json
import math

import pytest
import torch

from sr_imitation.core import OutputDistillationMemory, SleepConfig, sleep_consolidate
from sr_imitation.infra.runlog import LOG_NAME, RunLog, WandbConfig, read_log


def test_records_are_json_lines_flushed_as_written(tmp_path):
    log = RunLog(tmp_path)
    log.log("wake", stage=1, step=0, loss=0.5, alpha=torch.tensor([0.25, 0.75]))
    # Visible before close (flushed): a user can tail -f the file.
    lines = (tmp_path / LOG_NAME).read_text().splitlines()
    assert len(lines) == 1
    rec = json.loads(lines[0])
    assert rec["kind"] == "wake" and rec["stage"] == 1 and rec["step"] == 0
    assert rec["loss"] == 0.5 and rec["alpha"] == [0.25, 0.75]
    log.log("eval", stage=1, success=float("nan"))
    log.close()
    assert json.loads((tmp_path / LOG_NAME).read_text().splitlines()[1])["success"] == "nan"


def test_resume_appends_and_read_log_keeps_the_completed_phase(tmp_path):
    with RunLog(tmp_path) as log:
        for step in range(3):
            log.log("wake", stage=2, step=step, loss=1.0 + step)
    with (tmp_path / LOG_NAME).open("a") as f:
        f.write('{"kind": "wake", "stage": 2, "st')  # killed while writing
    assert len(read_log(tmp_path / LOG_NAME)) == 3  # a torn last line is skipped by readers
    # The resumed run cuts the torn record and re-runs stage 2 from its start.
    with RunLog(tmp_path) as log:
        for step in range(3):
            log.log("wake", stage=2, step=step, loss=10.0 + step)
        log.log("phase", stage=2, name="wake done")
    records = read_log(tmp_path / LOG_NAME)
    assert [r["loss"] for r in records if r["kind"] == "wake"] == [10.0, 11.0, 12.0]
    assert [r["name"] for r in records if r["kind"] == "phase"] == ["wake done"]


def test_a_corrupt_line_in_the_middle_is_an_error(tmp_path):
    (tmp_path / LOG_NAME).write_text('{"kind": "a"}\nnot json\n{"kind": "b"}\n')
    with pytest.raises(json.JSONDecodeError):
        read_log(tmp_path / LOG_NAME)


def test_wandb_offline_writes_locally(tmp_path, monkeypatch):
    monkeypatch.setenv("WANDB_SILENT", "true")
    with RunLog(tmp_path, WandbConfig(enable=True, mode="offline"), config={"seed": 3}) as log:
        log.log("sleep", stage=2, step=0, objective=0.1, solver_status="optimal")
    runs = list((tmp_path / "wandb").glob("offline-run-*"))
    assert len(runs) == 1 and any(runs[0].rglob("*.wandb"))
    with pytest.raises(ValueError, match="wandb.mode"):
        WandbConfig(mode="cloud")


def test_sleep_reports_every_applied_iteration(tmp_path):
    torch.manual_seed(0)
    net = torch.nn.Linear(3, 2)
    snap = torch.nn.Linear(3, 2)
    mems = [OutputDistillationMemory.from_snapshot(s, lambda o, m=m: m(o["x"]), {"x": torch.randn(32, 3)})
            for s, m in (("a", snap), ("b", torch.nn.Linear(3, 2)), ("c", torch.nn.Linear(3, 2)))]
    seen = []
    with RunLog(tmp_path) as log:
        result = sleep_consolidate(
            list(net.parameters()), lambda o: net(o["x"]), mems,
            SleepConfig(max_iterations=7, batch_size=8, anchor_tau=None, early_stop_window=100),
            progress=False, on_iteration=lambda it, rec: (seen.append(it), log.log("sleep", 3, it, **rec)),
        )
    assert seen == list(range(7)) == list(range(result.stop_iteration))
    records = read_log(tmp_path / LOG_NAME)
    assert [r["objective"] for r in records] == pytest.approx(result.sleep_objective)
    assert all(r["solver_status"] in ("optimal", "pareto_stationary") and math.isclose(sum(r["alpha"]), 1.0)
               for r in records)


def test_a_resumed_run_continues_the_same_wandb_run(tmp_path, monkeypatch):
    """Like LeRobot's run_id, the wandb id is stored with the run; a resume continues that run, its
    steps after the records already logged."""
    import json

    from sr_imitation.infra.runlog import WANDB_ID_FILE

    monkeypatch.setenv("WANDB_SILENT", "true")
    with RunLog(tmp_path, WandbConfig(enable=True, mode="offline")) as log:
        first = log._wandb.id
        log.log("wake", stage=1, step=0, loss=1.0)
        log.log("wake", stage=1, step=1, loss=0.5)
    assert json.loads((tmp_path / WANDB_ID_FILE).read_text())["id"] == first
    with RunLog(tmp_path, WandbConfig(enable=True, mode="offline")) as log:
        assert log._wandb.id == first and log._global_step == 2
        log.log("wake", stage=2, step=0, loss=0.4)
