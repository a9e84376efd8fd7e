"""The cosine-matrix summary of re-sleeps (experiments.sleep_cosines): what it copies, what it refuses
before the archive changes, and Eq. 1's optimum it reports on families of cosine matrices (orthogonal: 1/k; an
aligned pair: the third memory weighs more; a zero gradient: masked)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import experiments.sleep_cosines as sleep_cosines
from experiments.sleep_cosines import (
    CosinesConfig,
    collect,
    differing_values,
    largest_off_diagonal,
    main,
    run_cosines,
    summarize_run,
)
from sr_imitation.core.aggregation import nash_weights
from sr_imitation.infra.cli_errors import run_cli
from sr_imitation.infra.fingerprint import settings_fingerprint, write_fingerprint
from sr_imitation.io import read_checked_json, write_checked_json

ROOT = Path(__file__).resolve().parents[2]


def _cosines(vectors: np.ndarray) -> list[list[float]]:
    unit = vectors / np.linalg.norm(vectors, axis=1, keepdims=True)
    return (unit @ unit.T).tolist()


def fake_resleep(root: Path, name: str, first: list[list[float]], last: list[list[float]],
                 alpha: list[list[float]], stage: int = 3) -> Path:
    """A finished re-sleep's files, as ``sr-sac-sleep`` leaves them (only what the summary reads)."""
    run = root / name
    k = len(last)
    repeated = root / "archived" / name
    write_checked_json(repeated / "results.json", {"code": {"commit": "fedcba9876543210", "dirty": False}})
    write_checked_json(run / "resleep.json", {"source": f"store/{name}", "archived": str(repeated),
                                              "stage": stage, "changes": [], "changed": []})
    write_checked_json(run / "results.json", {"code": {"commit": "0123456789abcdef", "dirty": False},
                                              "metrics": {"afsr": {"final": 0.5}}})
    write_fingerprint(run / "settings_fingerprint.json", settings_fingerprint({"seed": 1}))
    write_checked_json(run / "stages" / f"{stage:02d}_skill" / "sleep" / "sleep_diagnostics.json",
                       {"skills": [f"s{i}" for i in range(k)], "alpha": alpha, "cosines_first_last": [first, last],
                        "stop_iteration": len(alpha), "stop_reason": "plateau"})
    return run


@pytest.fixture(autouse=True)
def compared(monkeypatch):
    """The comparison with the repeated run (``reporting.compare``, tested on its own) as a fixed text: these fake
    re-sleeps have no progress record to compare. ``compared.text`` can be changed by a test."""
    class Compared:
        text = "A = a\nB = b\nsettings: the same\n12 measured values compared: the runs differ in 0 values; " \
               "every number equal\n"

    monkeypatch.setattr(sleep_cosines, "report_text", lambda a, b: (Compared.text, {}))
    return Compared


def test_eq1_optimum_on_families_of_cosine_matrices(tmp_path):
    """Orthogonal gradients: 1/k. An aligned pair beside an orthogonal third: still 1/k on the simplex (each block's
    columns sum as its rows do), so uniform weights alone do not prove C near I: the summary reports C itself. Three
    directions in a plane at 0, 1 and 2 rad: all weight on the middle one, which agrees with both others."""
    archive = tmp_path / "archive"
    orthogonal = np.eye(3).tolist()
    row = summarize_run(collect(fake_resleep(tmp_path / "runs", "orth", orthogonal, orthogonal, [[1 / 3] * 3] * 4),
                                archive))
    assert row["largest_off_diagonal_last"] == 0.0
    np.testing.assert_allclose(row["nash_optimum_on_last"], [1 / 3] * 3, atol=1e-9)
    assert row["largest_weight_deviation"] == pytest.approx(0.0)

    aligned = _cosines(np.array([[1.0, 0.1, 0.0], [1.0, -0.1, 0.0], [0.0, 0.0, 1.0]]))  # cos(g1, g2) = 0.98
    row = summarize_run(collect(fake_resleep(tmp_path / "runs", "aligned", aligned, aligned,
                                             [[1 / 3] * 3, [0.25, 0.25, 0.5]]), archive))
    assert row["largest_off_diagonal_last"] == pytest.approx(0.9802, abs=1e-4)
    np.testing.assert_allclose(row["nash_optimum_on_last"], [1 / 3] * 3, atol=1e-4)
    assert row["largest_weight_deviation"] == pytest.approx(0.5 - 1 / 3)  # iteration 0 is left out, 1 is not

    fan = _cosines(np.array([[1.0, 0.0], [np.cos(1.0), np.sin(1.0)], [np.cos(2.0), np.sin(2.0)]]))
    row = summarize_run(collect(fake_resleep(tmp_path / "runs", "fan", fan, fan, [[1 / 3] * 3] * 2), archive))
    np.testing.assert_allclose(row["nash_optimum_on_last"], nash_weights(np.array(fan)).alpha)
    np.testing.assert_allclose(row["nash_optimum_on_last"], [0, 1, 0], atol=1e-6)


def test_a_zero_gradient_is_masked_in_the_largest_off_diagonal():
    c = np.array([[1.0, 0.3, 0.0], [0.3, 1.0, 0.0], [0.0, 0.0, 0.0]])  # the third memory: zero gradient
    assert largest_off_diagonal(c) == pytest.approx(0.3)
    assert largest_off_diagonal(np.array([[1.0, 0.0], [0.0, 0.0]])) == 0.0


