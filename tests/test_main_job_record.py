"""README's main-job picture, numbers and time come from the archived main job (docs/results/main_job): its two runs'
results recompute the figure's sentence and the AFSRs README quotes, and the time README states is the archived
measurement (``timing.json``, written when ``bash .ci/main.sh`` ran on a fresh clone with both cores idle)."""

from __future__ import annotations

import re
from pathlib import Path

from sr_imitation.io import read_checked_json
from sr_imitation.reporting.side_by_side import difference_sentence, side_by_side

ROOT = Path(__file__).resolve().parents[1]
ARCHIVE = ROOT / "docs" / "results" / "main_job"


def _paragraph() -> str:
    """README's main-job paragraph: the block after its ``<!-- id: main-job -->`` comment, up to a blank line."""
    readme = (ROOT / "README.md").read_text()
    block = readme.split("<!-- id: main-job -->", 1)[1].strip().split("\n\n", 1)[0]
    return " ".join(block.split())


def test_readme_shows_the_archived_figure_and_the_runs_recompute_its_numbers():
    summary = side_by_side({"sr": ARCHIVE / "sr_seed1000", "wake_only": ARCHIVE / "wake_only_seed1000"})
    assert difference_sentence(summary) in (ARCHIVE / "results.md").read_text()
    assert (ARCHIVE / "comparison.png").read_bytes()[:4] == b"\x89PNG"
    assert "(docs/results/main_job/comparison.png)" in (ROOT / "README.md").read_text()
    text = _paragraph()
    sr, wo = (summary["runs"][name]["afsr_final"] for name in ("sr", "wake_only"))
    assert f"SR {sr:.3f}" in text and f"wake-only {wo:.3f}" in text, text
    assert f"{summary['difference']:+.3f}" in text, text


def test_readme_s_time_is_the_archived_idle_measurement():
    timing = read_checked_json(ARCHIVE / "timing.json")
    assert timing["command"] == "bash .ci/main.sh" and timing["cores_idle"] is True
    assert timing["wall_s"] > 0 and re.fullmatch(r"[0-9a-f]{7,40}", timing["commit"])
    minutes = round(timing["wall_s"] / 60)
    text = _paragraph()
    assert f"{minutes} minutes" in text and timing["machine"] in text, text
