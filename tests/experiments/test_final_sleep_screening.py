"""The final-sleep screening's reader and decision rule (experiments/final_sleep_screening.py): the rule as the
protocol in docs/RESULTS.md writes it, over families of made-up measures, and the reader over archived runs."""

from __future__ import annotations

import copy
import shutil
from pathlib import Path

import pytest

from experiments.final_sleep_screening import CANDIDATES, ScreeningConfig, decide, main, order_rows
from sr_imitation.infra.cli_errors import run_cli
from sr_imitation.io import read_checked_json, write_checked_json
from sr_imitation.reporting.last_sleep import last_sleep_row, resleep_row

ROOT = Path(__file__).resolve().parents[2]
R2 = ROOT / "docs" / "results" / "lerobot06_mt5_imitation"
REVERSE = ROOT / "docs" / "results" / "order_mt5_imitation_reverse"


def _order(c0: list[float], by_candidate: dict[str, list[float]], newest: float = 0.0) -> dict:
    """One order: C0's final AFSR per seed (100-102) and each candidate's; every newest change ``newest``."""
    rows = {"C0": {100 + i: {"afsr": v, "newest_change": -0.3, "older_change": 0.0} for i, v in enumerate(c0)}}
    for c, values in by_candidate.items():
        rows[c] = {100 + i: {"afsr": v, "newest_change": newest, "older_change": 0.0} for i, v in enumerate(values)}
    return rows


@pytest.mark.parametrize("shift", [0.0, 0.2, 0.5])
def test_the_rule_passes_a_gain_of_the_size_it_asks_on_two_seeds_and_nothing_less(shift):
    """(i) +0.03 on the mean and two of three seeds above C0; (ii) the newest skill's change above -0.10; (iii) no loss
    over 0.03 in the other order: each at its edge, at any level of C0's values."""
    c0 = [0.5 + shift / 2, 0.4 + shift / 2, 0.6 + shift / 2]
    up = lambda d: [v + x for v, x in zip(c0, d, strict=True)]  # noqa: E731
    other = _order(c0, dict.fromkeys(CANDIDATES, c0))
    cases = {
        "passes": (up([0.04, 0.04, 0.04]), 0.0, c0, True),
        "mean gain short of 0.03": (up([0.029, 0.029, 0.029]), 0.0, c0, False),
        "one seed above only": (up([0.2, -0.01, -0.01]), 0.0, c0, False),
        "two seeds above, mean enough": (up([0.1, 0.1, -0.05]), 0.0, c0, True),
        "newest skill spent": (up([0.04, 0.04, 0.04]), -0.11, c0, False),
        "other order loses 0.031": (up([0.04, 0.04, 0.04]), 0.0, [v - 0.031 for v in c0], False),
        "other order loses 0.029": (up([0.04, 0.04, 0.04]), 0.0, [v - 0.029 for v in c0], True),
    }
    for name, (values, newest, in_other, passes) in cases.items():
        orders = {"forward": _order(c0, {**dict.fromkeys(CANDIDATES, c0), "anchor_off": in_other}),
                  "reverse": _order(c0, {**dict.fromkeys(CANDIDATES, c0), "anchor_off": values}, newest)}
        verdict = decide(orders, "reverse")
        assert verdict["candidates"]["anchor_off"]["passes"] is passes, name
        assert verdict["winner"] == ("anchor_off" if passes else None), name
    assert decide({"forward": other, "reverse": other}, "reverse")["winner"] is None  # no candidate differs from C0


def test_the_winner_is_the_highest_mean_and_a_tie_goes_to_the_simplest():
    c0 = [0.5, 0.5, 0.5]
    forward = _order(c0, dict.fromkeys(CANDIDATES, c0))
    reverse = _order(c0, {"anchor_off": [0.6] * 3, "anchor_newest": [0.7] * 3, "guard": [0.7] * 3})
    assert decide({"forward": forward, "reverse": reverse}, "reverse")["winner"] == "anchor_newest"
    reverse = _order(c0, {"anchor_off": [0.7] * 3, "anchor_newest": [0.7] * 3, "guard": [0.7] * 3})
    assert decide({"forward": forward, "reverse": reverse}, "reverse")["winner"] == "anchor_off"
    forward = _order(c0, {"anchor_off": [0.4] * 3, "anchor_newest": c0, "guard": c0})  # C1 loses the other order
    assert decide({"forward": forward, "reverse": reverse}, "reverse")["winner"] == "anchor_newest"


