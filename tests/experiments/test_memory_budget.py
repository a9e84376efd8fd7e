"""The memory-budget curve: per budget archive, mean +- SE per variant and SR's paired difference; a run whose
stored buffer size is not its point's budget is refused."""

from __future__ import annotations

import json

import pytest

from experiments.memory_budget import main
from sr_imitation.io import write_checked_json
from tests.reporting.test_results import _results


def _archive(root, budget, shifts):
    for variant, values in shifts.items():
        for seed, shift in enumerate(values):
            run = root / f"{variant}_seed{seed}"
            run.mkdir(parents=True)
            write_checked_json(run / "results.json", _results(seed=seed, shift=shift, sleep=variant == "sr",
                                                              config={"memory": {"buffer_size": budget}}))
    return root


def test_the_curve_pairs_seeds_per_budget_and_checks_the_budget(tmp_path):
    a = _archive(tmp_path / "m8", 8, {"sr": [0.0, -0.02], "wake_only": [-0.1, -0.12]})
    b = _archive(tmp_path / "m64", 64, {"sr": [0.0, 0.0], "wake_only": [-0.01, -0.03]})
    out = tmp_path / "out"
    main([f"--points=[8={a},64={b}]", "--variants=[sr,wake_only]", f"--output={out}"])
    summary = json.loads((out / "memory_budget.json").read_text())
    assert summary["budgets"]["8"]["wake_only"]["paired_to_sr"]["afsr"]["mean"] == pytest.approx(0.1)
    assert summary["budgets"]["64"]["wake_only"]["paired_to_sr"]["afsr"]["mean"] == pytest.approx(0.02)
    assert (out / "memory_budget.png").stat().st_size > 1000 and "| 8 |" in (out / "memory_budget.md").read_text()
    # --seeds: every point averages the same training seeds
    main([f"--points=[8={a},64={b}]", "--variants=[sr,wake_only]", "--seeds=[1]", f"--output={out}"])
    summary = json.loads((out / "memory_budget.json").read_text())
    assert summary["budgets"]["8"]["wake_only"]["paired_to_sr"]["seeds"] == [1]
    assert summary["budgets"]["8"]["wake_only"]["paired_to_sr"]["afsr"]["mean"] == pytest.approx(0.1)
    assert summary["budgets"]["64"]["wake_only"]["afsr"]["mean"] == pytest.approx(
        summary["budgets"]["64"]["sr"]["afsr"]["mean"] - 0.03)
    with pytest.raises(ValueError, match="memory.buffer_size 8, but its point says 16"):
        main([f"--points=[16={a}]", "--variants=[sr,wake_only]"])
