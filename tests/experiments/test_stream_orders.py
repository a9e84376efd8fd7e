"""The stream-order summary (experiments.stream_orders): rankings, the paired interaction and the anchor's share on
families of made-up values, then on the archived needle runs given as both orders (nothing may differ)."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from experiments.stream_orders import OrdersConfig, interaction, main, paired, ranking, run_orders, summarize_stream
from sr_imitation.experiments.hypotheses import archived_values
from sr_imitation.infra.cli_errors import run_cli
from sr_imitation.io import read_checked_json
from sr_imitation.reporting.last_sleep import ANCHOR_OFF, last_sleep_row, resleep_row

ROOT = Path(__file__).resolve().parents[2]
R1 = ROOT / "docs/results/lerobot06_needle_m16"


def test_interaction_is_the_paired_difference_of_differences():
    ref = {"sr": {0: 0.8, 1: 0.9, 2: 0.7}, "wake_only": {0: 0.6, 1: 0.7, 2: 0.7}}
    new = {"sr": {0: 0.5, 1: 0.6}, "wake_only": {0: 0.6, 1: 0.7}}
    out = interaction(ref, new)
    assert out["seeds"] == [0, 1]  # seed 2 lacks its new-order pair
    assert out["diffs"] == pytest.approx([-0.3, -0.3]) and out["mean"] == pytest.approx(-0.3)
    assert out["sem"] == pytest.approx(0.0, abs=1e-12)
    assert interaction(ref, {"sr": {0: 0.5}}) is None  # no wake-only in the new order


@pytest.mark.parametrize("shift", [0.0, 0.25, -0.1])
def test_a_common_shift_leaves_rankings_and_the_interaction_alone(shift):
    ref = {"sr": {0: 0.9, 1: 0.8}, "replay": {0: 0.4, 1: 0.5}, "wake_only": {0: 0.6, 1: 0.7}}
    new = {m: {s: v + shift for s, v in d.items()} for m, d in ref.items()}
    s = summarize_stream({"forward": ref, "reverse": new})
    rev = s["orders"]["reverse"]
    assert rev["ranking"] == ranking(ref) == ["sr", "wake_only", "replay"] and rev["ranking_held"]
    assert rev["interaction_sr_wake_only"]["mean"] == pytest.approx(0.0, abs=1e-12)


def test_a_swap_is_a_changed_ranking_and_the_anchor_share_is_paired():
    ref = {"sr": {0: 0.9, 1: 0.8}, "wake_only": {0: 0.6, 1: 0.7}, "sr_no_anchor": {0: 0.7, 1: 0.8}}
    new = {"sr": {0: 0.5, 1: 0.6}, "wake_only": {0: 0.6, 1: 0.7}, "sr_no_anchor": {1: 0.2}}
    s = summarize_stream({"forward": ref, "reverse": new})
    rev = s["orders"]["reverse"]
    assert not rev["ranking_held"] and rev["ranking"][0] == "wake_only"
    assert rev["anchor"]["seeds"] == [1] and rev["anchor"]["mean"] == pytest.approx(0.4)
    assert math.isnan(rev["anchor"]["sem"])
    assert s["orders"]["forward"]["anchor"]["mean"] == pytest.approx(0.1)
    assert paired({0: 1.0}, {1: 1.0}) is None


def test_the_archived_needle_runs_as_both_orders(tmp_path):
    run_cli("stream_orders", main, [f"--orders=[needle/forward={R1},needle/reverse={R1}]",
                                    f"--output={tmp_path}"])
    data = read_checked_json(tmp_path / "orders.json")["streams"]["needle"]
    fwd, rev = data["orders"]["forward"], data["orders"]["reverse"]
    for method in ("sr", "wake_only", "replay"):
        values = archived_values(R1, method, "afsr")
        assert fwd["methods"][method]["values"] == [values[s] for s in sorted(values)] and len(values) == 5
    assert fwd["ranking"] == ["sr", "wake_only", "replay"] and rev["ranking_held"]
    assert rev["interaction_sr_wake_only"]["diffs"] == [0.0] * 5
    assert "sr > wake_only > replay" in (tmp_path / "orders.md").read_text()
    assert (tmp_path / "orders.png").read_bytes()[:4] == b"\x89PNG"
    sleep = fwd["last_sleep"]  # the last sleep per order, from the runs and their anchor-off re-sleeps
    on = [last_sleep_row(R1 / f"sr_seed{s}")["older_mean_change"] for s in range(5)]
    off = [resleep_row(R1 / f"sr_seed{s}{ANCHOR_OFF}")["older_mean_change"] for s in range(5)]
    assert sleep["newest"] == "pullout" and sleep["newest_change"]["diffs"] == [0.0] * 5
    assert sleep["older_change"]["diffs"] == pytest.approx(on) and sleep["older_change_anchor_off"]["diffs"] == off
    assert sleep["older_with_minus_without"]["diffs"] == pytest.approx([a - b for a, b in zip(on, off, strict=True)])
    assert rev["last_sleep"] == sleep and "the last sleep of its SR runs: the newest skill (pullout)" in (
        tmp_path / "orders.md").read_text()


def test_an_order_without_sr_runs_has_no_last_sleep(tmp_path):
    """An archive with no SR run (the forward sr_no_anchor runs alone) gives no last-sleep entry, not an error."""
    forward = ROOT / "docs/results/order_needle_m16_forward"
    out = run_orders(OrdersConfig(orders=[f"needle/forward={forward}"]))
    assert out["needle"]["orders"]["forward"]["last_sleep"] is None
    assert sorted(out["needle"]["orders"]["forward"]["methods"]) == ["sr_no_anchor"]


def test_a_seed_archived_twice_and_a_bad_entry_are_refused(tmp_path, capsys):
    with pytest.raises(ValueError, match="archived twice"):
        run_orders(OrdersConfig(orders=[f"needle/forward={R1}+{R1}"]))
    with pytest.raises(SystemExit) as stop:
        run_cli("stream_orders", main, [f"--orders=[needle-forward={R1}]", f"--output={tmp_path}"])
    assert stop.value.code == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and "needle-forward" in err[0], err
    assert not (tmp_path / "orders.json").exists()