def test_a_screening_missing_a_seed_or_a_candidate_names_no_winner():
    """The rule reads means over every seed of both orders: with a re-sleep, a candidate or a run missing, a
    candidate that would pass on the seeds it has wins nothing, and the text says what is missing."""
    from experiments.final_sleep_screening import render

    c0 = [0.5, 0.5, 0.5]
    full = {"forward": _order(c0, dict.fromkeys(CANDIDATES, c0)),
            "reverse": _order(c0, {"anchor_off": [0.7] * 3, "anchor_newest": c0, "guard": c0})}
    assert decide(full, "reverse")["winner"] == "anchor_off" and decide(full, "reverse")["missing"] == []
    no_seed, no_candidate, no_run = (copy.deepcopy(full) for _ in range(3))
    del no_seed["reverse"]["guard"][102]
    del no_candidate["forward"]["anchor_newest"]
    for c in no_run["forward"]:
        del no_run["forward"][c][101]
    for orders, missing in ((no_seed, ["reverse guard seed 102"]),
                            (no_candidate, [f"forward anchor_newest seed {s}" for s in (100, 101, 102)]),
                            (no_run, [f"forward {c} seed 101" for c in ("C0", *CANDIDATES)])):
        verdict = decide(orders, "reverse")
        assert verdict["missing"] == missing and verdict["winner"] is None
        assert "Not read: the screening is incomplete" in render(orders, verdict)
        assert "Winner" not in render(orders, verdict) and "No candidate passes" not in render(orders, verdict)
    partial = {o: {c: {100: r[100]} for c, r in rows.items()} for o, rows in full.items()}  # seed 100 alone
    assert decide(partial, "reverse")["missing"] == []
    missing = decide(partial, "reverse", seeds=[100, 101, 102])["missing"]
    assert len(missing) == 16 and missing[0] == "forward C0 seed 101"


def test_the_reader_takes_c0_from_the_run_and_a_candidate_from_its_re_sleep():
    """On the archived MT5 runs: C0's measures are the run's own last sleep, C1's the anchor-off re-sleep's."""
    rows = order_rows(REVERSE)
    run = last_sleep_row(REVERSE / "sr_seed0")
    assert rows["C0"][0]["newest_change"] == run["newest_change"]
    assert rows["C0"][0]["older_change"] == pytest.approx(run["older_mean_change"], abs=1e-12)
    off = resleep_row(REVERSE / "sr_seed0_final_sleep_anchor_off")
    assert rows["anchor_off"][0]["newest_change"] == off["newest_change"]
    results = read_checked_json(REVERSE / "sr_seed0_final_sleep_anchor_off" / "sleep.json")["success"]
    assert rows["anchor_off"][0]["afsr"] == pytest.approx(sum(r["after"] for r in results.values()) / 5, abs=1e-12)
    assert rows["own"][0] == rows["C0"][0]  # sr-sleep repeats the run's own final sleep (exactly, AMD EPYC 26/2)
    forward = order_rows(R2)
    assert forward["own"][0] == forward["C0"][0]  # in the forward order too
    assert decide({"forward": order_rows(R2), "reverse": rows}, "reverse")["own_repeats_c0"]["reverse"][0] is True


def test_a_re_sleep_that_did_not_start_from_the_run_s_last_wake_is_refused(tmp_path):
    archive = tmp_path / "arch"
    shutil.copytree(REVERSE / "sr_seed0", archive / "sr_seed0")
    record = read_checked_json(REVERSE / "sr_seed0_final_sleep_anchor_off" / "sleep.json")
    record.pop("sha256", None)
    skill = record["sleep"]["skills"][1]
    record["success"][skill]["before"] -= 0.1
    write_checked_json(archive / "sr_seed0_final_sleep_guard" / "sleep.json", record)
    with pytest.raises(ValueError, match="sr_seed0_final_sleep_guard: its success before the sleep is not sr_seed0"):
        order_rows(archive)


def test_the_command_writes_its_files_and_refuses_a_trigger_order_it_was_not_given(tmp_path, capsys):
    main([f"--orders=[forward={R2},reverse={REVERSE}]", "--trigger_order=reverse", f"--output={tmp_path}"])
    assert {p.name for p in tmp_path.iterdir()} == {"screening.json", "screening.md", "screening.png"}
    assert read_checked_json(tmp_path / "screening.json")["decision"]["trigger_order"] == "reverse"
    with pytest.raises(ValueError, match="trigger_order: 'backward' is not one of the orders"):
        ScreeningConfig(orders=[f"forward={R2}", f"reverse={REVERSE}"], trigger_order="backward")
    with pytest.raises(SystemExit):
        run_cli("screening", main, [f"--orders=[forward={R2}]", "--trigger_order=forward"])
    assert "give two orders" in capsys.readouterr().err
