"""docs/RESULTS.md's headline numbers recompute from the committed raw files (issue 28's calibrated stream): the
first paragraph, Table 2's rows, the pre-registered tests and the per-seed line. A number typed by hand that drifts
from its raw file fails here (session 29 found a per-seed line that had)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from sr_imitation.experiments.hypotheses import HypothesesConfig, archived_values, run_tests

DOCS = Path(__file__).resolve().parents[1] / "docs"
ARCHIVE = DOCS / "results" / "needle_cpu_m16_compare"
VARIANTS = {"sr": "sr", "wake_only": "wake_only", "sr_sleep_only": "sr_sleep_only", "replay": "replay",
            "sequential_bc": "sequential_bc", "ewc": "ewc_lam10000", "lwf": "lwf_w0.1", "m2distill": "m2distill_w0.01",
            "mt_joint": "mt_joint"}


@pytest.fixture(scope="module")
def text() -> str:
    return re.sub(r"\s+", " ", (DOCS / "RESULTS.md").read_text())  # lines wrap anywhere


def _mean_se(values: list[float]) -> str:
    import numpy as np

    return f"{np.mean(values):.3f} +- {np.std(values, ddof=1) / np.sqrt(len(values)):.3f}"


def test_the_first_paragraph_and_the_tests_recompute(text):
    h1, h2 = run_tests(HypothesesConfig(archive=ARCHIVE, tests=["sr>wake_only", "sr!=replay"]))
    sr, wake = (list(archived_values(ARCHIVE, v, "afsr").values()) for v in ("sr", "wake_only"))
    assert (f"final AFSR {_mean_se(sr)} vs wake-only {_mean_se(wake)}, paired +{h1['mean']:.3f} +- {h1['sem']:.3f} "
            f"over 5 training seeds, one-sided paired t-test p = {h1['p']:.3f}") in text
    assert f"bootstrap 95% CI [{h1['ci_low']:+.3f}, {h1['ci_high']:+.3f}]" in text
    assert (f"| H1: SR - wake-only > 0 (one-sided) | 0-4 | {h1['mean']:+.3f} +- {h1['sem']:.3f} | "
            f"[{h1['ci_low']:+.3f}, {h1['ci_high']:+.3f}] | {h1['t']:.2f} | {h1['p']:.3f} |") in text
    assert (f"| H2: SR - replay != 0 (two-sided) | 0-4 | {h2['mean']:+.3f} +- {h2['sem']:.3f} | "
            f"[{h2['ci_low']:+.3f}, {h2['ci_high']:+.3f}] | {h2['t']:.2f} | {h2['p']:.4f} |") in text


def test_table_2_rows_and_the_per_seed_line_recompute(text):
    sr = archived_values(ARCHIVE, "sr", "afsr")
    for name, variant in VARIANTS.items():
        values = archived_values(ARCHIVE, variant, "afsr")
        assert sorted(values) == [0, 1, 2, 3, 4], variant
        row = re.search(r"\| \**\*?" + re.escape(name) + r"[^|]*\| 0-4 \| ([^|]*) \|", text)
        assert row is not None, name
        assert row.group(1).strip("* ") == _mean_se(list(values.values())), name
        if name != "sr":  # the last column: paired AFSR - SR
            diffs = [values[s] - sr[s] for s in sorted(sr)]
            assert re.search(r"\| \**\*?" + re.escape(name) + r"[^\n]*\| " + re.escape(f"{_signed(diffs)}") + r" \|",
                             text), name
    wake = archived_values(ARCHIVE, "wake_only", "afsr")
    pairs = ", ".join(f"{sr[s]:.3f} / {wake[s]:.3f}" for s in sorted(sr))
    assert f"Per seed (AFSR, SR / wake-only): {pairs}:" in text


def _signed(values: list[float]) -> str:
    import numpy as np

    return f"{np.mean(values):+.3f} +- {np.std(values, ddof=1) / np.sqrt(len(values)):.3f}"


def test_the_memory_budget_table_recomputes(text):
    from sr_imitation.experiments.memory_budget import BudgetConfig, collect

    folders = {8: "needle_cpu_m8_compare", 16: "needle_cpu_m16_compare", 64: "needle_cpu_m64_compare",
               256: "needle_cpu_m256_compare", 1024: "needle_cpu_v2_compare"}
    summary = collect(BudgetConfig(points=[f"{b}={DOCS / 'results' / f}" for b, f in folders.items()],
                                   variants=["sr", "wake_only", "replay"], seeds=[0, 1, 2]))

    def cell(d: dict) -> str:
        return f"{d['mean']:.3f} +- {d['sem']:.3f}"

    for budget, row in summary["budgets"].items():
        assert all(row[v]["seeds"] == [0, 1, 2] for v in ("sr", "wake_only", "replay")), budget
        afsr = " | ".join(cell(row[v]["afsr"]) for v in ("sr", "wake_only", "replay"))
        assert f"| {budget} | {afsr} | " in text, budget


def test_the_vision_rows_so_far_recompute():
    """Every filled cell of the vision table's "Runs so far" rows (typed in as each run landed) against its run."""
    import json

    from sr_imitation.stream.summary import phase_seconds

    archive = DOCS / "results" / "needle_cpu_vision_compare"
    lines = (DOCS / "RESULTS.md").read_text().splitlines()
    start = lines.index("| training seed | SR | wake-only | SR - wake-only | SR BWT / BWT_wake | "
                        "wake-only BWT / BWT_wake | minutes SR / wake-only |")
    rows = []
    for line in lines[start + 2:]:  # the table's rows: up to its first non-table line
        if not line.startswith("| "):
            break
        rows.append(line)
    assert len(rows) >= 5
    for line in rows:
        cells = [c.strip() for c in line.strip("|").split("|")]
        seed = int(cells[0].split()[0])
        runs = {v: archive / f"{v}_seed{seed}" for v in ("sr", "wake_only")}
        found = {v: json.loads((r / "results.json").read_text())["metrics"] for v, r in runs.items()
                 if (r / "results.json").is_file()}
        minutes = cells[6].split(" / ")
        for v, afsr_cell, bwt_cell, minute in (("sr", cells[1], cells[4], minutes[0]),
                                               ("wake_only", cells[2], cells[5], minutes[1])):
            if v not in found:
                assert afsr_cell in ("running", "queued") and minute == "-", line
                continue
            m = found[v]
            assert afsr_cell == f"{m['afsr']['final']:.3f} +- {m['afsr']['final_sem']:.3f}", line
            assert bwt_cell == f"{m['bwt']['final']:+.3f} / {m['bwt_wake']['final']:+.3f}", line
            assert minute == f"{phase_seconds(runs[v]) / 60:.1f}", line
        if len(found) == 2:
            assert cells[3] == f"{found['sr']['afsr']['final'] - found['wake_only']['afsr']['final']:+.3f}", line


