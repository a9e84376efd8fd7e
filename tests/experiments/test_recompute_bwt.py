"""recompute_bwt on the committed raw results: it reproduces the stored bwt and the known post-wake numbers."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from experiments.recompute_bwt import find_runs, main, recompute_run, summarize_runs

RESULTS = Path(__file__).resolve().parents[2] / "docs" / "results"


def test_needle_compare_both_references_and_paired_difference(tmp_path, capsys):
    runs = [recompute_run(d) for d in find_runs([RESULTS / "needle_cpu_compare"])]
    assert {r.variant for r in runs} == {"sr", "wake_only", "sequential_bc", "sr_no_anchor"}
    for r in runs:
        assert r.bwt == pytest.approx(r.stored_bwt, abs=1e-9), r.run  # the reported bwt is reproduced
    summary = summarize_runs(runs)
    sr, wake_only = summary["variants"]["sr"], summary["variants"]["wake_only"]
    # Post-wake reference: SR +0.100 +- 0.063 vs wake-only -0.028 +- 0.031 (reported bwt -0.056 vs -0.028).
    assert (sr["bwt_wake"]["mean"], sr["bwt_wake"]["sem"]) == pytest.approx((0.100, 0.063), abs=5e-4)
    assert (wake_only["bwt_wake"]["mean"], wake_only["bwt_wake"]["sem"]) == pytest.approx((-0.028, 0.031), abs=5e-4)
    assert (sr["bwt"]["mean"], wake_only["bwt"]["mean"]) == pytest.approx((-0.056, -0.028), abs=5e-4)
    # Without sleep both references are the same evaluation.
    for r in runs:
        if r.variant in ("wake_only", "sequential_bc"):
            assert r.bwt_wake == r.bwt
    paired = summary["paired_minus_baseline"]["sr"]
    assert summary["baseline"] == "wake_only" and paired["seeds"] == [0, 1, 2]
    assert paired["bwt_wake"]["mean"] == pytest.approx(sr["bwt_wake"]["mean"] - wake_only["bwt_wake"]["mean"])

    main([f"--runs={RESULTS / 'needle_cpu_compare'}", f"--output={tmp_path / 'bwt.md'}"])
    assert "| sr | 0, 1, 2 | -0.056 +- 0.007 | +0.100 +- 0.063 |" in capsys.readouterr().out
    saved = json.loads((tmp_path / "bwt.json").read_text())
    assert len(saved["runs"]) == 12 and (tmp_path / "bwt.md").is_file()


def test_sac_runs_without_after_wake_evaluations(tmp_path):
    runs = {Path(r.run).name: r for r in (recompute_run(d) for d in find_runs([RESULTS / "sac_mt5_cpu"]))}
    assert runs["wake_s0"].bwt_wake == runs["wake_s0"].bwt  # no sleep: the stage evaluation is the after-wake one
    assert runs["sleep_s0"].bwt_wake is None  # sleep stages were not evaluated after wake in these runs
    # A SAC result with after-wake evaluations (as sr-rl-train now writes them by default).
    nan = None
    results = {"skills": ["a", "b", "c"], "seed": 5, "method": "sleeping_robots",
               "success_matrix": [[0.9, nan, nan], [0.5, 0.8, nan], [0.2, 0.6, 1.0]],
               "metrics": {"bwt": ((0.2 - 0.9) + (0.6 - 0.8)) / 2},
               "stages": [{"eval_after_wake": {"success_rate": 0.9}},
                          {"sleep": {}, "eval_after_wake": {"success_rate": 0.95}},
                          {"sleep": {}, "eval_after_wake": {"success_rate": 0.7}}]}
    run = tmp_path / "sr_s5"
    run.mkdir()
    (run / "results.json").write_text(json.dumps(results))
    r = recompute_run(run)
    assert (r.variant, r.seed, r.substrate) == ("sr", 5, "sac")
    assert r.bwt_wake == pytest.approx(((0.2 - 0.9) + (0.6 - 0.95)) / 2)
    assert r.bwt == pytest.approx(r.stored_bwt)


def test_errors_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="no results.json"):
        find_runs([tmp_path])
    (tmp_path / "results.json").write_text(json.dumps({"skills": ["a"], "success_matrix": [[1.0]]}))
    with pytest.raises(ValueError, match=r"results.json: neither"):
        recompute_run(tmp_path)
