"""The last-sleep report (issue 89) on archived runs: every value recomputed from results.json by hand, the files it
writes, and a run without a final sleep refused in one line naming it."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from sr_imitation.infra.cli_errors import run_cli
from sr_imitation.io import read_checked_json
from sr_imitation.reporting.last_sleep import last_sleep_row, main, write_report

ARCHIVE = Path(__file__).resolve().parents[1] / "docs" / "results" / "needle_cpu_m16_compare"


@pytest.mark.parametrize("seed", [0, 2, 4])
def test_a_row_is_what_the_run_s_results_say(seed):
    run = ARCHIVE / f"sr_seed{seed}"
    raw = json.loads((run / "results.json").read_text())
    woke, slept = raw["extra"]["success_matrix_after_wake"][-1], raw["success_matrix"][-1]
    sleep = raw["stages"][-1]["sleep"]
    row = last_sleep_row(run)
    assert row["newest"] == raw["skills"][-1] == "pullout"
    assert (row["newest_after_wake"], row["newest_after_sleep"]) == (woke[-1], slept[-1])
    assert row["older_change"] == {s: slept[i] - woke[i] for i, s in enumerate(raw["skills"][:-1])}
    assert row["older_mean_change"] == pytest.approx(sum(slept[:-1]) / 4 - sum(woke[:-1]) / 4, abs=1e-12)
    assert row["loss_before"] == pytest.approx(sum(sleep["initial_memory_losses"]))
    assert row["newest_loss_before"] == 0.0 and row["newest_loss_after"] > 0  # its memory is the policy's own output
    assert row["stop_iteration"] == sleep["stop_iteration"]


def test_the_report_writes_a_sealed_table_and_a_figure(tmp_path):
    rows = write_report([ARCHIVE / f"sr_seed{s}" for s in range(5)], tmp_path)
    assert read_checked_json(tmp_path / "last_sleep.json")["rows"] == json.loads(json.dumps(rows))
    text = (tmp_path / "last_sleep.md").read_text()
    assert text.count("| sr_seed") == 5 and "Over 5 runs: the newest skill changed +0.000 +- 0.000" in text
    assert "re-sleeps" not in text
    assert (tmp_path / "last_sleep.png").read_bytes()[:4] == b"\x89PNG"


def test_a_run_without_a_final_sleep_is_one_line_naming_it(tmp_path, capsys):
    with pytest.raises(SystemExit) as done:
        run_cli("sr_imitation.reporting.last_sleep", main, [str(ARCHIVE / "wake_only_seed0"),
                                                             f"--output={tmp_path / 'out'}"])
    err = capsys.readouterr().err
    assert done.value.code == 2 and err.count("\n") == 1 and "wake_only_seed0: no final sleep" in err
    assert not (tmp_path / "out").exists()


def test_an_anchor_off_re_sleep_beside_a_run_gets_its_own_row(tmp_path):
    """A re-sleep folder (sr-sleep's sealed sleep.json) beside the run: its row from the before/after evaluation and the
    sleep's losses, and its own line under the table."""
    from sr_imitation.io import write_checked_json

    run = tmp_path / "sr_seed0"
    shutil.copytree(ARCHIVE / "sr_seed0", run)
    skills = ["approach", "place", "insert", "regrasp", "pullout"]
    before, after = [0.3, 0.9, 1.0, 1.0, 1.0], [0.4, 0.8, 1.0, 1.0, 0.9]
    write_checked_json(tmp_path / "sr_seed0_final_sleep_anchor_off" / "sleep.json", {
        "sleep_settings": {"anchor_strength": 0.0},
        "sleep": {"skills": skills, "initial_memory_losses": [1e-3] * 4 + [0.0], "final_memory_losses": [1e-5] * 5,
                  "anchor_lambda": 0.0, "stop_iteration": 700},
        "success": {s: {"before": b, "after": a} for s, b, a in zip(skills, before, after, strict=True)}})
    rows = write_report([run], tmp_path / "out")
    assert len(rows) == 2 and rows[1]["newest_change"] == pytest.approx(-0.1)
    assert rows[1]["older_mean_change"] == pytest.approx((0.1 - 0.1) / 4) and rows[1]["loss_before"] == 4e-3
    text = (tmp_path / "out" / "last_sleep.md").read_text()
    assert "Over 1 anchor-off re-sleeps: the newest skill changed -0.100" in text


@pytest.mark.parametrize("archive", ["lerobot06_needle_m16", "order_needle_m16_reverse"])
def test_an_archived_last_sleep_table_is_what_its_runs_say(archive):
    """Every archived last-sleep table (issue 89 item 3) recomputes from the raw files beside it: the runs' results.json
    and the anchor-off re-sleeps' sleep.json, row by row, with the markdown table that shows them."""
    from sr_imitation.reporting.last_sleep import ANCHOR_OFF, render_markdown, resleep_row

    folder = ARCHIVE.parent / archive
    stored = read_checked_json(folder / "last_sleep" / "last_sleep.json")["rows"]
    rows = [resleep_row(folder / Path(r["run"]).name) if r["run"].endswith(ANCHOR_OFF)
            else last_sleep_row(folder / Path(r["run"]).name) for r in stored]
    names = [n for s in range(5) for n in (f"sr_seed{s}", f"sr_seed{s}{ANCHOR_OFF}")]
    assert [Path(r["run"]).name for r in stored] == names
    for row, old in zip(rows, stored, strict=True):
        assert {k: v for k, v in row.items() if k != "run"} == {k: v for k, v in old.items() if k != "run"}
    assert (folder / "last_sleep" / "last_sleep.md").read_text() == render_markdown(stored)


def test_one_run_s_summary_gives_no_standard_error(tmp_path):
    """With one run the mean has no SE: the summary says so instead of printing nan."""
    text = (write_report([ARCHIVE / "sr_seed0"], tmp_path), (tmp_path / "last_sleep.md").read_text())[1]
    assert "nan" not in text and "Over 1 runs: the newest skill changed +0.000 across" in text
    assert "(one run: no SE)" in text