def test_the_vision_baseline_rows_so_far_recompute():
    """Every filled cell of the vision table's "Baselines so far" rows against its run (and SR's at the same seed)."""
    import json

    from sr_imitation.stream.summary import phase_seconds

    archive = DOCS / "results" / "needle_cpu_vision_compare"
    lines = (DOCS / "RESULTS.md").read_text().splitlines()
    start = lines.index("| variant | training seed | final AFSR | AFSR - SR (same seed) | BWT / BWT_wake | minutes |")
    rows = []
    for line in lines[start + 2:]:
        if not line.startswith("| "):
            break
        rows.append(line)
    variants = {"sequential BC": "sequential_bc", "MT-Joint": "mt_joint"}
    assert sorted((r.split("|")[1].strip(), r.split("|")[2].strip()) for r in rows) == sorted(
        (name, str(seed)) for name in variants for seed in range(3))
    for line in rows:
        cells = [c.strip() for c in line.strip("|").split("|")]
        variant, seed = variants[cells[0]], int(cells[1])
        run = archive / f"{variant}_seed{seed}"
        if not (run / "results.json").is_file():
            assert cells[2] in ("running", "queued") and cells[5] == "-", line
            continue
        m = json.loads((run / "results.json").read_text())["metrics"]
        assert cells[2] == f"{m['afsr']['final']:.3f} +- {m['afsr']['final_sem']:.3f}", line
        sr = archive / f"sr_seed{seed}" / "results.json"
        if sr.is_file():
            sr_afsr = json.loads(sr.read_text())["metrics"]["afsr"]["final"]
            assert cells[3] == f"{m['afsr']['final'] - sr_afsr:+.3f}", line
        if variant == "mt_joint":
            assert cells[4] == "n/a", line
        else:
            assert cells[4] == f"{m['bwt']['final']:+.3f} / {m['bwt_wake']['final']:+.3f}", line
        assert cells[5] == f"{phase_seconds(run) / 60:.1f}", line


