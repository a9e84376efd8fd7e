"""Issue 59's step A driver (experiments.sleep_screening): rule A as the protocol states it, and the
screening of a stored tiny SAC run end to end (control reproduced, table written, a rerun skips what is done)."""

from __future__ import annotations

import pytest

from experiments.sleep_screening import ScreeningConfig, rule_a, run_screening
from sr_imitation.experiments.archive import archive_run
from sr_imitation.io import read_checked_json
from sr_imitation.substrates.sac.config import EvalConfig
from sr_imitation.substrates.sac.trainer import SACTrainer
from tests.substrates.sac.test_trainer import tiny_config


def test_rule_a_picks_the_best_by_the_margin_and_breaks_ties_in_the_protocol_order():
    assert rule_a({"control": 0.50, "a1": 0.60, "a2": 0.58, "b1": 0.52})["winner"] == "a1"
    tie = rule_a({"control": 0.50, "a1": 0.595, "a2": 0.58, "b1": 0.60})  # b1 best, a1 within 0.01: a1
    assert tie["winner"] == "a1"
    assert rule_a({"control": 0.50, "a1": 0.40, "b2": 0.70})["winner"] == "b2"
    short = rule_a({"control": 0.50, "a1": 0.549, "b1": 0.52})  # best gains 0.049 < 0.05
    assert short["winner"] is None and "no candidate exceeds the control by 0.05 (best a1: +0.049)" in short["reason"]
    assert rule_a({"a1": 0.9})["winner"] is None


def test_the_screening_of_a_stored_run_reproduces_its_control_and_writes_the_table(tmp_path):
    runs = tmp_path / "runs"
    SACTrainer(tiny_config(runs / "sr_seed3", eval=EvalConfig(episodes=2, videos_per_skill=0))).run()
    archive_run(runs / "sr_seed3", tmp_path / "cal", "sr_seed3", keep_weights=True)
    cfg = ScreeningConfig(archive=tmp_path / "cal", seeds=[3], candidates=["control", "a1"],
                          output_root=tmp_path / "out", screening=tmp_path / "screening")
    waiting = run_screening(cfg)  # seed 3 alone: reported, not decided (rule A decides on seeds 100-102)
    assert waiting["rule_a"]["reason"] == "rule A decides on seeds [100, 101, 102] together; these are [3]"
    cfg.decide_on_any_seeds = True
    summary = run_screening(cfg)
    assert summary["controls_reproduce"] == [True] and summary["complete"]
    control, a1 = summary["rows"]
    assert control["final_afsr"] == read_checked_json(tmp_path / "cal" / "sr_seed3" / "results.json")[
        "metrics"]["afsr"]["final"]
    assert a1["stop_iteration"] == 12 and a1["stop_reason"] == "max_iterations"  # the whole (tiny) budget
    assert summary["rule_a"]["reason"].startswith(("a1 ", "no candidate"))
    assert summary["before"]["3"]["skills"] == ["reach", "door-open"] and len(summary["before"]["3"]["success"]) == 2
    table = (tmp_path / "screening" / "screening.md").read_text()
    assert "| control | 3 |" in table and "| a1 | 3 |" in table
    assert "Controls reproduce their archived runs: [True]" in table
    assert read_checked_json(tmp_path / "screening" / "screening.json") == summary
    assert (tmp_path / "screening" / "a1_seed3" / "results.json").is_file()
    # a second call finds every re-sleep finished and writes the same table
    assert run_screening(cfg) == summary
    with pytest.raises(ValueError, match="candidates"):
        ScreeningConfig(candidates=["a3"])