def test_the_summary_archives_and_writes_json_md_and_png(tmp_path):
    c = _cosines(np.array([[1.0, 0.2], [0.0, 1.0]]))
    runs = [fake_resleep(tmp_path / "runs", f"r{i}", c, c, [[0.5, 0.5]] * 3) for i in range(2)]
    archive = tmp_path / "archive"
    summary = run_cosines(CosinesConfig(archive=archive, runs=runs))
    assert [r["run"] for r in summary["runs"]] == ["r0", "r1"]
    assert sorted(p.name for p in (archive / "r0").iterdir()) == [
        "compare.txt", "resleep.json", "results.json", "settings_fingerprint.json", "stage3_sleep_diagnostics.json"]
    assert summary["runs"][0]["differing_values"] == 0
    assert read_checked_json(archive / "cosines.json") == json.loads(json.dumps(summary))
    md = (archive / "cosines.md").read_text()
    assert f"| r0 | `{tmp_path / 'runs' / 'archived' / 'r0'}` | 0 | 3 | 0.500 | 3 (plateau) | 0.196 / 0.196 |" in md
    assert (archive / "cosines.png").read_bytes()[:4] == b"\x89PNG"
    again = run_cosines(CosinesConfig(archive=archive))  # from the archive alone
    assert again == summary


def test_a_damaged_file_stops_before_the_archive_changes(tmp_path, capsys):
    c = np.eye(2).tolist()
    run = fake_resleep(tmp_path / "runs", "r", c, c, [[0.5, 0.5]])
    archive = tmp_path / "archive"
    collect(run, archive)
    before = (archive / "r" / "stage3_sleep_diagnostics.json").read_bytes()
    diag = run / "stages" / "03_skill" / "sleep" / "sleep_diagnostics.json"
    diag.write_text(diag.read_text().replace('"plateau"', '"max_iterations"'))
    with pytest.raises(SystemExit) as stop:
        run_cli("sleep_cosines", main, [f"--archive={archive}", f"--runs=[{run}]"])
    assert stop.value.code == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and str(diag) in err[0], err
    assert (archive / "r" / "stage3_sleep_diagnostics.json").read_bytes() == before  # the archived copy stays
    assert not (archive / "cosines.json").exists()


def test_a_run_without_cosines_or_without_its_stage_is_named(tmp_path):
    run = fake_resleep(tmp_path / "runs", "old", np.eye(2).tolist(), np.eye(2).tolist(), [[0.5, 0.5]])
    diag = run / "stages" / "03_skill" / "sleep" / "sleep_diagnostics.json"
    write_checked_json(diag, {**{k: v for k, v in read_checked_json(diag).items() if k != "cosines_first_last"}})
    with pytest.raises(ValueError, match="no cosine matrices"):
        summarize_run(collect(run, tmp_path / "archive"))
    diag.unlink()
    with pytest.raises(FileNotFoundError, match="not a finished re-sleep"):
        collect(run, tmp_path / "archive2")
    other = fake_resleep(tmp_path / "runs", "lost", np.eye(2).tolist(), np.eye(2).tolist(), [[0.5, 0.5]])
    (tmp_path / "runs" / "archived" / "lost" / "results.json").unlink()
    with pytest.raises(FileNotFoundError, match="repeats is not here"):
        collect(other, tmp_path / "archive3")
    assert not (tmp_path / "archive3" / "lost").exists()


def test_the_comparison_verdict_is_read_from_compare_txt(tmp_path, compared):
    assert differing_values("2766 measured values compared: the runs differ in 0 values; every number equal") == 0
    assert differing_values("40 measured values compared: the runs differ in 3 values; largest numeric ...") == 3
    assert differing_values("40 measured values compared: the runs agree; every number equal") == 0
    assert differing_values("no verdict") is None
    compared.text = "A = a\nB = b\n9 measured values compared: the runs differ in 2 values; largest ...\n"
    c = np.eye(2).tolist()
    summary = run_cosines(CosinesConfig(archive=tmp_path / "a", runs=[fake_resleep(tmp_path / "runs", "d", c, c,
                                                                                     [[0.5, 0.5]])]))
    assert summary["runs"][0]["differing_values"] == 2
    assert "| 2 | 3 |" in (tmp_path / "a" / "cosines.md").read_text()


def test_the_archived_cosines_recompute():
    """The archived summary is what its archived re-sleeps give (skipped before any is archived): every value read
    from the archived files exactly; Eq. 1's optimum, which the summary solves again, to 1e-12 (the solver's floats
    differ in the last bits between CPU types: the AMD EPYC family 25 model 1 and the Intel Xeon that wrote it)."""
    archive = ROOT / "docs" / "results" / "sac_sleep_cosines"
    if not (archive / "cosines.json").is_file():
        pytest.skip("no re-sleep's cosines are archived yet")
    stored = read_checked_json(archive / "cosines.json")
    again = json.loads(json.dumps({"runs": [summarize_run(p.parent) for p in sorted(archive.glob("*/resleep.json"))]}))
    assert len(stored["runs"]) == len(again["runs"]) == 5 and set(stored) == {"runs"}
    for old, new in zip(stored["runs"], again["runs"], strict=True):
        assert old["nash_optimum_on_last"] == pytest.approx(new.pop("nash_optimum_on_last"), rel=1e-12, abs=0)
        old = {k: v for k, v in old.items() if k != "nash_optimum_on_last"}
        assert old == new, old["run"]