def test_the_vision_test_h4_and_its_first_lines_recompute(text):
    """H4 (pre-registered): its table row and the first paragraph's vision sentence, from the vision archive."""
    import json

    import numpy as np

    archive = DOCS / "results" / "needle_cpu_vision_compare"
    (h4,) = run_tests(HypothesesConfig(archive=archive, tests=["sr>wake_only"]))
    assert h4["seeds"] == [0, 1, 2, 3, 4]
    assert (f"| H4: SR - wake-only > 0 (one-sided), vision stream | 0-4 | {h4['mean']:+.3f} +- {h4['sem']:.3f} | "
            f"[{h4['ci_low']:+.3f}, {h4['ci_high']:+.3f}] | {h4['t']:.2f} | {h4['p']:.4f} |") in text
    sr, wake = (list(archived_values(archive, v, "afsr").values()) for v in ("sr", "wake_only"))
    assert (f"SR {_mean_se(sr)} vs wake-only {_mean_se(wake)}, paired {h4['mean']:+.3f} +- {h4['sem']:.3f} over 5 "
            f"training seeds, every pair positive, one-sided paired t-test p = {h4['p']:.4f}") in text
    assert min(a - b for a, b in zip(sr, wake, strict=True)) > 0
    assert f"[{h4['ci_low']:+.3f}, {h4['ci_high']:+.3f}]); the gain is retention" in text
    bwt = {v: [json.loads((archive / f"{v}_seed{s}" / "results.json").read_text())["metrics"]["bwt"]["final"]
               for s in range(5)] for v in ("sr", "wake_only")}
    assert f"(BWT {np.mean(bwt['sr']):+.3f} vs {np.mean(bwt['wake_only']):+.3f})" in text
    assert (f"BWT {_signed(bwt['sr'])} for SR" in text and f"against {_signed(bwt['wake_only'])} for wake-only"
            in text)


def test_the_vision_summary_numbers_recompute(text):
    """The vision section's per-skill line (H4) and the baselines' three-seed means, from the committed summary."""
    import json

    summary = json.loads((DOCS / "results" / "needle_cpu_vision_compare" / "summary" / "summary.json").read_text())
    variants = summary["variants"]
    assert [int(x) for x in variants["sr"]["seeds"]] == [0, 1, 2, 3, 4]
    assert [int(x) for x in variants["mt_joint"]["seeds"]] == [0, 1, 2]
    final = {v: variants[v]["final_success"] for v in ("sr", "wake_only")}
    per_skill = ", ".join(f"{skill} {final['sr'][skill]['mean']:.3f} / {final['wake_only'][skill]['mean']:.3f}"
                          for skill in ("approach", "place", "insert", "regrasp", "pullout"))
    assert f"SR / wake-only {per_skill};" in text

    def cell(d: dict) -> str:
        return f"{d['mean']:.3f} +- {d['sem']:.3f}"

    assert f"**sequential BC {cell(variants['sequential_bc']['afsr'])}**" in text
    assert f"BWT {cell(variants['sequential_bc']['bwt'])})" in text
    assert f"**MT-Joint {cell(variants['mt_joint']['afsr'])}**" in text
    paired = summary["paired"]["mt_joint"]["afsr"]
    assert f"{-paired['mean']:.3f} +- {paired['sem']:.3f} below SR at the same seeds" in text
    joint = variants["mt_joint"]["final_success"]
    assert f"place ({cell(joint['place'])}:" in text and f"insert ({cell(joint['insert'])})" in text
    own = {v: variants[v]["success_after_own_wake"]["insert"] for v in ("sequential_bc", "wake_only")}
    assert f"({cell(own['sequential_bc'])}, against {cell(own['wake_only'])} for wake-only" in text


def test_the_vision_oracle_at_twice_the_steps_rows_recompute():
    """The exploratory MT-Joint 2x table: each filled cell against its run (1x and SR: the pre-registered archive)."""
    import json

    results = DOCS / "results"
    lines = (DOCS / "RESULTS.md").read_text().splitlines()
    start = lines.index("| training seed | MT-Joint, 9000 steps | MT-Joint, 18,000 steps | SR |")
    rows = lines[start + 2:start + 5]
    assert [int(r.split("|")[1]) for r in rows] == [0, 1, 2]
    for line in rows:
        cells = [c.strip() for c in line.strip("|").split("|")]
        seed = int(cells[0])
        for cell, run in zip(cells[1:], (results / "needle_cpu_vision_compare" / f"mt_joint_seed{seed}",
                                         results / "needle_cpu_vision_mtj_long" / f"mt_joint_seed{seed}",
                                         results / "needle_cpu_vision_compare" / f"sr_seed{seed}"), strict=True):
            if not (run / "results.json").is_file():
                assert cell == "running", line
                continue
            afsr = json.loads((run / "results.json").read_text())["metrics"]["afsr"]
            assert cell == f"{afsr['final']:.3f} +- {afsr['final_sem']:.3f}", line
    import numpy as np

    text = re.sub(r"\s+", " ", (DOCS / "RESULTS.md").read_text())
    long_ = [json.loads((results / "needle_cpu_vision_mtj_long" / f"mt_joint_seed{s}" / "results.json").read_text())
             ["metrics"]["afsr"]["final"] for s in range(3)]
    sr = [json.loads((results / "needle_cpu_vision_compare" / f"sr_seed{s}" / "results.json").read_text())
          ["metrics"]["afsr"]["final"] for s in range(3)]
    diffs = np.array(long_) - np.array(sr)
    assert f"MT-Joint at 18,000 steps is {_mean_se(long_)}" in text
    assert f"paired to SR {_signed(list(diffs))}" in text
