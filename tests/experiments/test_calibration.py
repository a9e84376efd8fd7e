"""The calibration reading: each criterion of the protocol computed from archived runs, with its verdict."""

from __future__ import annotations

import pytest

from experiments.calibration import CalibrationConfig, main, read_calibration
from sr_imitation.io import write_checked_json
from tests.reporting.test_results import _results


def _archive(root, variants: dict[str, float], seeds=(100, 101, 102)) -> None:
    for variant, shift in variants.items():
        for seed in seeds:
            run = root / f"{variant}_seed{seed}"
            run.mkdir(parents=True)
            write_checked_json(run / "results.json", _results(seed=seed, shift=shift, sleep=False))


def test_each_criterion_is_read_on_the_mean_over_calibration_seeds(tmp_path):
    # the toy results: final AFSR 0.7 + shift; final per skill 0.6 / 0.6 / 0.9; right after own wake 0.9 each;
    # after the next stage 0.7 (skill a) and 0.6 (skill b)
    _archive(tmp_path, {"mt_joint": 0.0, "sequential_bc": 0.0, "wake_only": -0.1})
    reading = read_calibration(CalibrationConfig(archive=tmp_path))
    c = reading["criteria"]
    assert c["C1"]["mt_joint_afsr"] == pytest.approx(0.7) and c["C1"]["met"] is False
    assert c["C1"]["mt_joint_final_per_skill"] == pytest.approx([0.6, 0.6, 0.9])
    assert c["C2"]["own_wake_per_skill"] == pytest.approx([0.9, 0.9, 0.9]) and c["C2"]["met"] is True
    assert c["C3"]["after_next_stage"] == pytest.approx([0.7, 0.6]) and c["C3"]["met"] is False  # 0.7 > 0.45
    assert c["C4"]["wake_only_afsr"] == pytest.approx(0.6) and c["C4"]["met"] is True
    assert all(c[k]["complete"] for k in ("C1", "C2", "C3", "C4"))
    loose = read_calibration(CalibrationConfig(archive=tmp_path, oracle_afsr=0.69, oracle_skill=0.59, forget_ratio=0.8,
                                               wake_only_afsr=0.55))
    assert [loose["criteria"][k]["met"] for k in ("C1", "C2", "C3", "C4")] == [True, True, True, False]


def test_missing_runs_are_not_measured_and_partial_seeds_are_marked(tmp_path, capsys):
    _archive(tmp_path, {"wake_only": 0.0}, seeds=(100,))
    main([f"--archive={tmp_path}", f"--output={tmp_path / 'out'}"])
    text = capsys.readouterr().out
    assert "C4 room" in text and "met (only 1 seed(s))" in text and "C1" not in text.split("|---|")[1]
    reading = read_calibration(CalibrationConfig(archive=tmp_path))
    assert reading["criteria"]["C1"] == {"seeds": 0, "met": None, "complete": False}
    assert (tmp_path / "out" / "calibration.md").is_file() and (tmp_path / "out" / "calibration.json").is_file()
