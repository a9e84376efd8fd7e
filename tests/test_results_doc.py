"""docs/RESULTS.md's and README's numbers recompute from the committed raw files: the calibrated needle stream's
first paragraph, Table 2's rows, the tests and the per-seed line; the MT5 imitation stream's calibration readings;
the first look's outcomes. A number typed by hand that drifts from its raw file fails here."""

from __future__ import annotations

import functools
import json
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sr_imitation.experiments.hypotheses import HypothesesConfig, archived_values, run_tests
from sr_imitation.experiments.mt5_compare import VARIANTS as MT5_VARIANTS
from sr_imitation.infra.fingerprint import FINGERPRINT_FILE, read_fingerprint
from sr_imitation.io import read_checked_json
from sr_imitation.reporting.same_weights import same_files
from sr_imitation.reporting.summary import phase_seconds
from sr_imitation.substrates.sac.cli import parse as parse_sac_config

DOCS = Path(__file__).resolve().parents[1] / "docs"
ARCHIVE = DOCS / "results" / "needle_cpu_m16_compare"
VARIANTS = {"sr": "sr", "wake_only": "wake_only", "sr_sleep_only": "sr_sleep_only", "replay": "replay",
            "sequential_bc": "sequential_bc", "ewc": "ewc_lam10000", "lwf": "lwf_w0.1", "m2distill": "m2distill_w0.01",
            "mt_joint": "mt_joint"}


RECORDS = DOCS / "results" / "records"
"""Each protocol's dated record, one file each (moved out of RESULTS.md unchanged on 2026-12-07)."""


def _record_text() -> str:
    """RESULTS.md and every protocol's record, as one text (the numbers quoted in either are checked alike)."""
    return "\n".join(p.read_text() for p in [DOCS / "RESULTS.md", *sorted(RECORDS.glob("*.md"))])


PAGES = [DOCS / "RESULTS.md", *sorted(RECORDS.glob("*.md")), DOCS / "EVIDENCE.md", DOCS.parent / "README.md"]
"""The pages whose numbers carry ids: RESULTS, every record, the evidence page and README."""
ID = re.compile(r"^\s*<!-- id: ([\w.-]+) -->\s*$")
DATED = re.compile(r"^\s*\*{1,2}20\d\d-\d\d-\d\d")
"""The start of a dated entry (``*2026-11-28 03:27 UTC, ...*``), which ends the block before it."""


@functools.cache
def _blocks() -> dict[str, str]:
    """Every id'd block of ``PAGES``: the lines after ``<!-- id: x -->`` (and any further ids on the lines right after
    it, which name the same block) up to the next blank line, the next id or the next dated entry (a table: its
    header, rule and rows)."""
    blocks: dict[str, str] = {}
    for page in PAGES:
        lines = page.read_text().split("\n")
        for i, line in enumerate(lines):
            if (m := ID.match(line)) is None:
                continue
            assert m[1] not in blocks, f"id {m[1]} twice"
            j = i + 1
            while j < len(lines) and ID.match(lines[j]):
                j += 1
            body = [lines[j]] if j < len(lines) else []
            j += 1
            while j < len(lines) and lines[j].strip() and not ID.match(lines[j]) and not DATED.match(lines[j]):
                body.append(lines[j])
                j += 1
            blocks[m[1]] = "\n".join(body)
    return blocks


def _by_id(ident: str) -> str:
    """The block that ``<!-- id: ident -->`` names, whitespace collapsed (its lines wrap anywhere)."""
    assert ident in _blocks(), f"no block has the id {ident}"
    return " ".join(_blocks()[ident].split())


def _states(ident: str, *numbers: str) -> None:
    """The block ``ident`` states each of ``numbers`` (each formatted as written: "0.895 +- 0.032", "p = 0.029", a
    verdict), in this order, each a whole number there (0.03 is not found in 0.032): the words around them may change
    freely; a number that drifts from its recompute fails here."""
    block, at = _by_id(ident), 0
    for number in numbers:
        found = re.compile(r"(?<![\w.+\-])" + re.escape(number) + r"(?!\.?\d)").search(block, at)
        assert found is not None, f"{ident}: {number!r} not found (in order) in: {block[at:at + 300]!r}"
        at = found.end()


@pytest.fixture(scope="module")
def readme() -> str:
    """README and the user documents it links for the evidence and the reference (moved out of it on 2026-12-07)."""
    pages = [DOCS.parent / "README.md", DOCS / "EVIDENCE.md", DOCS / "COMMANDS.md"]
    return re.sub(r"\s+", " ", "\n".join(p.read_text() for p in pages))


def _mean_se(values: list[float]) -> str:
    return f"{np.mean(values):.3f} +- {np.std(values, ddof=1) / np.sqrt(len(values)):.3f}"


def _table_rows(ident: str) -> list[list[str]]:
    """The cells of the rows of the table ``<!-- id: ident -->`` names (after its header and rule)."""
    assert ident in _blocks(), f"no block has the id {ident}"
    lines = _blocks()[ident].splitlines()
    assert lines[0].startswith("|") and set(lines[1].replace("|", "").strip()) <= set("-: "), ident
    return [[c.strip() for c in line.strip().strip("|").split("|")] for line in lines[2:] if line.startswith("| ")]


def _row(ident: str, key: str) -> list[str]:
    """The row of table ``ident`` whose first cell (bold or italics aside) is ``key`` or starts with ``key`` and a
    space."""
    rows = [cells for cells in _table_rows(ident) if re.fullmatch(re.escape(key) + r"( .*)?", cells[0].strip("*"))]
    assert len(rows) == 1, (ident, key, len(rows))
    return rows[0]


def _metrics(run: Path) -> dict | None:
    """A run's ``results.json`` metrics, or None while it has not finished."""
    path = run / "results.json"
    return json.loads(path.read_text())["metrics"] if path.is_file() else None


def _afsr_cell(metrics: dict) -> str:
    return f"{metrics['afsr']['final']:.3f} +- {metrics['afsr']['final_sem']:.3f}"


def test_the_first_paragraph_and_the_tests_recompute():
    h1, h2 = run_tests(HypothesesConfig(archive=ARCHIVE, tests=["sr>wake_only", "sr!=replay"]))
    sr, wake = (list(archived_values(ARCHIVE, v, "afsr").values()) for v in ("sr", "wake_only"))
    _states("needle-m16-h1", _mean_se(sr), _mean_se(wake), f"+{h1['mean']:.3f} +- {h1['sem']:.3f}", "5",
            f"p = {h1['p']:.3f}", f"[{h1['ci_low']:+.3f}, {h1['ci_high']:+.3f}]")
    for key, h, p in (("H1:", h1, f"{h1['p']:.3f}"), ("H2:", h2, f"{h2['p']:.4f}")):
        assert _row("needle-m16-h-table", key)[1:6] == ["0-4", f"{h['mean']:+.3f} +- {h['sem']:.3f}",
                                                         f"[{h['ci_low']:+.3f}, {h['ci_high']:+.3f}]", f"{h['t']:.2f}",
                                                         p], key


def test_table_2_rows_and_the_per_seed_line_recompute():
    sr = archived_values(ARCHIVE, "sr", "afsr")
    for name, variant in VARIANTS.items():
        values = archived_values(ARCHIVE, variant, "afsr")
        assert sorted(values) == [0, 1, 2, 3, 4], variant
        cells = _row("needle-m16-table2", name)
        assert cells[1] == "0-4" and cells[2].strip("* ") == _mean_se(list(values.values())), name
        if name != "sr":  # the last column: paired AFSR - SR
            diffs = [values[s] - sr[s] for s in sorted(sr)]
            assert cells[-1].strip("* ") == _signed(diffs), name
    wake = archived_values(ARCHIVE, "wake_only", "afsr")
    _states("needle-m16-per-seed", *(f"{sr[s]:.3f} / {wake[s]:.3f}" for s in sorted(sr)))


def _signed(values: list[float]) -> str:
    return f"{np.mean(values):+.3f} +- {np.std(values, ddof=1) / np.sqrt(len(values)):.3f}"


def test_the_memory_budget_table_recomputes():
    from experiments.memory_budget import BudgetConfig, collect

    folders = {8: "needle_cpu_m8_compare", 16: "needle_cpu_m16_compare", 64: "needle_cpu_m64_compare",
               256: "needle_cpu_m256_compare", 1024: "needle_cpu_v2_compare"}
    summary = collect(BudgetConfig(points=[f"{b}={DOCS / 'results' / f}" for b, f in folders.items()],
                                   variants=["sr", "wake_only", "replay"], seeds=[0, 1, 2]))

    def cell(d: dict) -> str:
        return f"{d['mean']:.3f} +- {d['sem']:.3f}"

    for budget, row in summary["budgets"].items():
        assert all(row[v]["seeds"] == [0, 1, 2] for v in ("sr", "wake_only", "replay")), budget
        assert _row("memory-budget-table", str(budget))[1:4] == [cell(row[v]["afsr"])
                                                                  for v in ("sr", "wake_only", "replay")], budget


def test_the_vision_rows_so_far_recompute():
    """Every filled cell of the vision table's "Runs so far" rows (typed in as each run landed) against its run."""
    archive = DOCS / "results" / "needle_cpu_vision_compare"
    rows = _table_rows("vision-rows")
    assert len(rows) >= 5
    for cells in rows:
        seed = int(cells[0].split()[0])
        runs = {v: archive / f"{v}_seed{seed}" for v in ("sr", "wake_only")}
        found = {v: m for v, r in runs.items() if (m := _metrics(r)) is not None}
        minutes = cells[6].split(" / ")
        for v, afsr_cell, bwt_cell, minute in (("sr", cells[1], cells[4], minutes[0]),
                                               ("wake_only", cells[2], cells[5], minutes[1])):
            if v not in found:
                assert afsr_cell in ("running", "queued") and minute == "-", cells
                continue
            m = found[v]
            assert afsr_cell == _afsr_cell(m), cells
            assert bwt_cell == f"{m['bwt']['final']:+.3f} / {m['bwt_wake']['final']:+.3f}", cells
            assert minute == f"{phase_seconds(runs[v]) / 60:.1f}", cells
        if len(found) == 2:
            assert cells[3] == f"{found['sr']['afsr']['final'] - found['wake_only']['afsr']['final']:+.3f}", cells


def test_the_vision_baseline_rows_so_far_recompute():
    """Every filled cell of the vision table's "Baselines so far" rows against its run (and SR's at the same seed)."""
    archive = DOCS / "results" / "needle_cpu_vision_compare"
    rows = _table_rows("vision-baselines")
    variants = {"sequential BC": "sequential_bc", "MT-Joint": "mt_joint"}
    assert sorted((cells[0], cells[1]) for cells in rows) == sorted(
        (name, str(seed)) for name in variants for seed in range(3))
    for cells in rows:
        variant, seed = variants[cells[0]], int(cells[1])
        run = archive / f"{variant}_seed{seed}"
        m = _metrics(run)
        if m is None:
            assert cells[2] in ("running", "queued") and cells[5] == "-", cells
            continue
        assert cells[2] == _afsr_cell(m), cells
        sr = _metrics(archive / f"sr_seed{seed}")
        if sr is not None:
            assert cells[3] == f"{m['afsr']['final'] - sr['afsr']['final']:+.3f}", cells
        if variant == "mt_joint":
            assert cells[4] == "n/a", cells
        else:
            assert cells[4] == f"{m['bwt']['final']:+.3f} / {m['bwt_wake']['final']:+.3f}", cells
        assert cells[5] == f"{phase_seconds(run) / 60:.1f}", cells


def test_the_vision_test_h4_and_its_first_lines_recompute():
    """H4 (exploratory since 2026-11-28: seed 0's pair was known when it was written): its table row and the first
    paragraph's vision sentence, from the vision archive."""
    archive = DOCS / "results" / "needle_cpu_vision_compare"
    (h4,) = run_tests(HypothesesConfig(archive=archive, tests=["sr>wake_only"]))
    assert h4["seeds"] == [0, 1, 2, 3, 4]
    assert _row("vision-h4-table", "H4:")[1:6] == ["0-4", f"{h4['mean']:+.3f} +- {h4['sem']:.3f}",
                                                    f"[{h4['ci_low']:+.3f}, {h4['ci_high']:+.3f}]", f"{h4['t']:.2f}",
                                                    f"{h4['p']:.4f}"]
    sr, wake = (list(archived_values(archive, v, "afsr").values()) for v in ("sr", "wake_only"))
    assert min(a - b for a, b in zip(sr, wake, strict=True)) > 0  # "every pair positive"
    bwt = {v: list(archived_values(archive, v, "bwt").values()) for v in ("sr", "wake_only")}
    _states("vision-h4-summary", _mean_se(sr), _mean_se(wake), f"{h4['mean']:+.3f} +- {h4['sem']:.3f}", "5",
            f"p = {h4['p']:.4f}", f"[{h4['ci_low']:+.3f}, {h4['ci_high']:+.3f}]",
            f"{np.mean(bwt['sr']):+.3f}", f"{np.mean(bwt['wake_only']):+.3f}")
    _states("vision-five-seeds", _mean_se(sr), _mean_se(wake), f"{_signed(bwt['sr'])}", _signed(bwt["wake_only"]))


def test_the_vision_summary_numbers_recompute():
    """The vision section's per-skill line (H4) and the baselines' three-seed means, from the committed summary."""
    summary = json.loads((DOCS / "results" / "needle_cpu_vision_compare" / "summary" / "summary.json").read_text())
    variants = summary["variants"]
    assert [int(x) for x in variants["sr"]["seeds"]] == [0, 1, 2, 3, 4]
    assert [int(x) for x in variants["mt_joint"]["seeds"]] == [0, 1, 2]
    final = {v: variants[v]["final_success"] for v in ("sr", "wake_only")}
    _states("vision-five-seeds", *(f"{skill} {final['sr'][skill]['mean']:.3f} / {final['wake_only'][skill]['mean']:.3f}"
                                   for skill in ("approach", "place", "insert", "regrasp", "pullout")))

    def cell(d: dict) -> str:
        return f"{d['mean']:.3f} +- {d['sem']:.3f}"

    paired = summary["paired"]["mt_joint"]["afsr"]
    joint = variants["mt_joint"]["final_success"]
    own = {v: variants[v]["success_after_own_wake"]["insert"] for v in ("sequential_bc", "wake_only")}
    _states("vision-baselines-means", cell(variants["sequential_bc"]["afsr"]), cell(variants["sequential_bc"]["bwt"]),
            cell(variants["mt_joint"]["afsr"]), f"{-paired['mean']:.3f} +- {paired['sem']:.3f}", cell(joint["place"]),
            cell(joint["insert"]), cell(own["sequential_bc"]), cell(own["wake_only"]))


def test_the_vision_oracle_at_twice_the_steps_rows_recompute():
    """The exploratory MT-Joint 2x table: each filled cell against its run (1x and SR: the pre-registered archive)."""
    compare = DOCS / "results" / "needle_cpu_vision_compare"
    long_archive = DOCS / "results" / "needle_cpu_vision_mtj_long"
    rows = _table_rows("vision-mtj-long")
    assert [int(cells[0]) for cells in rows] == [0, 1, 2]
    for cells in rows:
        seed = int(cells[0])
        for cell, run in zip(cells[1:], (compare / f"mt_joint_seed{seed}", long_archive / f"mt_joint_seed{seed}",
                                         compare / f"sr_seed{seed}"), strict=True):
            m = _metrics(run)
            assert cell == ("running" if m is None else _afsr_cell(m)), cells
    long_ = [_metrics(long_archive / f"mt_joint_seed{s}")["afsr"]["final"] for s in range(3)]
    sr = [_metrics(compare / f"sr_seed{s}")["afsr"]["final"] for s in range(3)]
    _states("vision-mtj-long-means", _mean_se(long_), _signed(list(np.array(long_) - np.array(sr))))


# --- the normalization default measured: --stream.stats=seen against union on needle_cpu_m16 ----------------------

def test_the_seen_against_union_table_and_its_tests_recompute(readme):
    """Each row of the seen-vs-union table against its two runs, the means, the paired differences and the
    exploratory tests' p values as RESULTS quotes them, and the union re-run's agreement with the archived run."""
    seen, union = DOCS / "results" / "needle_cpu_m16_stats_seen", DOCS / "results" / "needle_cpu_m16_compare"
    rows = _table_rows("stats-seen-table")
    assert [(c[0], int(c[1])) for c in rows] == [(v, s) for v in ("sr", "wake_only") for s in (0, 1, 2)]
    for cells in rows:
        run = f"{cells[0]}_seed{cells[1]}"
        u, n = (json.loads((a / run / "results.json").read_text()) for a in (union, seen))
        assert json.loads((seen / run / "train_config.json").read_text())["stream"]["stats"] == "seen"
        assert json.loads((union / run / "train_config.json").read_text())["stream"]["stats"] == "union"
        assert cells[2:6] == [f"{u['metrics']['afsr']['final']:.3f}", f"{n['metrics']['afsr']['final']:.3f}",
                              f"{u['metrics']['bwt']['final']:+.3f}", f"{n['metrics']['bwt']['final']:+.3f}"], cells
        assert cells[6] == " / ".join(f"{x:.2f}" for x in n["success_matrix"][-1])
        assert cells[7] == " / ".join(f"{x:.2f}" for x in n["success_after_own_wake"])
    assert sorted(archived_values(seen, "sr", "afsr")) == [0, 1, 2]
    tests = [f"{seen}::sr!={union}::sr", f"{seen}::wake_only!={union}::wake_only", "sr>wake_only"]
    sr, wake, sleep = run_tests(HypothesesConfig(archive=seen, tests=tests))
    _states("stats-seen-reading", _mean_se(sr["a_values"]), _mean_se(sr["b_values"]),
            _signed(list(np.subtract(sr["a_values"], sr["b_values"]))), f"p = {sr['p']:.3f}",
            f"p = {sr['sign_flip_p']:.2f}", _mean_se(wake["a_values"]), _mean_se(wake["b_values"]),
            f"{wake['mean']:+.3f} +- {wake['sem']:.3f}", f"p = {wake['p']:.3f}", f"p = {wake['sign_flip_p']:.2f}",
            f"{sleep['mean']:+.3f} +- {sleep['sem']:.3f}", f"p = {sleep['p']:.3f}", f"p = {sleep['sign_flip_p']:.3f}")
    assert all(a < b for t in (sr, wake) for a, b in zip(t["a_values"], t["b_values"], strict=True))  # every pair
    stored = json.loads((seen / "hypotheses" / "hypotheses.json").read_text())["tests"]
    assert [t["p"] for t in stored] == pytest.approx([sr["p"], wake["p"], sleep["p"]])
    assert f"SR {np.mean(sr['a_values']):.3f} against {np.mean(sr['b_values']):.3f} and wake-only " \
           f"{np.mean(wake['a_values']):.3f} against {np.mean(wake['b_values']):.3f}, lower on every seed" in readme
    assert f"sleep still helps under it ({sleep['mean']:+.3f} over wake-only)" in readme
    scale = read_checked_json(seen / "input_scale.json")["runs"]  # the state input weights, measured on checkpoints
    wakes = {run: [r for r in rows if r["phase"] == "wake"] for run, rows in scale.items()}
    seen_runs = [w for run, w in wakes.items() if "m16_seen" in run]
    (union_run,) = [w for run, w in wakes.items() if "m16_union_check" in run]
    assert len(seen_runs) == 6 and all(len(w) == 5 for w in wakes.values())
    last = [w[-1]["max"] for w in seen_runs]
    medians = [w[-1]["median"] for w in seen_runs]
    first = [w[0]["max"] for w in wakes.values()]
    _states("stats-seen-input-scale", f"{min(last):.0f}-{max(last):.0f}", "35",
            f"{min(medians):.1f}-{max(medians):.1f}", f"{union_run[-1]['max']:.2f}", f"{union_run[-1]['median']:.2f}",
            f"{min(first):.2f}-{max(first):.2f}")
    rerun = json.loads((seen / "union_rerun_sr_seed0" / "results.json").read_text())
    archived = json.loads((union / "sr_seed0" / "results.json").read_text())
    assert rerun["success_matrix"] == archived["success_matrix"] and rerun["code"]["commit"].startswith("f3e38eb")


def test_the_reexpress_inputs_check_recomputes(readme):
    """The exploratory check (seen with --stream.reexpress_inputs=false): its runs' settings, what their wakes
    learned, and the means, paired differences and p values RESULTS quotes, recomputed from the three archives."""
    results = DOCS / "results"
    actions, seen = results / "needle_cpu_m16_stats_seen_actions", results / "needle_cpu_m16_stats_seen"
    runs = {(v, s): json.loads((actions / f"{v}_seed{s}" / "results.json").read_text())
            for v in ("sr", "wake_only") for s in (0, 1, 2)}
    for v, s in runs:
        stream = json.loads((actions / f"{v}_seed{s}" / "train_config.json").read_text())["stream"]
        assert stream["stats"] == "seen" and stream["reexpress_inputs"] is False
    own = [x for r in runs.values() for x in r["success_after_own_wake"]]
    _states("stats-reexpress-check", f">= {min(own):.2f}")
    assert all(r["success_after_own_wake"][3] == 1.0 for r in runs.values())  # regrasp 1.00 in all six
    sr, wake = run_tests(HypothesesConfig(archive=actions, tests=[f"{actions}::sr!={seen}::sr",
                                                                  f"{actions}::wake_only!={seen}::wake_only"]))
    bwt = {v: [runs[(v, s)]["metrics"]["bwt"]["final"] for s in (0, 1, 2)] for v in ("sr", "wake_only")}
    _states("stats-reexpress-check", _mean_se(sr["a_values"]), f"{np.mean(sr['b_values']):.3f}",
            f"{sr['mean']:+.3f} +- {sr['sem']:.3f}", f"p = {sr['p']:.3f}", f"p = {sr['sign_flip_p']:.2f}",
            _mean_se(wake["a_values"]), f"{np.mean(wake['b_values']):.3f}", f"{wake['mean']:+.3f} +- {wake['sem']:.3f}",
            f"p = {wake['p']:.3f}", f"p = {wake['sign_flip_p']:.2f}", _signed(bwt["sr"]), _signed(bwt["wake_only"]))
    assert f"(SR {np.mean(sr['a_values']):.3f}, wake-only {np.mean(wake['a_values']):.3f})" in readme


# --- provenance: the protocol's runs were made by code that already held the protocol --------------------------------

PROTOCOL_COMMIT, GATE_COMMIT, TEST_CODE = "67f93d6", "1702742", "c8c03d9"
"""The imitation protocol's commit, the SAC gate statement's, and the code every calibration and test run of the
imitation protocol was recorded to run from (RESULTS)."""
SLEEP_PROTOCOL, SLEEP_CODE, RD_ACT_CODE = "e89c5b1", "5545b02", "268706b"
W_PROTOCOL = "94cdc5a"
"""Protocol W's statement, which also added its variant ``sr_c_b1_pw``: its runs ran from this commit."""
"""Issue 59's protocol commit ("a SAC sleep that keeps what its wakes learn"), the code of its step-B runs and of
its confirmation's runs (RESULTS' 2026-11-29 20:40 and 2026-11-30 10:20 lines), and the code of Reset & Distill's MT5
imitation runs (queue lines rd_mt5_*)."""
RD = "reset_distill_"
"""The run-name prefix of Reset & Distill's runs, which issue 59 added to the imitation protocol's archive."""
V_ACT_CODE, V_ACT = "0ceecc3", "sr_c_seed"
"""The code of V on ACT (``needle_compare``'s variant ``sr_c``, queue lines src_needle_m16_* and src_mt5_*; RESULTS'
2026-11-30 16:25 line) and its runs' name prefix, which issue 59 added to the needle m16 and imitation archives."""


def _flat(d: dict, prefix: str = "") -> dict:
    """A nested config as ``{"a.b": value}`` (an empty section adds nothing)."""
    out = {}
    for key, value in d.items():
        out.update(_flat(value, f"{prefix}{key}.") if isinstance(value, dict) else {prefix + key: value})
    return out


def _git(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["git", "-C", str(DOCS.parent), *args], capture_output=True, text=True, check=False)


@pytest.mark.parametrize("archives, statement, code, only, but", [
    (["metaworld_mt5_imitation_calibration", "metaworld_mt5_imitation_calibration_k1",
      "metaworld_mt5_imitation_calibration_k2", "metaworld_mt5_imitation_calibration_k3",
      "metaworld_mt5_imitation_calibration_k4", "needle_cpu_m16_replication", "metaworld_mt5_imitation_compare"],
     PROTOCOL_COMMIT, TEST_CODE, "", (RD, V_ACT)),
    (["sac_mt5_gate"], GATE_COMMIT, None, "", ()),
    (["sac_sleep_calibration", "sac_sleep_screening", "sac_mt5_gate_avx2"], SLEEP_PROTOCOL, None, "", ()),
    (["sac_sleep_step_b", "sac_mt5_gate_xeon", "sac_gate_cross_cpu"], SLEEP_PROTOCOL, SLEEP_CODE, "", ()),
    (["metaworld_mt5_imitation_compare", "needle_cpu_m16_compare"], SLEEP_PROTOCOL, RD_ACT_CODE, RD, ()),
    (["metaworld_mt5_imitation_compare", "needle_cpu_m16_compare", "needle_cross_cpu"],
     SLEEP_PROTOCOL, V_ACT_CODE, V_ACT, ()),
    (["sac_gate_plain_wake"], W_PROTOCOL, W_PROTOCOL, "", ()),
])
def test_every_protocol_run_came_from_code_that_already_held_its_protocol(archives, statement, code, only, but):
    """A run cannot start before the code it ran from exists: every archived run of a protocol (its results.json
    ``code``) ran from a clean checkout of a commit that descends from the commit stating the protocol, so git shows
    the statement first. The imitation protocol's runs all ran from the one recorded code commit; so did issue 59's
    step-B and confirmation runs, its Reset & Distill runs in the imitation and needle m16 archives, and V on ACT's
    runs there (the runs checked: those whose names start with ``only`` and with none of ``but``)."""
    if _git("rev-parse", "--is-shallow-repository").stdout.strip() != "false":
        pytest.skip("needs the repository's history (a shallow clone has none)")
    runs = [run for name in archives if (DOCS / "results" / name).is_dir()
            for run in sorted((DOCS / "results" / name).glob("*_seed*")) if (run / "results.json").is_file()
            and run.name.startswith(only) and not run.name.startswith(but)]
    if statement == SLEEP_PROTOCOL and code != V_ACT_CODE:
        assert runs  # the calibration, step-B and Reset & Distill runs are there to check
    if statement == PROTOCOL_COMMIT:
        assert len(runs) >= 46  # calibration (36 runs over five steps) and N1 (10): the runs are there to check
    commits = {}
    for run in runs:
        recorded = json.loads((run / "results.json").read_text())["code"]
        assert recorded["dirty"] is False, run
        commits.setdefault(recorded["commit"], []).append(run.name)
    for commit in commits:
        assert _git("merge-base", "--is-ancestor", statement, commit).returncode == 0, (commit, commits[commit])
        if code is not None:
            assert commit.startswith(_git("rev-parse", code).stdout.strip()), (commit, commits[commit])


PREREGISTERED = {("metaworld_mt5_imitation_compare", "hypotheses"), ("needle_cpu_m16_replication", "hypotheses"),
                 ("sac_mt5_gate", "hypotheses"), ("sac_mt5_gate_xeon", "hypotheses_sleep"),
                 ("stream_orders", "hypotheses")}
"""The archives (and folders) whose tests were stated before any run of their preset: M1 and M2, N1 (the imitation
protocol), G1 (the SAC gate), V1 and V2 (issue 59's confirmation, RESULTS' 10:20 line), O1-O3 (the stream orders)."""


def test_only_tests_stated_before_any_run_are_labelled_pre_registered_in_an_archive():
    """The protocol's rule, on every archived ``hypotheses.md``: headed "Pre-registered" only in an archive whose tests
    a protocol declared before any run of its preset (and only the declared ones: no ``hypotheses_exploratory/``);
    every other one "Exploratory (not pre-registered)" (the m16 H1/H2 and vision H4 files were headed "Pre-registered"
    until 2026-11-28)."""
    found = sorted(DOCS.glob("results/**/hypotheses*/hypotheses.md"))
    assert len(found) >= 7
    for md in found:
        head = md.read_text().splitlines()[0]
        if head.startswith("Pre-registered"):
            assert (md.parents[1].name, md.parent.name) in PREREGISTERED, md
        else:
            assert head.startswith("Exploratory (not pre-registered)"), md
    for name in ("needle_cpu_m16_compare", "needle_cpu_vision_compare"):
        text = (DOCS / "results" / name / "hypotheses" / "hypotheses.md").read_text()
        assert text.startswith("Exploratory") and "Labelled exploratory (corrected 2026-11-28" in text, name


def test_every_mt5_test_run_ran_the_recorded_test_preset():
    """Each archived test run of the MT5 imitation stream is ``configs/metaworld_mt5_imitation.json`` with exactly
    the ``--extra`` flags of RESULTS' dated test-preset line (08:49 UTC), on a training seed 0-9 (calibration seeds
    never enter a test); ``configs/metaworld_mt5_imitation_test.json`` is that preset as a file of its own."""
    line = _by_id("mt5-test-preset")
    assert line.startswith("--extra=[") and line.endswith("]")
    flags = dict(f.removeprefix("--").split("=", 1) for f in line[len("--extra=["):-1].split(","))
    assert flags["memory.buffer_size"] == "8" and flags["policy.dim_model"] == "256"

    preset = _flat(json.loads((DOCS.parent / "configs" / "metaworld_mt5_imitation.json").read_text()))
    expected = {k: v for k, v in preset.items() if k not in ("output_dir", "seed", "method")}
    expected.update({k: type(preset[k])(v) if k in preset else v for k, v in flags.items()})
    test_preset = _flat(json.loads((DOCS.parent / "configs" / "metaworld_mt5_imitation_test.json").read_text()))
    assert {k: v for k, v in test_preset.items() if k not in ("output_dir", "seed", "method")} == expected
    from sr_imitation.experiments.needle_compare import VARIANTS as NEEDLE_VARIANTS

    runs = sorted((DOCS / "results" / "metaworld_mt5_imitation_compare").glob("*_seed*"))
    for run in runs:
        config = _flat(json.loads((run / "train_config.json").read_text()))
        variant = NEEDLE_VARIANTS[run.name.rsplit("_seed", 1)[0]]  # what the variant itself changes
        own = {"method": variant.method, **{f"sleep.{k}": v for k, v in variant.sleep.items()},
               **{f"policy.{k}": v for k, v in variant.policy.items()},
               **{f"method_options.{k}": v for k, v in variant.options.items()}}
        assert {k: config.get(k) for k in expected | own} == expected | own, run.name
        assert 0 <= config["seed"] <= 9 and run.name.endswith(f"_seed{config['seed']}"), run.name


def test_every_mt5_run_after_step_k1_read_the_same_demonstrations():
    """The 100-demonstration datasets are recorded once per machine (RESULTS' K1 line): every archived run from K1 on,
    calibration and test, read datasets with the same content digests (its settings_fingerprint.json), so a session
    that had to record them again (another machine, another CPU type) cannot add runs on other demonstrations
    unnoticed; step 0's 50-demonstration runs read other ones."""
    digests: dict[tuple, list[str]] = {}
    for name in ("calibration", "calibration_k1", "calibration_k2", "calibration_k3", "calibration_k4", "compare"):
        for run in sorted((DOCS / "results" / f"metaworld_mt5_imitation_{name}").glob("*_seed*")):
            settings = json.loads((run / "settings_fingerprint.json").read_text())["settings"]
            key = tuple(sorted((k, v) for k, v in settings.items() if k.startswith("inputs.datasets.")))
            assert len(key) == 5, run
            digests.setdefault(key, []).append(f"{name}/{run.name}")
    assert len(digests) == 2, {k: len(v) for k, v in digests.items()}
    step0, rest = sorted(digests.values(), key=lambda runs: not runs[0].startswith("calibration/"))
    assert all(r.startswith("calibration/") for r in step0) and not any(r.startswith("calibration/") for r in rest)
    assert sum(r.startswith("compare/") for r in rest) >= 27


# --- the needle replication N1 (seeds 5-9; the protocol's third test) -------------------------------------------------

def test_the_needle_replication_n1_recomputes():
    """N1's table, test and descriptive numbers against its ten archived runs; its runs' settings equal seeds 0-4's
    but for the seed (and settings added since, at the values of the earlier behaviour); the stored test equals a
    recompute, and a test over seeds 5-9 cannot run on fewer."""
    replication = DOCS / "results" / "needle_cpu_m16_replication"
    rows = _table_rows("n1-table")
    runs = {(v, s): json.loads((replication / f"{v}_seed{s}" / "results.json").read_text())
            for v in ("sr", "wake_only") for s in range(5, 10)}
    assert [int(c[0]) for c in rows] == [5, 6, 7, 8, 9]
    for seed, sr, wake, diff in rows:
        a, b = (runs[(v, int(seed))]["metrics"]["afsr"]["final"] for v in ("sr", "wake_only"))
        assert [sr, wake, diff] == [f"{a:.3f}", f"{b:.3f}", f"{a - b:+.3f}"], seed
    added = {"eval.env": "needle", "allow_unhashed_inputs": False, "torch_threads": 1}

    def settings(run: Path) -> dict:
        return {k: v for k, v in _flat(json.loads((run / "train_config.json").read_text())).items()
                if k not in ("seed", "output_dir")}

    for v in ("sr", "wake_only"):
        new, old = settings(replication / f"{v}_seed5"), settings(ARCHIVE / f"{v}_seed0")
        differ = {k for k in new.keys() | old.keys() if new.get(k) != old.get(k) and k not in ("seed", "output_dir")}
        assert differ <= set(added) and all(new[k] == added[k] and k not in old for k in differ), (v, differ)
    (n1,) = run_tests(HypothesesConfig(archive=replication, tests=["N1=sr>wake_only@5-9"]))
    _states("n1-test", _mean_se(n1["a_values"]), _mean_se(n1["b_values"]), f"{n1['mean']:+.3f} +- {n1['sem']:.3f}",
            f"t = {n1['t']:.2f}", f"p = {n1['p']:.3f}", f"p = {n1['sign_flip_p']:.3f}",
            f"[{n1['ci_low']:+.3f}, {n1['ci_high']:+.3f}]")
    assert min(np.subtract(n1["a_values"], n1["b_values"])) > 0  # "every pair positive"
    stored = json.loads((replication / "hypotheses" / "hypotheses.json").read_text())["tests"]
    assert [(t["name"], t["seeds"], t["p"], t["sign_flip_p"]) for t in stored] == \
        [("N1", [5, 6, 7, 8, 9], n1["p"], n1["sign_flip_p"])]
    old = run_tests(HypothesesConfig(archive=ARCHIVE, tests=["sr>wake_only"]))[0]
    bwt = {v: [runs[(v, s)]["metrics"]["bwt"]["final"] for s in range(5, 10)] for v in ("sr", "wake_only")}
    final = {v: np.mean([runs[(v, s)]["success_matrix"][-1] for s in range(5, 10)], axis=0)
             for v in ("sr", "wake_only")}
    own = {(v, s): r["success_after_own_wake"] for (v, s), r in runs.items()}
    below = sorted((s, x[2]) for (v, s), x in own.items() if min(x) < 1)
    assert all(v == "wake_only" and min(x) == x[2] for (v, s), x in own.items() if min(x) < 1)
    assert [s for s, _ in below] == [7, 9]
    _states("n1-test", f"{old['mean']:+.3f} +- {old['sem']:.3f}", f"{np.mean(old['a_values']):.3f}",
            f"{np.mean(old['b_values']):.3f}", "7", "9", f"{below[0][1]:.2f}", f"{below[1][1]:.2f}",
            _signed(bwt["sr"]), _signed(bwt["wake_only"]), f"{final['sr'][0]:.2f}", f"{final['wake_only'][0]:.2f}",
            f"{final['sr'][2]:.2f}", f"{final['wake_only'][2]:.2f}")
    with pytest.raises(ValueError, match="no finished run yet"):
        run_tests(HypothesesConfig(archive=replication, tests=["sr>wake_only@5-10"]))
    for ident in ("ev-needle-m16", "n1-summary"):  # the evidence page's "Does sleep help?" and the earlier summary
        _states(ident, f"{np.mean(n1['a_values']):.3f}", f"{np.mean(n1['b_values']):.3f}",
                f"{n1['mean']:+.3f} +- {n1['sem']:.3f}", f"p = {n1['p']:.3f}", f"{n1['sign_flip_p']:.3f}")


# --- the MT5 imitation stream's tests M1 and M2, and the family's Holm verdict ---------------------------------------

MT5_COMPARE = DOCS / "results" / "metaworld_mt5_imitation_compare"
FAMILY = ["M1=sr>wake_only@0-9", "M2=sr!=replay@0-9",
          f"N1={DOCS / 'results' / 'needle_cpu_m16_replication'}::sr>wake_only@5-9"]
"""The protocol's test family, exactly as its commit declares it (RESULTS, 09:19 note: the command)."""
MT5_SKILLS = ["reach", "door-open", "drawer-open", "window-close", "button-press"]
"""The stream's skills in its order, as RESULTS names them."""


def _mt5_runs(variants: tuple[str, ...], seeds: range = range(10)) -> dict[tuple[str, int], dict]:
    """The archived MT5 imitation runs' ``results.json``, by (variant, training seed)."""
    return {(v, s): json.loads((MT5_COMPARE / f"{v}_seed{s}" / "results.json").read_text())
            for v in variants for s in seeds}


def _finals(runs: dict[tuple[str, int], dict], variant: str, metric: str, seeds: range) -> list[float]:
    """``variant``'s final ``metric`` on each of ``seeds``, from :func:`_mt5_runs`' runs."""
    return [runs[(variant, s)]["metrics"][metric]["final"] for s in seeds]


def _after_next_wake(runs: dict[tuple[str, int], dict], variant: str, seeds: range) -> list[float]:
    """Each earlier skill's success right after the next wake (skills 1-4), over ``seeds``."""
    return [runs[(variant, s)]["success_matrix"][i + 1][i] for s in seeds for i in range(4)]


def _gate_run(run: Path, seed: int, overrides: dict[str, Any]) -> dict:
    """An archived run of ``configs/sac_mt5_gate.json`` checked to have run that preset with only its seed and
    ``overrides`` changed, from the gate's code, clean; its ``results.json``."""
    preset = _flat(json.loads((DOCS.parent / "configs" / "sac_mt5_gate.json").read_text()))
    config = _flat(json.loads((run / "train_config.json").read_text()))
    expected = preset | overrides | {"seed": seed, "output_dir": "."}
    assert {k: config.get(k) for k in expected} == expected, run.name
    results = json.loads((run / "results.json").read_text())
    assert results["code"]["commit"].startswith("09fcd3e") and results["code"]["dirty"] is False, run.name
    return results


def test_the_sac_gate_s_result_recomputes():
    """The SAC gate's table, verdict and AFSRs (RESULTS, dated below its statement) from its two archived MT-Joint
    runs: each ran ``configs/sac_mt5_gate.json`` exactly (its seed aside; the oracle's actor is plain, no
    excitability, as the statement says), from the gate's code; each skill's final success per seed and averaged over
    seeds 0-1; the gate passes only if every average is >= 0.8, and RESULTS says what the numbers say."""
    gate = DOCS / "results" / "sac_mt5_gate"
    runs = [_gate_run(gate / f"mt_joint_seed{seed}", seed, {"excitability.enabled": False}) for seed in (0, 1)]
    finals = np.array([r["success_matrix"][-1] for r in runs])
    means = finals.mean(axis=0)
    rows = _table_rows("gate-table")
    assert [r[0] for r in rows] == runs[0]["skills"]
    for i, (_, a, b, mean, ok) in enumerate(rows):
        assert (a, b, mean) == (f"{finals[0, i]:.2f}", f"{finals[1, i]:.2f}", f"{means[i]:.2f}")
        assert ok == ("yes" if means[i] >= 0.8 else "no")
    passed = bool((means >= 0.8).all())
    _states("gate-result", "**the gate passes.**" if passed else "**the gate fails.**")
    afsr = [r["metrics"]["afsr"]["final"] for r in runs]
    _states("gate-afsr", f"{afsr[0]:.3f}", f"{afsr[1]:.3f}", f"{np.mean(afsr):.3f}")
    _states("ev-sac-gate", "**passes**" if passed else "**fails**", " / ".join(f"{m:.2f}" for m in means),
            f"{np.mean(afsr):.3f}")


SAC_FOLLOW_UP = ("sr", "wake_only", "reset_distill")
"""The SAC gate's follow-up variants (RESULTS, the gate's statement)."""


def _variant_settings(variant: str) -> dict[str, Any]:
    """The settings ``mt5_compare.VARIANTS[variant]`` changes, as ``sr-train`` parses them on the gate's preset."""
    flags = MT5_VARIANTS[variant]
    parsed = _flat(parse_sac_config([f"--config_path={DOCS.parent / 'configs' / 'sac_mt5_gate.json'}",
                                     *flags]).stored_config())
    return {key: parsed[key] for key in (flag.removeprefix("--").split("=", 1)[0] for flag in flags)}


def test_the_sac_follow_up_rows_so_far_recompute():
    """The SAC gate's follow-up table (RESULTS, below the gate's result) has one row per archived SR, wake-only and
    Reset & Distill run, each recomputed from its raw files (compute minutes: ``phase_seconds``, which counts a wake
    resumed from its snapshot from its start); every such run ran ``configs/sac_mt5_gate.json`` with
    only its seed and its variant's flags (``mt5_compare.VARIANTS``) changed, from the gate's code, clean."""
    gate = DOCS / "results" / "sac_mt5_gate"
    archived = sorted((v, int(p.name.rsplit("_seed", 1)[1])) for v in SAC_FOLLOW_UP for p in gate.glob(f"{v}_seed*"))
    rows = _table_rows("gate-follow-up")
    assert sorted((v, int(s)) for v, s, *_ in rows) == archived
    final_afsr = {}
    for variant, seed, finals, own, afsr, bwt, minutes in rows:
        run = gate / f"{variant}_seed{seed}"
        r = _gate_run(run, int(seed), _variant_settings(variant))
        assert finals == " / ".join(f"{x:.2f}" for x in r["success_matrix"][-1]), run.name
        assert own == " / ".join(f"{x:.2f}" for x in r["success_after_own_wake"]), run.name
        m = r["metrics"]
        assert afsr == f"{m['afsr']['final']:.3f}", run.name
        assert bwt == f"{m['bwt']['final']:+.3f} / {m['bwt_wake']['final']:+.3f}", run.name
        assert minutes == f"{phase_seconds(run) / 60:.0f}", run.name
        final_afsr[(variant, int(seed))] = m["afsr"]["final"]
    pairs = {s: (final_afsr[("sr", s)], final_afsr[("wake_only", s)]) for v, s in final_afsr if v == "sr"
             and ("wake_only", s) in final_afsr}
    assert sorted(pairs) == list(range(5))  # all five pairs are in (each dated entry gives its pair)
    for s, (a, b) in pairs.items():
        _states(f"gate-pair-{s}", f"{a - b:+.3f}")
    distill = sorted(s for v, s in final_afsr if v == "reset_distill")
    assert distill == list(range(5))  # the evidence page and RESULTS give its mean beside SR's and wake-only's
    rd, sr, wake = ([final_afsr[(v, s)] for s in distill] for v in ("reset_distill", "sr", "wake_only"))
    diff = np.subtract(rd, sr)
    for ident in ("ev-sac-rd", "gate-rd-summary", "gate-rd"):  # the evidence, the headline, the dated closing entry
        _states(ident, "Reset & Distill (descriptive, seeds 0-4)", _mean_se(rd), _mean_se(sr), _mean_se(wake),
                _signed(diff), " / ".join(f"{d:+.3f}" for d in diff))


G1 = "G1=sr>wake_only@0-4"
"""The SAC gate's one pre-registered test, exactly as its statement declares it (RESULTS, commit 1702742)."""


def test_g1_the_sac_gate_s_test_recomputes():
    """G1 (SR > wake-only, final AFSR, one-sided, SAC gate preset, training seeds 0-4, a family of one): RESULTS'
    sentence, the headline's and README's short form against a recompute from the archived runs; the stored
    hypotheses equal it and are labelled pre-registered (its text is in commit 1702742, before any run of the
    preset)."""
    gate = DOCS / "results" / "sac_mt5_gate"
    (g1,) = run_tests(HypothesesConfig(archive=gate, tests=[G1]))
    assert g1["seeds"] == [0, 1, 2, 3, 4]
    pairs = " / ".join(f"{d:+.3f}" for d in np.subtract(g1["a_values"], g1["b_values"]))
    _states("g1-test", "G1", _mean_se(g1["a_values"]), _mean_se(g1["b_values"]),
            f"{g1['mean']:+.3f} +- {g1['sem']:.3f}", pairs, f"t = {g1['t']:.2f}", f"p = {g1['p']:.1e}",
            f"p = {g1['sign_flip_p']:.4f}",
            f"[{g1['ci_low']:+.3f}, {g1['ci_high']:+.3f}]")
    stored = json.loads((gate / "hypotheses" / "hypotheses.json").read_text())["tests"]
    assert [(t["name"], t["seeds"], t["p"], t["sign_flip_p"], t["mean"]) for t in stored] == \
        [("G1", [0, 1, 2, 3, 4], g1["p"], g1["sign_flip_p"], g1["mean"])]
    assert (gate / "hypotheses" / "hypotheses.md").read_text().startswith("Pre-registered")
    for ident in ("ev-sac-gate", "g1-summary"):  # the evidence page's SAC bullet and the earlier summary
        _states(ident, f"{np.mean(g1['a_values']):.3f}", f"{np.mean(g1['b_values']):.3f}",
                f"{g1['mean']:+.3f} +- {g1['sem']:.3f}", f"p = {g1['p']:.1e}", f"{g1['sign_flip_p']:.3f}")


SLEEP_FAMILY = DOCS / "results" / "sac_mt5_gate_xeon"
"""Issue 59's confirmation: the archive its family is computed in (RESULTS' record, 2026-11-30 10:20 UTC: the Intel Xeon
family 6 model 167 with the libraries capped at AVX2, the type of all fifteen of its runs)."""


def _sleep_family() -> tuple[str, list[dict]]:
    """Rule B's V and the family recomputed from the archived runs, as the protocol declares it (skips the calling
    test until the family has been computed and stored)."""
    if not (SLEEP_FAMILY / "hypotheses_sleep" / "hypotheses.json").is_file():
        pytest.skip("the family is computed only when V's five test-seed runs are archived")
    v = read_checked_json(DOCS / "results" / "sac_sleep_step_b" / "step_b.json")["rule_b"]["variant"]
    assert v is not None, "a family without a V: rule B chose none, so no confirmatory run may exist"
    return v, run_tests(HypothesesConfig(archive=SLEEP_FAMILY, holm=True,
                                         tests=[f"V1={v}>sr@0-4", f"V2={v}!=reset_distill@0-4"]))


def test_the_sleep_family_recomputes():
    """Issue 59's confirmatory family as its protocol declares it (RESULTS, "a SAC sleep that keeps what its wakes
    learn"): V1 = V > SR (one-sided), V2 = V != Reset & Distill (two-sided), paired over training seeds 0-4, Holm over
    exactly these two, V being rule B's choice (step_b.json). Once archived, the stored statistics equal a recompute
    from the archived runs, are labelled pre-registered and have their figure (skipped before)."""
    stored_path = SLEEP_FAMILY / "hypotheses_sleep" / "hypotheses.json"
    v, family = _sleep_family()
    assert [(r["name"], r["a"], r["b"], r["alternative"], r["seeds"]) for r in family] == \
        [("V1", v, "sr", "greater", [0, 1, 2, 3, 4]), ("V2", v, "reset_distill", "two-sided", [0, 1, 2, 3, 4])]
    keys = ("name", "a", "b", "alternative", "seeds", "a_values", "b_values", "mean", "sem", "t", "p", "sign_flip_p",
            "p_holm", "sign_flip_p_holm", "significant_holm")
    stored = json.loads(stored_path.read_text())["tests"]
    assert [[t[k] for k in keys] for t in stored] == [[r[k] for k in keys] for r in family]
    assert (SLEEP_FAMILY / "hypotheses_sleep" / "hypotheses.md").read_text().startswith("Pre-registered")
    assert (SLEEP_FAMILY / "hypotheses_sleep" / "hypotheses.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def _family_numbers(row: dict, names: dict[str, str]) -> list[str]:
    """RESULTS' entry for one test of issue 59's family, as its numbers (and names and verdict) in their order, every
    number from its recomputed row."""
    pairs = " / ".join(f"{d:+.3f}" for d in np.subtract(row["a_values"], row["b_values"]))
    sided = "one-sided" if row["alternative"] == "greater" else "two-sided"
    verdict = "**rejected its null**" if row["significant_holm"] else "**not rejected**"
    return [f"{row['name']}:", f"{names[row['a']]} {_mean_se(row['a_values'])}",
            f"{names[row['b']]} {_mean_se(row['b_values'])}", f"{row['mean']:+.3f} +- {row['sem']:.3f}", pairs,
            f"t = {row['t']:.2f}", f"{sided} p = {row['p']:.4f}", f"p = {row['sign_flip_p']:.4f}",
            f"p = {row['p_holm']:.4f}", f"{row['sign_flip_p_holm']:.4f}",
            f"[{row['ci_low']:+.3f}, {row['ci_high']:+.3f}]", verdict]


def test_the_sleep_family_sentences_recompute():
    """RESULTS' family entry and README's SAC row state each test of the family exactly as recomputed from the
    archived runs (skipped until the family is computed): the means, the pairs, t, the decision p and the exact
    sign-flip p, both Holm-adjusted, the CI, and the verdict in the test's own words."""
    _, family = _sleep_family()
    for row in family:
        _states(f"family-{row['name'].lower()}", *_family_numbers(row, NAMES))
        short = (f"{row['name']} {'rejected' if row['significant_holm'] else 'not rejected'} "
                 f"(Holm-adjusted p = {row['p_holm']:.4f}; {row['p']:.3f} alone)")
        assert short in _which_method_rows()["configs/sac_mt5_gate.json"], short


CROSS_CPU = DOCS / "results" / "sac_gate_cross_cpu"
"""The agreement checks between CPU types (RESULTS' 2026-11-30 07:30 and 2026-12-01 22:49 lines)."""


def _cpu_type(run: Path) -> str:
    """``<family>/<model>`` of the CPU a run's results.json recorded (Intel or AMD)."""
    m = re.search(r"family (\d+), model (\d+);", read_checked_json(run / "results.json")["machine"]["cpu"])
    return f"{m[1]}/{m[2]}"


def _cpu_models(runs) -> dict[str, str]:
    """Each run's Intel (family 6) CPU model number, as its results.json recorded the machine."""
    types = {run.name: _cpu_type(run) for run in sorted(runs) if (run / "results.json").is_file()}
    assert all(t.startswith("6/") for t in types.values()), types
    return {name: t.split("/")[1] for name, t in types.items()}


def _equal_everywhere(run_a: Path, run_b: Path, at_least: int, compare_output: Path) -> None:
    """Two whole runs agree in every measured value (none on one side only), recomputed, and the archived output of
    the comparison says so."""
    from sr_imitation.reporting.compare import compare_runs

    report = compare_runs(run_a, run_b)
    assert report["compared"] >= at_least, report["compared"]
    assert not (report["differences"] or report["only_a"] or report["only_b"]), report["differences"][:3]
    assert "the runs agree; every number equal" in compare_output.read_text()


def test_the_sleep_family_is_of_one_cpu_type():
    """The family is computed over one CPU type only. Its runs were made on the Intel Xeon family 6 model 167; a run
    made on model 207 joins it only because a whole run of the family made there (``sr_c_b1`` seed 1, all five
    stages) equals its model 167 archive in every measured value (RESULTS' 2026-12-01 22:49 rule), and that
    comparison is archived and re-checked here."""
    models = _cpu_models(SLEEP_FAMILY.iterdir())
    assert set(models.values()) <= {"167", "207"}, models
    if "207" in models.values():
        assert models["sr_c_b1_seed1"] == "167" and _cpu_models([CROSS_CPU / "sr_c_b1_seed1_m207"]) == {
            "sr_c_b1_seed1_m207": "207"}
        _equal_everywhere(SLEEP_FAMILY / "sr_c_b1_seed1", CROSS_CPU / "sr_c_b1_seed1_m207", 2000,
                          CROSS_CPU / "compare_sr_c_b1_seed1_m207.txt")


def test_the_c_b1_wake_observation_recomputes():
    """RESULTS' twentieth-session observation behind protocol W: ``sr_c_b1`` and ``reset_distill`` differ in their
    settings by ``excitability.enabled`` and the method's own settings only, all 25 wake agents' checksums differ,
    and the drawer-open and reach numbers it quotes, from the family's archive."""
    own = {}
    for variant in ("reset_distill", "sr_c_b1", "sr"):
        runs = [read_checked_json(SLEEP_FAMILY / f"{variant}_seed{s}" / "results.json") for s in range(5)]
        own[variant] = [r["success_after_own_wake"] for r in runs]
    for seed in range(5):
        rd, c_b1 = (SLEEP_FAMILY / f"{v}_seed{seed}" for v in ("reset_distill", "sr_c_b1"))
        a, b = (read_fingerprint(run / FINGERPRINT_FILE) for run in (rd, c_b1))
        differ = {k for k in set(a) | set(b) if a.get(k) != b.get(k)}
        assert differ - {"method"} - {k for k in differ if k.startswith("method_")} == {"excitability.enabled"}
        wakes = same_files(rd, c_b1, ["stages/*/wake/agent.safetensors"])
        assert list(wakes.values()) == ["differs"] * 5, wakes
    reach, drawer = 0, 2  # MT5's order
    calibration = [read_checked_json(DOCS / "results" / "sac_sleep_step_b" / f"sr_c_b1_seed{s}" / "results.json")
                   for s in (100, 101, 102)]
    assert all(o[drawer] == 0.0 for o in own["sr_c_b1"]) and all(r["success_after_own_wake"][drawer] == 0.0
                                                                  for r in calibration)
    _states("c-b1-wake-observation", "25", f"{own['sr_c_b1'][0][reach]:.2f}", f"{own['reset_distill'][0][reach]:.2f}",
            "0.00", "eight", *(" / ".join(f"{o[drawer]:.2f}" for o in own[v]) for v in ("reset_distill", "sr")))


def test_v_on_act_is_of_one_cpu_type():
    """V on ACT's needle m16 rows (descriptive) may hold runs of model 167 and of model 207 only because seed 0 made
    again on model 207 equals its model 167 archive in every measured value (RESULTS' 2026-12-01 23:56 rule; the
    repeat and the comparison are archived in ``needle_cross_cpu``)."""
    archive, repeat = DOCS / "results" / "needle_cpu_m16_compare", DOCS / "results" / "needle_cross_cpu"
    models = _cpu_models(archive.glob(V_ACT + "*"))
    assert models["sr_c_seed0"] == "167" and set(models.values()) <= {"167", "207"}, models
    assert _cpu_models([repeat / "sr_c_seed0_m207"]) == {"sr_c_seed0_m207": "207"}
    _equal_everywhere(archive / "sr_c_seed0", repeat / "sr_c_seed0_m207", 400, repeat / "compare_sr_c_seed0_m207.txt")


def _v_act(n: int, archive: str = "needle_cpu_m16_compare") -> tuple[list[dict], list[float]]:
    """V on ACT's archived runs of seeds 0..n-1 (needle m16 unless another archive is named) and their final AFSRs."""
    runs = [read_checked_json(DOCS / "results" / archive / f"{V_ACT}{s}" / "results.json") for s in range(n)]
    return runs, [r["metrics"]["afsr"]["final"] for r in runs]


def _over(archives, variant: str, metric: str = "afsr") -> dict[int, float]:
    """``{seed: final metric}`` of ``variant``'s archived runs, merged over several archives (a preset's seeds 0-4 in
    one, its replication's 5-9 in another)."""
    return {s: v for name in archives for s, v in archived_values(DOCS / "results" / name, variant, metric).items()}


def test_the_v_on_act_needle_seeds_5_7_line_recomputes():
    """RESULTS' nineteenth-session line on V on ACT's needle m16 seeds 5-7 (descriptive): each final AFSR, the
    running list of seeds 0-7 with its mean +- SE, and regrasp's own-wake and final success, from the archive."""
    runs, values = _v_act(8)
    regrasp = [(r["success_after_own_wake"][r["skills"].index("regrasp")],
                r["success_matrix"][-1][r["skills"].index("regrasp")]) for r in runs[5:]]
    assert all(own >= 0.965 for own, _ in regrasp)
    _states("v-act-needle-5-7", *(f"**{values[seed]:.3f}**" for seed in (5, 6, 7)),
            ", ".join(f"{v:.3f}" for v in values), _mean_se(values), *(f"{end:.2f}" for _, end in regrasp))


def test_the_v_on_act_needle_seed_8_line_recomputes():
    """RESULTS' nineteenth-session line on V on ACT's needle m16 seed 8 (descriptive): its final AFSR, BWT against
    both references, and the mean +- SE of seeds 0-8, from the archive."""
    runs, values = _v_act(9)
    metrics = runs[8]["metrics"]
    _states("v-act-needle-8", f"**{values[8]:.3f}**", f"{metrics['bwt']['final']:.3f}",
            f"{metrics['bwt_wake']['final']:.3f}", _mean_se(values))


def test_the_v_on_act_needle_seed_9_line_recomputes():
    """RESULTS' 04:35 line on V on ACT's needle m16 seed 9 (descriptive): its final AFSR, BWT against both
    references, its final row, and seeds 0-9's mean +- SE beside the archived SR's and Reset & Distill on ACT's."""
    runs, values = _v_act(10)
    metrics = runs[9]["metrics"]
    final = " / ".join(f"{v:.2f}" for v in runs[9]["success_matrix"][-1])
    archive, sr_archives = RD_ON_ACT["configs/needle_cpu_m16.json"]
    sr = _over(sr_archives, "sr")
    rd = archived_values(DOCS / "results" / archive, "reset_distill", "afsr")
    assert sorted(sr) == sorted(rd) == list(range(10))
    _states("v-act-needle-9", f"**{values[9]:.3f}**",
            f"{metrics['bwt']['final']:.3f} / {metrics['bwt_wake']['final']:.3f}", final, _mean_se(values),
            f"SR {np.mean(list(sr.values())):.3f}",
            f"Reset & Distill on ACT {np.mean(list(rd.values())):.3f}")


MT5_IMITATION = DOCS / "results" / "metaworld_mt5_imitation_compare"
MT5_ROWS = (("sr", "SR"), ("replay", "replay"), ("wake_only", "wake-only"), ("reset_distill", "Reset & Distill on ACT"))
"""The archived MT5 imitation rows V on ACT's dated lines sit beside: (variant, the name the lines give it)."""


def _mt5_rows() -> dict[str, dict[int, float]]:
    """Each of ``MT5_ROWS``' archived final AFSRs, ``{variant: {seed: AFSR}}``."""
    return {v: archived_values(MT5_IMITATION, v, "afsr") for v, _ in MT5_ROWS}


def _final_row(run: dict) -> str:
    """A run's success per skill at the end, as the dated lines write it ("1.00 / 0.40 / ...")."""
    return " / ".join(f"{v:.2f}" for v in run["success_matrix"][-1])


def _newest_after_sleep(run: dict) -> list[str]:
    """Skills 2-5's success right after their own stage's sleep (the success matrix's diagonal), as written."""
    return [f"{run['success_matrix'][k][k]:.2f}" for k in range(1, 5)]


def test_the_v_on_act_mt5_seeds_0_1_line_recomputes():
    """RESULTS' twentieth-session line on V on ACT's MT5 imitation seeds 0-1 (descriptive): each final AFSR, BWT
    against both references and final row, the archived rows beside them, the own-wake range and the newest skill
    right after each sleep, from the archive; and the runs were made on model 207."""
    archive = MT5_IMITATION
    runs, _ = _v_act(2, archive.name)
    assert set(_cpu_models(archive / f"{V_ACT}{s}" for s in (0, 1)).values()) == {"207"}
    stated = []
    for seed, r in enumerate(runs):
        m, ends = r["metrics"], _final_row(r)
        bwt = f"{m['bwt']['final']:.3f}" if seed == 0 else f"{m['bwt']['final']:+.3f}"
        stated += [f"**{m['afsr']['final']:.3f}**", bwt.replace("-0.000", "0.000"), f"{m['bwt_wake']['final']:.3f}",
                   ends]
    _states("v-act-mt5-0-1", *stated)
    _states("v-act-mt5-0-1", *(f"{name} {got[0]:.3f} and {got[1]:.3f}"
                               for (_, name), got in zip(MT5_ROWS, _mt5_rows().values(), strict=True)))
    own = [v for r in runs for v in r["success_after_own_wake"]]
    newest = [_newest_after_sleep(r) for r in runs]
    _states("v-act-mt5-0-1", f"{min(own):.2f}-{max(own):.2f}", *newest[0], *newest[1])


def test_the_v_on_act_mt5_seeds_2_3_line_recomputes():
    """RESULTS' twenty-first-session line on V on ACT's MT5 imitation seeds 2-3 (descriptive): the runs were made on the
    AMD EPYC family 25 model 1 (the 07:36 line) and the earlier two on model 207; each final AFSR, BWT against both
    references and final row; the archived rows beside them; the own-wake values; the newest skill right after each
    sleep; seeds 0-3's values and mean +- SE beside SR's and Reset & Distill on ACT's on the same seeds."""
    archive = MT5_IMITATION
    runs, values = _v_act(4, archive.name)
    assert [_cpu_type(archive / f"{V_ACT}{s}") for s in range(4)] == ["6/207", "6/207", "25/1", "25/1"]
    stated = []
    for seed in (2, 3):
        m, ends = runs[seed]["metrics"], _final_row(runs[seed])
        bwt = f"{m['bwt']['final']:.3f}" if seed == 2 else f"{m['bwt']['final']:+.3f}"
        stated += [f"**{values[seed]:.3f}**", bwt, f"{m['bwt_wake']['final']:.3f}", ends]
    _states("v-act-mt5-2-3", *stated)
    others = _mt5_rows()
    _states("v-act-mt5-2-3", *(f"{name} {others[v][2]:.3f} and {others[v][3]:.3f}" for v, name in MT5_ROWS))
    own = [v for r in runs[2:] for v in r["success_after_own_wake"]]
    assert runs[2]["success_after_own_wake"][0] == 0.5
    newest = [_newest_after_sleep(r) for r in runs[2:]]
    _states("v-act-mt5-2-3", f"{min(own[1:]):.2f}-{max(own):.2f}", "0.50", *newest[0], *newest[1],
            ", ".join(f"{v:.3f}" for v in values), _mean_se(values),
            _mean_se([others["sr"][s] for s in range(4)]), _mean_se([others["reset_distill"][s] for s in range(4)]))


def _newest_means(runs: list[dict]) -> tuple[float, float]:
    """Skills 2-5's mean success after their own wake and right after their own stage's sleep, over ``runs``."""
    wake = np.mean([r["success_after_own_wake"][k] for r in runs for k in range(1, 5)])
    after = np.mean([r["success_matrix"][k][k] for r in runs for k in range(1, 5)])
    return wake, after


V_ACT_MT5_PAIRS = {  # the line's id -> (its seeds, their CPU type, how many seeds of 0..last end below SR's and
    # below Reset & Distill on ACT's archived runs, as the line words it)
    "v-act-mt5-4-5": (
        (4, 5), "25/1", {"sr": 6, "reset_distill": 5},
        ("all six", "on five")),
    "v-act-mt5-6-7": (
        (6, 7), "25/17", {"sr": 8, "reset_distill": 6},
        ("all eight", "on six")),
    "v-act-mt5-8-9": (
        (8, 9), "25/17", {"sr": 10, "reset_distill": 6},
        ("all ten", "on six")),
}


@pytest.mark.parametrize("ident", sorted(V_ACT_MT5_PAIRS))
def test_the_v_on_act_mt5_pair_lines_recompute(ident):
    """RESULTS' lines on two of V on ACT's MT5 imitation seeds each (descriptive) against the archive: the runs' CPU
    type (the 07:36 and 10:43 lines), each final AFSR, BWT against both references and final row, the newest skill
    right after each sleep, the own-wake range, the archived rows on those seeds; the running list of seeds 0..last
    with its mean +- SE beside every archived row's on the same seeds, on how many it ended below SR and below Reset &
    Distill on ACT, and the newest skill's mean right after its sleep and after its own wake."""
    seeds, cpu, below, words = V_ACT_MT5_PAIRS[ident]
    archive, n = MT5_IMITATION, seeds[-1] + 1
    runs, values = _v_act(n, archive.name)
    assert [_cpu_type(archive / f"{V_ACT}{s}") for s in seeds] == [cpu, cpu]
    for seed in seeds:
        m, ends = runs[seed]["metrics"], _final_row(runs[seed])
        _states(ident, f"**{values[seed]:.3f}**", f"{m['bwt']['final']:+.3f} / {m['bwt_wake']['final']:.3f}", ends)
        _states(ident, f"seed {seed} {', '.join(_newest_after_sleep(runs[seed])[:3])}",
                _newest_after_sleep(runs[seed])[3])
    own = [v for s in seeds for v in runs[s]["success_after_own_wake"]]
    others = _mt5_rows()
    _states(ident, f"{min(own):.2f}-{max(own):.2f}")
    _states(ident, *(f"{name} {others[v][seeds[0]]:.3f} and {others[v][seeds[1]]:.3f}" for v, name in MT5_ROWS))
    _states(ident, f"0-{n - 1}", ", ".join(f"{v:.3f}" for v in values), _mean_se(values),
            *(f"{name} {_mean_se([others[v][s] for s in range(n)])}" for v, name in MT5_ROWS))
    assert {v: sum(values[s] < others[v][s] for s in range(n)) for v in below} == below
    _states(ident, *words)  # below SR on "all n" seeds, below Reset & Distill on ACT on "k"
    wake, after = _newest_means(runs)
    _states(ident, f"0-{n - 1}", f"{after:.3f}", f"{wake:.3f}")


def test_the_v_on_act_mt5_summary_and_readme_recompute():
    """V on ACT's MT5 imitation runs over all ten seeds (descriptive): RESULTS' summary of them (the archived
    ``summary_sr_c``: AFSR, BWT against both references beside SR's against its own wakes, the three CPU types) and
    README's sentence (the mean +- SE beside SR's and Reset & Distill on ACT's, the seeds below each, the newest skill's
    mean after its own wake and right after the sleep that follows, BWT against its own wakes beside SR's)."""
    runs, values = _v_act(10, MT5_IMITATION.name)
    assert [_cpu_type(MT5_IMITATION / f"{V_ACT}{s}") for s in range(10)] == ["6/207"] * 2 + ["25/1"] * 4 + ["25/17"] * 4
    others = _mt5_rows()
    below = {v: sum(values[s] < others[v][s] for s in range(10)) for v in ("sr", "reset_distill")}
    assert below == {"sr": 10, "reset_distill": 6}
    bwt, bwt_wake = (_mean_se([r["metrics"][m]["final"] for r in runs]) for m in ("bwt", "bwt_wake"))
    sr_wake = _mean_se(list(archived_values(MT5_IMITATION, "sr", "bwt_wake").values()))
    variant = read_checked_json(MT5_IMITATION / "summary_sr_c" / "summary.json")["variants"]["sr_c"]
    assert variant["bwt_wake"]["per_seed"] == pytest.approx([r["metrics"]["bwt_wake"]["final"] for r in runs])
    assert f"{variant['bwt']['mean']:+.3f} +- {variant['bwt']['sem']:.3f}" == f"+{bwt}"
    reach = [f"{runs[s]['success_after_own_wake'][0]:.2f}" for s in (8, 9)]
    assert min(v for s in (8, 9) for v in runs[s]["success_after_own_wake"][1:]) == 1.0
    _states("v-act-mt5-8-9", *reach)  # "the two lowest own-wake values being reach's"
    _states("v-act-mt5-8-9", _mean_se(values), f"+{bwt}", bwt_wake, sr_wake, "0-1", "model 207", "2-5",
            "family 25 model 1", "6-9", "model 17")
    wake, after = _newest_means(runs)
    _states("ev-which-method-prose", f"{_mean_se(values)} over seeds 0-9", _mean_se(list(others["sr"].values())),
            _mean_se(list(others["reset_distill"].values())), "all ten", "on six", f"{wake:.3f}", "a third",
            f"{after:.3f}", bwt_wake, sr_wake)
    assert 0.25 < after / wake < 0.42  # "about a third"
    assert "seeds 0-1 Intel Xeon model 207, 2-5 AMD EPYC family 25 model 1, 6-9 model 17" in \
        _which_method_rows()["configs/metaworld_mt5_imitation.json"]


def test_the_issue_59_summary_recomputes():
    """RESULTS' opening paragraph on what issue 59 added: the confirmatory family's three means on test seeds 0-4 and
    both Holm-adjusted p values with their verdicts, SR c_b1 below Reset & Distill on every seed, and each imitation
    stream's Reset & Distill on ACT, SR c on ACT and SR means over seeds 0-9, from the archives."""
    _, (v1, v2) = _sleep_family()
    _states("issue-59-summary", f"SR c_b1 {_mean_se(v1['a_values'])}", f"SR {_mean_se(v1['b_values'])}", "V1",
            f"p = {v1['p_holm']:.4f}", f"Reset & Distill {_mean_se(v2['b_values'])}", "V2", f"p = {v2['p_holm']:.4f}",
            "neither rejected", "every seed")
    assert not (v1["significant_holm"] or v2["significant_holm"])
    assert all(np.less(v2["a_values"], v2["b_values"]))  # SR c_b1 below Reset & Distill on every seed
    means = {}
    for preset, (archive, sr_archives) in RD_ON_ACT.items():
        rd = archived_values(DOCS / "results" / archive, "reset_distill", "afsr")
        sr = _over(sr_archives, "sr")
        assert sorted(rd) == sorted(sr) == list(range(10))
        means[preset] = (_mean_se(list(rd.values())), _mean_se(_v_act(10, archive)[1]), _mean_se(list(sr.values())))
    (rd_n, v_n, sr_n), (rd_m, v_m, sr_m) = (means[p] for p in RD_ON_ACT)  # needle m16, then MT5 imitation
    _states("issue-59-summary", f"Reset & Distill on ACT {rd_n}", rd_m, v_n, v_m, sr_n, sr_m)


def test_the_sac_sleeps_cosines_recompute():
    """RESULTS' 06:30 table (issue 59, exploratory): each row's cosine ranges and final weights from the archived
    stage-5 sleep diagnostics of the two repeats, whose compare reports found every number equal to their runs."""
    for run, folder in (("sr (calibration)", "sr_seed100"), ("sr_b1 (step B)", "sr_b1_seed100")):
        base = DOCS / "results" / "sac_sleep_cosines" / folder
        diag = read_checked_json(base / "stage5_sleep_diagnostics.json")
        cells = []
        for c in diag["cosines_first_last"]:
            c = np.array(c)
            pulling = np.diag(c) > 0.5
            off = c[~np.eye(len(c), dtype=bool) & np.outer(pulling, pulling)]
            assert np.abs(off).max() < 0.2  # the claim: nearly orthogonal
            cells.append(f"{off.min():+.3f} to {off.max():+.3f}")
        alpha = diag["alpha"][-1]
        assert _row("sac-cosines-table", f"{run} seed 100")[1:] == [
            f"{diag['stop_iteration']} iterations ({diag['stop_reason']})", cells[0], cells[1],
            f"{min(alpha):.3f}-{max(alpha):.3f}"], run
        assert "the runs differ in 0 values; every number equal" in (base / "compare.txt").read_text()


def test_the_1735_cosines_line_recomputes():
    """RESULTS' 17:35 cosine numbers (issue 59, exploratory) against the archive's summary, which
    tests/experiments/test_sleep_cosines.py recomputes from the archived re-sleeps: each repeat equal to its run, the
    largest off-diagonal cosines, the weights' and Eq. 1's optimum's distance from 1/5."""
    runs = {r["run"]: r for r in read_checked_json(DOCS / "results" / "sac_sleep_cosines" / "cosines.json")["runs"]}
    for name in ("sr_c_b1_seed102", "sr_b1_seed102", "sr_seed0"):
        r = runs[name]
        assert r["differing_values"] == 0 and not r["settings_changed"], name
        assert r["largest_weight_deviation"] <= 0.030 and max(abs(a - 0.2) for a in r["nash_optimum_on_last"]) <= 0.008
    counts = [int(c) for c in re.findall(r"(\d+) measured values", "".join(
        (DOCS / "results" / "sac_sleep_cosines" / n / "compare.txt").read_text()
        for n in ("sr_c_b1_seed102", "sr_b1_seed102", "sr_seed0")))]
    _states("sac-cosines-1735", f"0 of {counts[0]}, {counts[1]} and {counts[2]}",
            *(f"**{runs[n]['largest_off_diagonal_first']:.3f} / {runs[n]['largest_off_diagonal_last']:.3f}**"
              for n in ("sr_c_b1_seed102", "sr_b1_seed102", "sr_seed0")), "0.030", "0.008")
    first, last = (max(r[f"largest_off_diagonal_{w}"] for r in runs.values()) for w in ("first", "last"))
    assert len(runs) == 5 and max(r["largest_weight_deviation"] for r in runs.values()) <= 0.03
    _states("ev-which-method-prose", "(five", f"{first:.3f}", f"{last:.3f}", "0.03")  # "within 0.03 of uniform"


def test_the_1752_drawer_open_line_recomputes():
    """RESULTS' 17:52 observation (exploratory): drawer-open's success right after its own wake, per archived run."""
    def own_wake(archive: str, run: str) -> float:
        results = json.loads((DOCS / "results" / archive / run / "results.json").read_text())
        return results["success_after_own_wake"][results["skills"].index("drawer-open")]

    for variant in ("sr", "wake_only", "reset_distill"):
        values = " / ".join(f"{own_wake('sac_mt5_gate', f'{variant}_seed{s}'):.2f}" for s in range(5))
        _states("sac-drawer-1752", f"`{variant}` {values}")
    assert all(own_wake("sac_sleep_calibration", f"sr_seed{s}") == 1.0 for s in (100, 101, 102))
    _states("sac-drawer-1752", "`sr_b1` seed 100", f"{own_wake('sac_sleep_step_b', 'sr_b1_seed100'):.2f}")
    xeon = [("sac_sleep_step_b", f"{v}_seed{s}") for v, s in (("sr_b1", 101), ("sr_b1", 102), ("sr_c_b1", 100),
                                                             ("sr_c_b1", 101), ("sr_c_b1", 102))]
    xeon.append(("sac_mt5_gate_xeon", "sr_seed0"))
    for archive, run in xeon:
        assert own_wake(archive, run) == 0.0, run
        assert "Xeon" in json.loads((DOCS / "results" / archive / run / "results.json").read_text())["machine"]["cpu"]
    assert own_wake("sac_mt5_gate_avx2", "sr_seed0") == 1.0
    learned = sum(own_wake("sac_mt5_gate", f"{v}_seed{s}") >= 0.5
                  for v in ("sr", "wake_only", "reset_distill") for s in range(5))
    _states("sac-drawer-1752", f"{learned} of 15")


def test_the_mt5_family_recomputes():
    """M1 and M2's table and the family's Holm-adjusted verdict against the archived runs (SR, wake-only and replay on
    seeds 0-9, N1's ten runs); the stored hypotheses equal a recompute; a test cannot run on seeds it lacks."""
    rows = _table_rows("mt5-family-seeds")
    runs = _mt5_runs(("sr", "wake_only", "replay"))
    assert [int(r[0]) for r in rows] == list(range(10))
    for seed, *cells in rows:
        a, b, c = (runs[(v, int(seed))]["metrics"]["afsr"]["final"] for v in ("sr", "wake_only", "replay"))
        assert cells == [f"{a:.3f}", f"{b:.3f}", f"{c:.3f}", f"{a - b:+.3f}", f"{a - c:+.3f}"], seed
    family = run_tests(HypothesesConfig(archive=MT5_COMPARE, tests=FAMILY, holm=True))
    table = _table_rows("mt5-family-table")
    assert [r[0].split(":")[0] for r in table] == ["M1", "M2", "N1"]
    for cells, r in zip(table, family, strict=True):
        assert cells[1:9] == [f"{r['seeds'][0]}-{r['seeds'][-1]}", f"{r['mean']:+.3f} +- {r['sem']:.3f}",
                              f"[{r['ci_low']:+.3f}, {r['ci_high']:+.3f}]", f"{r['t']:.2f}",
                              *(f"{r[k]:.4f}" for k in ("p", "sign_flip_p", "p_holm", "sign_flip_p_holm"))], cells[0]
        assert cells[9].startswith("rejected" if r["significant_holm"] else "not rejected"), cells[0]
    stored = json.loads((MT5_COMPARE / "hypotheses" / "hypotheses.json").read_text())["tests"]
    assert [(t["name"], t["seeds"], t["p"], t["sign_flip_p"], t["p_holm"], t["sign_flip_p_holm"]) for t in stored] \
        == [(r["name"], r["seeds"], r["p"], r["sign_flip_p"], r["p_holm"], r["sign_flip_p_holm"]) for r in family]
    with pytest.raises(ValueError, match="no finished run yet"):
        run_tests(HypothesesConfig(archive=MT5_COMPARE, tests=["sr>wake_only@0-10"]))
    # descriptive: the arms, BWT against both references, per-skill finals, the first two wakes shared by SR and
    # wake-only (no sleep precedes the second), the README's lines
    metric = {(v, m): [runs[(v, s)]["metrics"][m]["final"] for s in range(10)]
              for v in ("sr", "wake_only", "replay") for m in ("afsr", "bwt", "bwt_wake", "prs", "spi")}
    _states("mt5-family-verdict", _mean_se(metric[("sr", "afsr")]), _mean_se(metric[("wake_only", "afsr")]),
            f"{family[0]['mean']:+.3f} +- {family[0]['sem']:.3f}", _mean_se(metric[("replay", "afsr")]),
            f"{family[1]['mean']:+.3f} +- {family[1]['sem']:.3f}")
    bwt = {v: _signed(metric[(v, "bwt")]) for v in ("sr", "wake_only", "replay")}
    own = np.mean([runs[("sr", s)]["success_after_own_wake"] for s in range(10)], axis=0)
    assert metric[("wake_only", "bwt")] == metric[("wake_only", "bwt_wake")]
    final = {v: np.mean([runs[(v, s)]["success_matrix"][-1] for s in range(10)], axis=0)
             for v in ("sr", "wake_only", "replay")}
    _states("mt5-descriptive", " / ".join(f"{x:.2f}" for x in own), bwt["sr"], _signed(metric[("sr", "bwt_wake")]),
            bwt["wake_only"], bwt["replay"],
            *(f"{n} " + " / ".join(f"{final[v][i]:.2f}" for v in ("sr", "wake_only", "replay"))
              for i, n in enumerate(MT5_SKILLS)),
            *(f"{label} " + " / ".join(f"{np.mean(metric[(v, m)]):.3f}" for v in ("sr", "wake_only", "replay"))
              for m, label in (("prs", "PRS"), ("spi", "SPI"))))
    for s in range(10):
        sr, wake = (runs[(v, s)]["stages"] for v in ("sr", "wake_only"))
        assert [sr[i]["wake"]["best_val_l1"] for i in (0, 1)] == [wake[i]["wake"]["best_val_l1"] for i in (0, 1)]
        assert "sleep" not in sr[0] and "sleep" in sr[1]
    curve = {v: np.mean([runs[(v, s)]["metrics"]["afsr"]["curve"] for s in range(10)], axis=0)
             for v in ("sr", "wake_only", "replay")}
    second = {v: np.mean([runs[(v, s)]["success_matrix"][1][:2] for s in range(10)], axis=0)
              for v in ("sr", "wake_only", "replay")}
    before = np.mean([runs[("sr", s)]["extra"]["success_matrix_after_wake"][1][:2] for s in range(10)], axis=0)
    later = {v: " / ".join(f"{x:.3f}" for x in curve[v][2:]) for v in ("sr", "wake_only")}
    _states("mt5-descriptive", f"{before[0]:.2f}", f"{second['sr'][0]:.2f}", f"{before[1]:.2f}",
            f"{second['sr'][1]:.2f}", f"{second['wake_only'][0]:.2f} / {second['wake_only'][1]:.2f}",
            f"{second['replay'][0]:.2f} / {second['replay'][1]:.2f}", f"{curve['sr'][1]:.3f}",
            f"{curve['wake_only'][1]:.3f}", f"{curve['replay'][1]:.3f}", later["sr"], later["wake_only"],
            f"{final['sr'][1]:.2f}")
    assert curve["sr"][1] < curve["wake_only"][1] and all(curve["sr"][2:] > curve["wake_only"][2:])
    assert f"{final['sr'][1]:.2f}" == f"{final['wake_only'][1]:.2f}"  # door-open's "final 0.75 in both"
    diffs = np.subtract(family[0]["a_values"], family[0]["b_values"])
    assert (np.sum(diffs > 1e-9), np.sum(np.abs(diffs) < 1e-9), np.sum(diffs < -1e-9)) == (8, 1, 1)
    reach_own = [runs[("sr", s)]["success_after_own_wake"][0] for s in range(10)]
    reach_final = [final[v][0] for v in ("sr", "wake_only", "replay")]
    _states("ev-mt5-imitation", _mean_se(metric[("sr", "afsr")]), _mean_se(metric[("wake_only", "afsr")]),
            f"{family[0]['mean']:+.3f} +- {family[0]['sem']:.3f}", "8 of 10", f"p = {family[0]['p']:.3f}",
            f"{family[0]['sign_flip_p']:.3f}", f"{min(r['p_holm'] for r in family):.3f}",
            f"{min(reach_own):.2f}-{max(reach_own):.2f}", f"{min(reach_final):.2f}-{max(reach_final):.2f}")
    assert not any(r["significant_holm"] for r in family)


def test_the_mt5_references_recompute():
    """The MT5 stream's references on seeds 0-9 (descriptive): MT-Joint's and sequential BC's final AFSR and success
    per skill, sequential BC's success right after each own wake and on each earlier skill right after the next
    wake, the share of the gap between them that SR, wake-only and replay close; the baselines EWC, LwF and
    M2Distill on seeds 0-2 likewise (final AFSR and BWT, right after own wake, the worst earlier skill right after
    the next wake, final per skill); and the README's line."""
    runs = _mt5_runs(("mt_joint", "sequential_bc", "sr", "wake_only", "replay"))
    afsr = {v: _finals(runs, v, "afsr", range(10)) for v in ("mt_joint", "sequential_bc", "sr", "wake_only", "replay")}
    final = {v: np.mean([runs[(v, s)]["success_matrix"][-1] for s in range(10)], axis=0)
             for v in ("mt_joint", "sequential_bc")}
    skills = {v: ", ".join(f"{n} {x:.2f}" for n, x in zip(MT5_SKILLS, final[v], strict=True)) for v in final}
    low = [str(s) for s in range(10) if runs[("mt_joint", s)]["success_matrix"][-1][0] < 0.8]
    _states("mt5-descriptive", _mean_se(afsr["mt_joint"]), skills["mt_joint"], ", ".join(low))
    assert np.mean(afsr["mt_joint"]) >= 0.9 and final["mt_joint"][0] < 0.8 and min(final["mt_joint"][1:]) >= 0.8
    own = np.mean([runs[("sequential_bc", s)]["success_after_own_wake"] for s in range(10)], axis=0)
    at_next = _after_next_wake(runs, "sequential_bc", range(10))
    bwt = _finals(runs, "sequential_bc", "bwt", range(10))
    _states("mt5-descriptive", f"({_list(own)})", f"{np.mean(at_next):.2f}", f"{len(at_next)}",
            f"{sum(x > 0.1 for x in at_next)}", f"{max(at_next):.2f}", _mean_se(afsr["sequential_bc"]),
            skills["sequential_bc"], _signed(bwt))
    closed = {v: (np.mean(afsr[v]) - np.mean(afsr["sequential_bc"]))
              / (np.mean(afsr["mt_joint"]) - np.mean(afsr["sequential_bc"])) for v in ("sr", "wake_only", "replay")}
    _states("mt5-descriptive", *(f"{closed[v]:.0%}" for v in ("sr", "wake_only", "replay")))
    names = {"ewc_lam10000": "EWC", "lwf_w0.1": "LwF", "m2distill_w0.01": "M2Distill"}
    base = _mt5_runs((*names, "sequential_bc"), range(3))

    def finals(v: str, metric: str) -> list[float]:
        return _finals(base, v, metric, range(3))

    ends = ", ".join(f"{n} {_mean_se(finals(v, 'afsr'))} (BWT {_signed(finals(v, 'bwt'))})" for v, n in names.items())
    _states("mt5-descriptive", ends, _mean_se(finals("sequential_bc", "afsr")))
    own_wake = {v: np.mean([base[(v, s)]["success_after_own_wake"] for s in range(3)], axis=0) for v in names}
    _states("mt5-descriptive", *(f"{n} {_list(own_wake[v])}" for v, n in names.items()))
    next_wake = {v: _after_next_wake(base, v, range(3)) for v in names}
    _states("mt5-descriptive", "12", *(x for v in names for x in (f"{np.mean(next_wake[v]):.2f}",
                                                                  f"{max(next_wake[v]):.2f}")))
    last = {v: np.mean([base[(v, s)]["success_matrix"][-1] for s in range(3)], axis=0) for v in names}
    _states("mt5-descriptive", *(f"{n} {', '.join(f'{k} {x:.2f}' for k, x in zip(MT5_SKILLS, last[v], strict=True))}"
                                 for v, n in names.items()))
    # the drawer-open LwF and M2Distill end with came back in the last wake after the window-close wake had lost it
    back = [(v, s) for v in ("lwf_w0.1", "m2distill_w0.01") for s in range(3)
            if base[(v, s)]["success_matrix"][-1][2] > 0]
    fell = max(base[k]["success_matrix"][3][2] for k in back)
    _states("mt5-descriptive", f"{len(back)}", f"{fell:.2f}")
    means = ", ".join(f"{n} {np.mean(finals(v, 'afsr')):.3f}" for v, n in names.items())
    _states("ev-mt5-imitation", f"MT-Joint {np.mean(afsr['mt_joint']):.3f}",
            f"sequential BC {np.mean(afsr['sequential_bc']):.3f}", "10", f"{closed['sr']:.0%}",
            f"{closed['wake_only']:.0%}", means, "3")
    _states("mt5-references-summary", f"{np.mean(afsr['mt_joint']):.3f}", f"{np.mean(afsr['sequential_bc']):.3f}",
            "10", means, "3")  # the earlier summary's headline


# --- the MT5 imitation stream's calibration (protocol in RESULTS; readings below it) ---------------------------------

def _list(values: list[float]) -> str:
    return " / ".join(f"{v:.2f}" for v in values)


def _seeds(step: str, variant: str, metric: str) -> str:
    """A calibration step's final ``metric`` of ``variant`` on seeds 100 / 101 / 102, as RESULTS writes it."""
    archive = DOCS / "results" / f"metaworld_mt5_imitation_calibration_{step}"
    finals = [json.loads((archive / f"{variant}_seed{s}" / "results.json").read_text())["metrics"][metric]["final"]
              for s in (100, 101, 102)]
    return " / ".join(f"{v:.3f}" for v in finals)


@pytest.mark.parametrize("step, readings", [
    ("metaworld_mt5_imitation_calibration", lambda c: [("calib-step0", [
        f"{c['C1']['mt_joint_afsr']:.3f}", _list(c["C1"]["mt_joint_final_per_skill"]),
        _list(c["C2"]["own_wake_per_skill"]), f"{c['C3']['final_afsr']:.3f}", f"{c['C4']['wake_only_afsr']:.3f}"])]),
    ("metaworld_mt5_imitation_calibration_k1", lambda c: [("calib-k1", [
        f"{c['C1']['mt_joint_afsr']:.3f}", _list(c["C1"]["mt_joint_final_per_skill"]), f"{c['C3']['final_afsr']:.3f}",
        f"{c['C4']['wake_only_afsr']:.3f}"])]),
    ("metaworld_mt5_imitation_calibration_k2", lambda c: [("calib-k2", [
        f"{c['C1']['mt_joint_afsr']:.3f}", f"{c['C1']['mt_joint_final_per_skill'][0]:.2f}",
        _list(c["C2"]["own_wake_per_skill"]), f"{c['C3']['final_afsr']:.3f}"])]),
    ("metaworld_mt5_imitation_calibration_k3", lambda c: [
        ("calib-k3-c1", [_seeds("k3", "mt_joint", "afsr"), f"{c['C1']['mt_joint_afsr']:.3f}",
                         _list(c["C1"]["mt_joint_final_per_skill"])]),
        ("calib-test-preset", [f"{c['C1']['mt_joint_afsr']:.3f}", f"{c['C1']['mt_joint_final_per_skill'][0]:.2f}"]),
        ("calib-k3-c2c3", [_list(c["C2"]["own_wake_per_skill"]), _list(c["C3"]["after_next_stage"]),
                           f"{c['C3']['final_afsr']:.3f}"]),
        ("calib-k3-c4", [f"{c['C4']['wake_only_afsr']:.3f}", _list(c["C4"]["wake_only_final_per_skill"]),
                         "C4 **not met**"])]),
    ("metaworld_mt5_imitation_calibration_k4", lambda c: [  # K4 re-runs wake-only only (RESULTS, 04:27 UTC)
        ("calib-k4-c4", [f"{c['C4']['wake_only_afsr']:.3f}", _list(c["C4"]["wake_only_final_per_skill"]),
                         "C4 **met**"])]),
])
def test_each_calibration_step_s_reading_recomputes_from_its_raw_runs(step, readings):
    """Each archived step's ``calibration/calibration.json`` equals the reading recomputed now from the step's raw
    runs, and the record quotes its numbers as they recompute (rounded as written there), in each reading's block."""
    from experiments.calibration import CalibrationConfig, read_calibration

    archive = DOCS / "results" / step
    stored = json.loads((archive / "calibration" / "calibration.json").read_text())
    now = read_calibration(CalibrationConfig(archive=archive))
    assert now["criteria"] == stored["criteria"] and now["seeds"] == stored["seeds"]
    for ident, numbers in readings(now["criteria"]):
        _states(ident, *numbers)


# --- the first look (README): the numbers it states recompute from its archived runs ---------------------------------

def test_the_first_look_s_stated_outcomes_recompute_from_its_runs(readme):
    """README's "A first look" states, for the preset as it is (30 epochs per wake), the final success per skill of
    training seeds 0-4 and of the preset's own seed 1000, and that every skill reached >= 0.80 right after its own
    wake on seeds 0-4; each archived run was made with the preset's settings."""
    preset = json.loads((DOCS.parent / "configs" / "needle_try.json").read_text())["train"]
    finals = {}
    for seed in (0, 1, 2, 3, 4, 1000):
        run = DOCS / "results" / "needle_try_first_look" / f"wake30_seed{seed}"
        config = json.loads((run / "train_config.json").read_text())
        assert config["seed"] == seed and config["wake"] == {**config["wake"], **preset["wake"]}
        assert config["stream"]["skills"] == preset["stream"]["skills"]
        results = json.loads((run / "results.json").read_text())
        if seed != 1000:
            assert min(results["success_after_own_wake"]) >= 0.8, (seed, results["success_after_own_wake"])
        finals[seed] = " / ".join(f"{v:.2f}" for v in results["success_matrix"][-1])
    assert "at the end " + ", ".join(finals[s] for s in (0, 1, 2, 3)) + ", " + finals[4] + "; the preset's own" \
        in readme, finals
    assert f"ends {finals[1000]}, insert reaching only {finals[1000].split(' / ')[-1]}" in readme


WHICH_METHOD = {  # README's "Which method where": row (its preset) -> archive, and each variant's seeds
    "configs/needle_cpu_m16.json": ("needle_cpu_m16_compare", {"sr": 5, "wake_only": 5, "replay": 5}),
    "configs/needle_cpu_vision.json": ("needle_cpu_vision_compare", {"sr": 5, "wake_only": 5}),
    "configs/needle_cpu.json": ("needle_cpu_v2_compare", {"sr": 5, "wake_only": 5}),
    "configs/metaworld_mt5_imitation.json": ("metaworld_mt5_imitation_compare",
                                             {"sr": 10, "replay": 10, "wake_only": 10, "sequential_bc": 10}),
    "configs/sac_mt5_gate.json": ("sac_mt5_gate_xeon", {"reset_distill": 5, "sr": 5, "sr_c_b1": 5}),  # the family's
}
NAMES = {"sr": "SR", "wake_only": "wake-only", "replay": "replay", "reset_distill": "Reset & Distill",
         "sequential_bc": "sequential BC", "sr_c_b1": "SR c_b1"}


def _which_method_rows() -> dict[str, str]:
    """README's "Which method where" table: each row's line, by the preset it names first."""
    lines = (DOCS / "EVIDENCE.md").read_text().split("## Which method where", 1)[1].split("\n## ", 1)[0]
    return {line.split("`")[1]: line for line in lines.splitlines() if line.startswith("| ") and "`configs/" in line}


def test_the_which_method_where_table_recomputes():
    """README's table: each row's means +- SE from its archive, and the method it names highest is the highest of
    those it lists (not of the oracle, which is not a continual method)."""
    rows = _which_method_rows()
    assert set(rows) == set(WHICH_METHOD)
    for preset, (archive, variants) in WHICH_METHOD.items():
        cells = rows[preset].split(" | ")
        values = {}
        for variant, n in variants.items():
            got = archived_values(DOCS / "results" / archive, variant, "afsr")
            assert len(got) == n, (preset, variant)
            values[variant] = list(got.values())
            stated = f"{NAMES[variant]} {_mean_se(values[variant])}"
            if variant == "sr" and not cells[1].startswith("SR"):
                stated = _mean_se(values[variant])  # SR's own column when another method is the highest
            assert stated in rows[preset], (preset, stated)
        best = max(values, key=lambda v: np.mean(values[v]))
        assert cells[1].startswith(NAMES[best]), (preset, best)


RD_ON_ACT = {  # README row (its preset) -> the archive of Reset & Distill on ACT and the archives of SR's seeds 0-9
    "configs/needle_cpu_m16.json": ("needle_cpu_m16_compare", ("needle_cpu_m16_compare", "needle_cpu_m16_replication")),
    "configs/metaworld_mt5_imitation.json": ("metaworld_mt5_imitation_compare", ("metaworld_mt5_imitation_compare",)),
}
"""Issue 59 item 5's rows (descriptive). The runs sit outside ``WHICH_METHOD``: they were made on another CPU type than
their rows' other runs, so they name no method highest."""


def test_the_reset_and_distill_on_act_cells_recompute():
    """README's Reset & Distill on ACT cells and sentences: every seed's final AFSR in seed order and their mean +- SE,
    on how many seeds SR's archived run ended higher, and the BWT against its own wakes, from the archives; the
    archived summary beside the runs holds the same numbers."""
    rows = _which_method_rows()
    values, below, bwt_wake = {}, {}, {}
    for preset, (archive, sr_archives) in RD_ON_ACT.items():
        got = archived_values(DOCS / "results" / archive, "reset_distill", "afsr")
        assert sorted(got) == list(range(10)), (preset, sorted(got))
        values[preset] = [got[s] for s in range(10)]
        listed = ", ".join(f"{v:.3f}" for v in values[preset])
        stated = f"Reset & Distill on ACT {_mean_se(values[preset])}"
        assert f"{stated} (seeds 0-9: {listed}; descriptive, no test" in rows[preset]
        _states("ev-needle-m16" if preset == "configs/needle_cpu_m16.json" else "ev-mt5-imitation", stated, "10")
        sr = _over(sr_archives, "sr")
        assert sorted(sr) == list(range(10)), (preset, sorted(sr))
        below[preset] = sum(got[s] < sr[s] for s in range(10))
        wake = list(archived_values(DOCS / "results" / archive, "reset_distill", "bwt_wake").values())
        bwt_wake[preset] = _mean_se(wake)
        summary = json.loads((DOCS / "results" / archive / "summary_reset_distill" / "summary.json").read_text())
        variant = summary["variants"]["reset_distill"]
        assert variant["afsr"]["per_seed"] == pytest.approx(values[preset])
        assert f"{variant['bwt_wake']['mean']:.3f} +- {variant['bwt_wake']['sem']:.3f}" == bwt_wake[preset]
    needle, mt5 = RD_ON_ACT  # its two rows, in the order written
    _states("ev-which-method-prose", f"{below[needle]} of 10", f"{below[mt5]} of 10", bwt_wake[needle], bwt_wake[mt5])
    bwt = list(archived_values(DOCS / "results" / RD_ON_ACT[mt5][0], "reset_distill", "bwt").values())
    _states("rd-act-mt5-all", f"**{_mean_se(values[mt5])}**", _signed(bwt), bwt_wake[mt5])  # all ten MT5 seeds
    runs = [json.loads((DOCS / "results" / RD_ON_ACT[mt5][0] / f"{RD}seed{s}" / "results.json").read_text())
            for s in range(10)]
    newest = [r["success_matrix"][k][k] for r in runs for k in range(1, 5)]  # right after skill k's distillation
    own = [r["success_after_own_wake"][k] for r in runs for k in range(1, 5)]
    _states("rd-act-mt5-all", f"{np.mean(newest):.3f}", f"0.00 in {newest.count(0.0)} of those {len(newest)}",
            f"{np.mean(own):.3f}")


@pytest.mark.parametrize("preset", sorted(RD_ON_ACT))
def test_the_v_on_act_cells_recompute(preset):
    """README's SR c on ACT cell in each imitation row (issue 59 item 5, descriptive): every seed's final AFSR in seed
    order and their mean +- SE, from the archive; the archived summary beside the runs holds the same values."""
    archive, _ = RD_ON_ACT[preset]
    _, values = _v_act(10, archive)
    listed = ", ".join(f"{v:.3f}" for v in values)
    row = _which_method_rows()[preset]
    assert "SR c on ACT" in row and f"{_mean_se(values)} (seeds 0-9: {listed}; descriptive, no test" in row
    summary = read_checked_json(DOCS / "results" / archive / "summary_sr_c" / "summary.json")
    assert summary["variants"]["sr_c"]["afsr"]["per_seed"] == pytest.approx(values)


def test_the_v_on_act_needle_sentence_recomputes():
    """README's sentence on SR c on ACT's needle runs (descriptive): on how many seeds it ended below SR's archived run
    and above Reset & Distill on ACT's, the mean success after its own wakes, and BWT against its own wakes beside
    SR's; the archived summary holds the same BWT."""
    archive, sr_archives = RD_ON_ACT["configs/needle_cpu_m16.json"]
    runs, values = _v_act(10)
    sr = _over(sr_archives, "sr")
    sr_wake = list(_over(sr_archives, "sr", "bwt_wake").values())
    rd = archived_values(DOCS / "results" / archive, "reset_distill", "afsr")
    assert sorted(sr) == sorted(rd) == list(range(10)) and len(sr_wake) == 10
    below, above = sum(values[s] < sr[s] for s in range(10)), sum(values[s] > rd[s] for s in range(10))
    own = np.mean([np.mean(r["success_after_own_wake"]) for r in runs])
    bwt_wake = _mean_se([r["metrics"]["bwt_wake"]["final"] for r in runs])
    ties = {"SR": [s for s in range(10) if values[s] == sr[s]], "Reset & Distill on ACT": [s for s in range(10)
                                                                                   if values[s] == rd[s]]}
    models = _cpu_models(DOCS / "results" / archive / f"{V_ACT}{s}" for s in range(10))
    assert [models[f"{V_ACT}{s}"] for s in range(10)] == ["167"] * 3 + ["207"] * 7
    assert {_cpu_type(DOCS / "results" / archive / f"{RD}seed{s}") for s in range(10)} == {"25/1"}
    _states("ev-which-method-prose", f"{below} of 10", f"one tie (seed {ties['SR'][0]})", f"{above} of 10",
            f"one tie (seed {ties['Reset & Distill on ACT'][0]})", "three CPU types", "0-2", "model 167", "3-9",
            "model 207", "family 25 model 1", f"{own:.3f}", bwt_wake, _mean_se(sr_wake),
            f"docs/results/{archive}/summary_sr_c/")
    assert [len(v) for v in ties.values()] == [1, 1]
    variant = read_checked_json(DOCS / "results" / archive / "summary_sr_c" / "summary.json")["variants"]["sr_c"]
    assert f"{variant['bwt_wake']['mean']:.3f} +- {variant['bwt_wake']['sem']:.3f}" == bwt_wake


def test_the_v_on_act_needle_summary_line_recomputes():
    """RESULTS' twentieth-session line on V on ACT's needle m16 summary (descriptive): AFSR, BWT against both
    references, the range of the per-skill means right after their own wakes and regrasp's final mean, from the ten
    runs; the archived summary holds the same."""
    runs, values = _v_act(10)
    bwt, bwt_wake = ([r["metrics"][m]["final"] for r in runs] for m in ("bwt", "bwt_wake"))
    skills = runs[0]["skills"]
    own = [np.mean([r["success_after_own_wake"][k] for r in runs]) for k in range(len(skills))]
    regrasp = [r["success_matrix"][-1][skills.index("regrasp")] for r in runs]
    _states("v-act-needle-summary", _mean_se(values), _mean_se(bwt), _mean_se(bwt_wake),
            f"{min(own):.3f}-{max(own):.3f}", f"regrasp ends lowest, {_mean_se(regrasp)}")
    assert min(own) == own[skills.index("insert")]
    ends = [np.mean([r["success_matrix"][-1][k] for r in runs]) for k in range(len(skills))]
    assert min(ends) == ends[skills.index("regrasp")]
    summary = json.loads((DOCS / "results" / "needle_cpu_m16_compare" / "summary_sr_c" / "summary.json").read_text())
    assert summary["variants"]["sr_c"]["bwt"]["per_seed"] == pytest.approx(bwt)


def test_the_v_on_act_needle_line_recomputes():
    """RESULTS' 2026-12-02 01:16 line (descriptive): V on ACT's needle m16 seeds 0-4, each final AFSR and their mean
    +- SE, and the regrasp claim (learned in every own wake, 0.00 at the end in three of five), from the archive."""
    runs, values = _v_act(5)
    _states("v-act-needle-0-4", "0-4", ", ".join(f"{v:.3f}" for v in values), _mean_se(values))
    regrasp = [r["skills"].index("regrasp") for r in runs]
    assert all(r["success_after_own_wake"][i] == 1.0 for r, i in zip(runs, regrasp, strict=True))
    assert sum(r["success_matrix"][-1][i] == 0.0 for r, i in zip(runs, regrasp, strict=True)) == 3
    _states("v-act-needle-0-4", "0.00 in three of five")


def _summary_and_rest() -> tuple[str, str]:
    results = (DOCS / "RESULTS.md").read_text()
    start = results.index("## Summary")
    end = results.index("## Contents")
    return results[start:end], results[:start] + results[end:] + _record_text()


def test_results_opens_with_a_summary_of_at_most_600_words_whose_every_number_the_record_states():
    """The summary quotes, it does not compute: each of its numbers is stated in the sections and records below (whose
    numbers the tests above recompute from the raw files)."""
    summary, rest = _summary_and_rest()
    assert len(summary.split()) <= 600
    rest = " ".join(rest.split())
    numbers = set(re.findall(r"(?<![\w.])[+-]?\d+\.\d+(?:e-?\d+)?", summary))
    assert len(numbers) >= 40
    assert sorted(n for n in numbers if n not in rest) == []


def test_the_contents_link_every_section_and_every_protocol_links_its_record():
    """RESULTS keeps the summary, the contents and the protocols; the contents link every protocol (by its anchor)
    and every record file; each protocol links its record, and each record file names what it records in its first
    line: ``# Record: <the protocol's or the section's title>``."""
    results = (DOCS / "RESULTS.md").read_text()
    headings = [line[3:] for line in results.splitlines() if line.startswith("## ")]
    toc = re.findall(r"^- \[(.+)\]\(#([^)]+)\)$", results, re.M)
    assert [t for t, _ in toc] == [h for h in headings if not h.startswith("Summary (") and h != "Contents"]
    assert len(toc) >= 5  # the protocols (the SAC gate's statement keeps its own title: it is not edited)
    for title, anchor in toc:  # GitHub's anchors: lower case, punctuation dropped, spaces to hyphens
        assert anchor == re.sub(r"[^\w\- ]", "", title.lower()).replace(" ", "-"), title
    files = sorted(p.name for p in RECORDS.glob("*.md"))
    listed = re.findall(r"^- (\d{4}-\d\d-\d\d): \[(.+?)\]\(results/records/([\w]+\.md)\)", results, re.M)
    assert sorted(name for _, _, name in listed) == files and len(files) >= 17
    assert [d for d, _, _ in listed] == sorted(d for d, _, _ in listed)  # by the date of their first entry
    for _, title, name in listed:
        assert (RECORDS / name).read_text().splitlines()[0] == f"# Record: {title}", name
    sections = results.split("\n## ")
    for title, _ in toc:  # each protocol links its record, whose title is the protocol's
        (body,) = [s for s in sections if s.startswith(title)]
        (name,) = set(re.findall(r"\(results/records/([\w]+\.md)\)", body))
        assert (RECORDS / name).read_text().startswith(f"# Record: {title}\n"), name


def test_a_block_is_found_by_its_id_and_a_drifted_number_fails(monkeypatch):
    """``_states`` finds numbers in their block whatever the words around them, and fails when one drifts, is out of
    order, or is only a prefix of the number written (0.03 in 0.032)."""
    block = {"x": "SR 0.895 +- 0.032 vs wake-only 0.764,\np = 0.029"}
    monkeypatch.setattr(sys.modules[__name__], "_blocks", lambda: block)
    _states("x", "0.895 +- 0.032", "0.764", "p = 0.029")
    for numbers in (["0.896 +- 0.032"], ["0.764", "0.895 +- 0.032"], ["0.03"], ["0.89"], ["-0.764"], ["p = 0.02"]):
        with pytest.raises(AssertionError):
            _states("x", *numbers)
    with pytest.raises(AssertionError, match="no block has the id"):
        _by_id("y")


def test_the_lerobot06_replication_r1_recomputes():
    """R1 of the LeRobot 0.6 replication (descriptive, seeds 0-4): each arm's final AFSR per seed and mean +- SE, BWT,
    the paired differences with the protocol's "holds" rule and the descriptive p values, the change from LeRobot
    0.4.4's archived runs on the same seeds, from the archive; the evidence page's paragraph states the same."""
    archive = DOCS / "results" / "lerobot06_needle_m16"
    arms = ("sr", "wake_only", "replay")
    afsr = {v: archived_values(archive, v, "afsr") for v in arms}
    assert all(sorted(afsr[v]) == [0, 1, 2, 3, 4] for v in arms)
    values = {v: [afsr[v][s] for s in range(5)] for v in arms}
    bwt = {v: list(archived_values(archive, v, "bwt").values()) for v in arms}
    _states("r1-complete", *(x for v in arms for x in (" / ".join(f"{a:.3f}" for a in values[v]),
                                                       f"({_mean_se(values[v])})")),
            *(f"{np.mean(bwt[v]):.3f}" for v in arms))
    tests = run_tests(HypothesesConfig(archive=archive, tests=["sr>wake_only", "sr>replay"]))
    for t in tests:
        diffs = np.subtract(t["a_values"], t["b_values"])
        holds = t["mean"] > 0 and sum(diffs > 0) >= 4
        _states("r1-complete", " / ".join(f"{d:+.3f}" for d in diffs), f"{t['mean']:+.3f} +- {t['sem']:.3f}",
                "**holds**" if holds else "**does not hold**", f"p = {t['p']:.4f}", f"p = {t['sign_flip_p']:.4f}")
        _states("ev-lerobot06", f"{t['mean']:+.3f} +- {t['sem']:.3f}")
    for v in arms:  # what the stack changed: 0.6.1 - 0.4.4 on the same seeds
        old = archived_values(ARCHIVE, v, "afsr")
        _states("r1-complete", _signed([afsr[v][s] - old[s] for s in range(5)]),
                f"{np.mean(values[v]):.3f} against {np.mean(list(old.values())):.3f}")
    _states("ev-lerobot06", *(_mean_se(values[v]) for v in arms))


def test_the_sac_sleep_lengths_and_the_cross_cpu_sentence_recompute():
    """The evidence page's SAC sentences: SR's sleeps on the gate's runs stop after 200-900 of their 4000 iterations
    and up to 1600 in the calibration runs; SR's final AFSR on the Xeon test runs against the gate's runs of the same
    seeds (seed 3 the farthest apart), from the archives."""
    def stops(archive: str) -> list[int]:
        return [st["sleep"]["stop_iteration"] for run in sorted((DOCS / "results" / archive).glob("sr_seed*"))
                for st in read_checked_json(run / "results.json")["stages"] if st.get("sleep")]

    gate, calibration = stops("sac_mt5_gate"), stops("sac_sleep_calibration")
    limit = json.loads((DOCS / "results" / "sac_mt5_gate" / "sr_seed0" / "train_config.json").read_text())
    assert len(gate) == 20 and len(calibration) == 12
    _states("ev-which-method-prose", f"{min(gate)}-{max(gate)} of {limit['sleep']['max_iterations']}",
            f"up to {max(calibration)}")
    xeon, amd = (archived_values(DOCS / "results" / a, "sr", "afsr") for a in ("sac_mt5_gate_xeon", "sac_mt5_gate"))
    assert sorted(xeon) == sorted(amd) == [0, 1, 2, 3, 4]
    far = max(range(5), key=lambda s: abs(xeon[s] - amd[s]))
    _states("ev-which-method-prose", _mean_se(list(xeon.values())), _mean_se(list(amd.values())),
            f"seed {far}: {xeon[far]:.3f} against {amd[far]:.3f}")


def test_reach_on_mt5_by_imitation_is_kept_by_the_fresh_network_methods():
    """The correction to "kept by no method" (reach on MT5 by imitation): Reset & Distill on ACT's and SR c on ACT's
    final reach over seeds 0-9 against SR's, replay's and wake-only's range, from the archive."""
    reach = {v: np.mean([read_checked_json(MT5_IMITATION / f"{v}_seed{s}" / "results.json")["success_matrix"][-1][0]
                         for s in range(10)]) for v in ("sr", "replay", "wake_only", "reset_distill", "sr_c")}
    kept = [reach[v] for v in ("sr", "replay", "wake_only")]
    _states("ev-mt5-imitation", f"{min(kept):.2f}-{max(kept):.2f}", f"({reach['reset_distill']:.3f})",
            f"({reach['sr_c']:.3f})")
    for ident in ("mt5-descriptive", "mt5-evidence-summary"):
        _states(ident, f"{min(kept):.2f}-{max(kept):.2f}", f"{reach['reset_distill']:.3f}", f"{reach['sr_c']:.3f}")


def test_step_b_s_cpu_types_are_stated_where_its_numbers_are():
    """Step B compared runs of different CPU types; the record's step-B entry and the evidence page say which, as the
    step-B runs' results.json files record them (the calibration SR runs recorded no CPU; the record names it)."""
    step_b = DOCS / "results" / "sac_sleep_step_b"
    types = {run.name: _cpu_type(run) for run in sorted(step_b.glob("sr*_seed*"))}
    assert types == {"sr_b1_seed100": "25/1", "sr_b1_seed101": "6/167", "sr_b1_seed102": "6/167",
                     "sr_c_b1_seed100": "6/167", "sr_c_b1_seed101": "6/167", "sr_c_b1_seed102": "6/167"}
    assert all("machine" not in read_checked_json(run / "results.json")
               for run in (DOCS / "results" / "sac_sleep_calibration").glob("sr_seed*"))
    for ident in ("step-b-complete", "ev-which-method-prose"):
        _states(ident, "0.743 +- 0.025" if ident == "step-b-complete" else "0.687 +- 0.058", "family 25 model 1",
                "model 167", "(seed 100)", "model 167")
    means = {v: _mean_se([read_checked_json(step_b / f"{v}_seed{s}" / "results.json")["metrics"]["afsr"]["final"]
                          for s in (100, 101, 102)]) for v in ("sr_b1", "sr_c_b1")}
    _states("step-b-complete", means["sr_c_b1"], means["sr_b1"])



SAMPLER0 = "_final_sleep_anchor_off_sampler0"
NEEDLE_EPISODES = "_final_sleep_anchor_off_needle_episodes"
"""The needle reverse order's anchor-off re-sleeps of 16:00-17:00 UTC 2026-12-07, evaluated on the episodes of each
skill's place in the needle's own order rather than the run's (the 17:xx entry); the entries before it read them."""
"""The anchor-off re-sleeps made before 2026-12-07 16:00 UTC with sleep seed 0 instead of the run's final sleep's own
(the entries written from them recompute from them; the stream-order record's 16:00 entry says why they were redone)."""

def test_the_stream_orders_interim_entry_recomputes():
    """The stream-order record's interim entry (needle reverse, seeds 0-2): every seed's final AFSR, the means +- SE,
    the interaction against R1 and the last-sleep changes, from the archived runs and re-sleeps."""
    from experiments.stream_orders import interaction
    from sr_imitation.reporting.last_sleep import last_sleep_row, resleep_row

    reverse, forward = DOCS / "results" / "order_needle_m16_reverse", DOCS / "results" / "lerobot06_needle_m16"
    rev = {v: {s: x for s, x in archived_values(reverse, v, "afsr").items() if s <= 2}
           for v in ("sr", "wake_only", "replay", "sr_no_anchor")}
    fwd = {v: archived_values(forward, v, "afsr") for v in ("sr", "wake_only")}
    numbers = [" / ".join(f"{rev[v][s]:.3f}" for s in sorted(rev[v])) for v in ("sr", "wake_only", "replay")]
    numbers += [" / ".join(f"{rev['sr_no_anchor'][s]:.3f}" for s in (0, 1)), _mean_se(list(rev["wake_only"].values())),
                _mean_se(list(rev["sr"].values())), f"{rev['wake_only'][2] - rev['sr'][2]:.3f}"]
    inter = interaction(fwd, rev)
    assert inter["seeds"] == [0, 1, 2]
    numbers.append(f"{inter['mean']:.3f} +- {inter['sem']:.3f}")
    for rows in ([last_sleep_row(reverse / f"sr_seed{s}") for s in range(3)],
                 [resleep_row(reverse / f"sr_seed{s}{SAMPLER0}") for s in range(3)],
                 [last_sleep_row(forward / f"sr_seed{s}") for s in range(5)]):
        assert all(r["newest_change"] == 0 and r["newest_after_sleep"] == 1.0 for r in rows[:3])
        numbers.append(_signed([r["older_mean_change"] for r in rows]))
    _states("orders-interim-1", *numbers)


def test_the_stream_orders_o1_entry_recomputes():
    """The stream-order record's O1 entry (needle reverse, seeds 0-4): every seed's final AFSR, both means, O1's
    difference, t, p and sign-flip p, the interaction against R1, and the trigger's two readings."""
    from experiments.stream_orders import interaction
    from sr_imitation.experiments.hypotheses import format_p
    from sr_imitation.reporting.last_sleep import last_sleep_row

    reverse, forward = DOCS / "results" / "order_needle_m16_reverse", DOCS / "results" / "lerobot06_needle_m16"
    (o1,) = run_tests(HypothesesConfig(archive=reverse, tests=["O1=sr>wake_only@0-4"]))
    sr, wake = o1["a_values"], o1["b_values"]
    fwd = {v: archived_values(forward, v, "afsr") for v in ("sr", "wake_only")}
    inter = interaction(fwd, {"sr": dict(enumerate(sr)), "wake_only": dict(enumerate(wake))})
    assert o1["seeds"] == [0, 1, 2, 3, 4] and inter["seeds"] == [0, 1, 2, 3, 4]
    assert np.mean(sr) >= np.mean(wake)  # the trigger's first reading: SR's mean is not below wake-only's
    rows = [last_sleep_row(reverse / f"sr_seed{s}") for s in range(5)]
    assert all(r["newest_after_wake"] == r["newest_after_sleep"] == 1.0 for r in rows)
    _states("orders-needle-o1", " / ".join(f"{v:.3f}" for v in sr), " / ".join(f"{v:.3f}" for v in wake),
            _mean_se(sr), _mean_se(wake), f"{o1['mean']:+.3f} +- {o1['sem']:.3f}", f"t = {o1['t']:.2f}",
            f"p = {format_p(o1['p'])}", f"p = {format_p(o1['sign_flip_p'])}",
            f"{inter['mean']:+.3f} +- {inter['sem']:.3f}", f"{np.mean(wake):.3f}",
            f"{np.mean(list(fwd['wake_only'].values())):.3f}", f"{np.mean(sr):.3f}",
            f"{np.mean(list(fwd['sr'].values())):.3f}")


def test_the_stream_orders_o2_entry_recomputes():
    """The stream-order record's O2 entry (needle reverse, seeds 0-4): replay's final AFSR per seed and its mean, O2's
    difference, t, p and sign-flip p."""
    from sr_imitation.experiments.hypotheses import format_p

    reverse = DOCS / "results" / "order_needle_m16_reverse"
    (o2,) = run_tests(HypothesesConfig(archive=reverse, tests=["O2=sr!=replay@0-4"]))
    replay = o2["b_values"]
    assert o2["seeds"] == [0, 1, 2, 3, 4] and o2["alternative"] == "two-sided"
    assert all(a > b for a, b in zip(o2["a_values"], replay, strict=True))  # "SR ahead on all five seeds"
    _states("orders-needle-o2", " / ".join(f"{v:.3f}" for v in replay), _mean_se(replay),
            f"{o2['mean']:+.3f} +- {o2['sem']:.3f}", f"t = {o2['t']:.2f}", f"p = {format_p(o2['p'])}",
            f"p = {format_p(o2['sign_flip_p'])}")


def test_the_stream_orders_needle_complete_entry_recomputes():
    """The stream-order record's needle entry (both orders, seeds 0-4): the forward sr_no_anchor runs, the anchor's
    share per order, the last sleep with and without the anchor, and the archived order table it quotes."""
    from experiments.stream_orders import paired
    from sr_imitation.reporting.last_sleep import last_sleep_row, resleep_row

    results = DOCS / "results"
    fwd_runs, rev = results / "lerobot06_needle_m16", results / "order_needle_m16_reverse"
    no_anchor = {"forward": archived_values(results / "order_needle_m16_forward", "sr_no_anchor", "afsr"),
                 "reverse": archived_values(rev, "sr_no_anchor", "afsr")}
    sr = {"forward": archived_values(fwd_runs, "sr", "afsr"), "reverse": archived_values(rev, "sr", "afsr")}
    assert all(sorted(v) == [0, 1, 2, 3, 4] for v in (*no_anchor.values(), *sr.values()))
    numbers = [" / ".join(f"{no_anchor['forward'][s]:.3f}" for s in range(5)),
               _mean_se([*no_anchor["forward"].values()]), _mean_se([*no_anchor["reverse"].values()])]
    for order in ("forward", "reverse"):
        share = paired(sr[order], no_anchor[order])
        numbers.append(f"{share['mean']:+.3f} +- {share['sem']:.3f}")
    assert sum(sr["forward"][s] > no_anchor["forward"][s] for s in range(5)) == 4
    on_off = []
    for folder in (fwd_runs, rev):
        on = [last_sleep_row(folder / f"sr_seed{s}") for s in range(5)]
        off = [resleep_row(folder / f"sr_seed{s}{SAMPLER0}") for s in range(5)]
        assert all(r["newest_after_wake"] == r["newest_after_sleep"] == 1.0 for r in on + off)  # "all ten ... ten"
        numbers += [_signed([r["older_mean_change"] for r in on]), _signed([r["older_mean_change"] for r in off])]
        diff = [a["older_mean_change"] - b["older_mean_change"] for a, b in zip(on, off, strict=True)]
        assert sum(d > 0 for d in diff) == 4
        on_off.append(_signed(diff))
    _states("orders-needle-complete", *numbers, *on_off)
    table = (results / "stream_orders" / "orders.md").read_text()
    assert "forward: ranking sr > sr_no_anchor > wake_only > replay" in table
    assert "reverse: ranking sr > wake_only > sr_no_anchor > replay" in table


MT5_REVERSE = DOCS / "results" / "order_mt5_imitation_reverse"


@functools.cache
def _stream_order_family() -> tuple[dict, dict, dict]:
    """O1, O2, O3 on seeds 0-4 with Holm over the three, as the stream-order protocol declares them."""
    tests = ["O1=sr>wake_only@0-4", "O2=sr!=replay@0-4", f"O3={MT5_REVERSE}::sr>wake_only@0-4"]
    o1, o2, o3 = run_tests(HypothesesConfig(archive=DOCS / "results" / "order_needle_m16_reverse", tests=tests,
                                            holm=True))
    return o1, o2, o3


def _last_sleeps(archive: Path) -> tuple[list[dict], list[dict]]:
    """Seeds 0-4: each SR run's final sleep as the run made it, and its re-sleep with the anchor off."""
    from sr_imitation.reporting.last_sleep import ANCHOR_OFF, last_sleep_row, resleep_row

    return ([last_sleep_row(archive / f"sr_seed{s}") for s in range(5)],
            [resleep_row(archive / f"sr_seed{s}{ANCHOR_OFF}") for s in range(5)])


def test_the_evidence_page_s_stream_order_paragraph_recomputes():
    """EVIDENCE's reverse-order paragraph (and README's needle and MT5 rows, which quote it): the means, O1's, O2's and
    O3's differences and p-values (before and after Holm), and MT5's reverse last sleep with and without the anchor,
    from the archived reverse-order runs and re-sleeps."""
    from sr_imitation.experiments.hypotheses import format_p

    o1, o2, o3 = _stream_order_family()
    assert o1["seeds"] == o2["seeds"] == o3["seeds"] == [0, 1, 2, 3, 4]
    assert all(a > b for a, b in zip(o2["a_values"], o2["b_values"], strict=True))
    assert sum(a > b for a, b in zip(o3["a_values"], o3["b_values"], strict=True)) == 4
    on, off = _last_sleeps(MT5_REVERSE)
    assert all(r["newest"] == "reach-v3" and r["newest_change"] < 0 for r in on)
    newest = _signed([r["newest_change"] for r in on])
    _states("ev-stream-orders", _mean_se(o1["a_values"]), _mean_se(o1["b_values"]),
            f"{o1['mean']:+.3f} +- {o1['sem']:.3f}", f"p = {o1['p']:.2f}", f"p = {o1['sign_flip_p']:.2f}",
            f"by {o1['mean']:.3f}", _mean_se(o2["b_values"]), f"{o2['mean']:+.3f} +- {o2['sem']:.3f}",
            f"p = {format_p(o2['p'])}", f"{format_p(o2['p_holm'])} after Holm", _mean_se(o3["a_values"]),
            _mean_se(o3["b_values"]), f"{o3['mean']:+.3f} +- {o3['sem']:.3f}", f"p = {o3['p']:.3f}",
            f"p = {o3['sign_flip_p']}", f"{o3['p_holm']:.3f} after Holm", newest,
            _signed([r["older_mean_change"] for r in on]), _signed([r["newest_change"] for r in off]))
    readme = (DOCS.parent / "README.md").read_text().split("## Which method where", 1)[1]
    (row,) = [line for line in readme.splitlines() if line.startswith("| [needle, 16 stored frames]")]
    assert f"SR {_mean_se(o1['a_values'])} and wake-only {_mean_se(o1['b_values'])}" in row
    assert f"(p = {o1['p']:.2f})" in row and f"(O2, Holm p = {format_p(o2['p_holm'])})" in row
    (row,) = [line for line in readme.splitlines() if line.startswith("| [Meta-World MT5 by imitation]")]
    assert f"SR {_mean_se(o3['a_values'])} and wake-only {_mean_se(o3['b_values'])}" in row
    assert f"(O3, p = {o3['p']:.3f}, adjusted {o3['p_holm']:.3f})" in row and not o3["significant_holm"]
    assert f"lowered the newest skill by {newest[1:]}" in row and newest.startswith("-")


def test_the_stream_orders_mt5_seed0_entry_recomputes():
    """The stream-order record's first MT5 entry (seed 0, both orders): the four final AFSRs, and the last sleep with
    the anchor and re-slept without it in each order, from the archived runs and re-sleeps."""
    from sr_imitation.reporting.last_sleep import last_sleep_row, resleep_row

    numbers = []
    for name in ("lerobot06_mt5_imitation", "order_mt5_imitation_reverse"):
        archive = DOCS / "results" / name
        numbers += [f"{archived_values(archive, v, 'afsr')[0]:.3f}" for v in ("sr", "wake_only")]
    reverse, forward = (DOCS / "results" / n for n in ("order_mt5_imitation_reverse", "lerobot06_mt5_imitation"))
    on, off = last_sleep_row(reverse / "sr_seed0"), resleep_row(reverse / f"sr_seed0{SAMPLER0}")
    assert on["newest"] == off["newest"] == "reach-v3" and on["newest_after_wake"] == off["newest_after_wake"]
    numbers += [f"{on['newest_after_wake']:.3f}", f"{on['newest_after_sleep']:.3f}", f"{on['newest_change']:+.3f}",
                f"{on['older_mean_change']:+.3f}", f"{off['newest_after_sleep']:.3f}", f"{off['newest_change']:+.3f}",
                f"{off['older_mean_change']:+.3f}"]
    on, off = last_sleep_row(forward / "sr_seed0"), resleep_row(forward / f"sr_seed0{SAMPLER0}")
    assert on["newest"] == "button-press-topdown-v3"
    assert on["newest_after_wake"] == on["newest_after_sleep"] == off["newest_after_sleep"] == 1.0
    numbers += [f"{on['older_mean_change']:+.3f}", f"{off['older_mean_change']:+.3f}"]
    _states("orders-mt5-seed0", *numbers)


def test_the_stream_orders_re_sleep_seed_correction_recomputes():
    """The correction entry: each new re-sleep starts from its run's own first batch (memory losses before the sleep
    equal the run's; the earlier ones did not), how far the batch order moved the older skills' change, and the
    corrected readings with and without the anchor, from both sets of re-sleeps."""
    from sr_imitation.reporting.last_sleep import ANCHOR_OFF, last_sleep_row, resleep_row

    numbers, moved = [], []
    for name, suffix in (("lerobot06_needle_m16", ANCHOR_OFF), ("order_needle_m16_reverse", NEEDLE_EPISODES)):
        folder = DOCS / "results" / name
        on = [last_sleep_row(folder / f"sr_seed{s}") for s in range(5)]
        off = [resleep_row(folder / f"sr_seed{s}{suffix}") for s in range(5)]
        old = [resleep_row(folder / f"sr_seed{s}{SAMPLER0}") for s in range(5)]
        assert [r["loss_before"] for r in off] == [r["loss_before"] for r in on]  # the run's own first batch
        assert all(a["loss_before"] != b["loss_before"] for a, b in zip(on, old, strict=True))
        assert [r["newest_change"] for r in off] == [r["newest_change"] for r in old] == [0.0] * 5
        moved.append([a["older_mean_change"] - b["older_mean_change"] for a, b in zip(off, old, strict=True)])
        diff = [a["older_mean_change"] - b["older_mean_change"] for a, b in zip(on, off, strict=True)]
        numbers += [_signed([r["older_mean_change"] for r in off]), _signed(diff)]
        numbers.append(f"{_signed([r['older_mean_change'] for r in old]).split(' ')[0]}")
    assert max(abs(x) for m in moved for x in m) == pytest.approx(0.025, abs=1e-3)
    for name in ("lerobot06_mt5_imitation", "order_mt5_imitation_reverse"):
        folder = DOCS / "results" / name
        new, old = (read_checked_json(folder / f"sr_seed0{suffix}" / "sleep.json")["success"]
                    for suffix in (ANCHOR_OFF, SAMPLER0))
        assert new == old  # "every success value identical"
    fwd, rev = numbers[:3], numbers[3:]
    _states("orders-resleep-seed", _signed(moved[0]), _signed(moved[1]), fwd[0], fwd[2], rev[0], rev[2], fwd[1],
            rev[1])


def test_the_needle_reverse_re_sleeps_on_the_run_s_episodes_recompute():
    """The episodes correction: every new reverse re-sleep starts from its run's own evaluation (success before the
    sleep equals the run's after its last wake) with the earlier one's memory losses and stop, the earlier ones did
    not on seeds 0, 2 and 3 (regrasp), and the corrected readings."""
    from sr_imitation.reporting.last_sleep import ANCHOR_OFF, last_sleep_row, resleep_row
    from sr_imitation.reporting.results import load_results

    folder = DOCS / "results" / "order_needle_m16_reverse"
    on = [last_sleep_row(folder / f"sr_seed{s}") for s in range(5)]
    new = [resleep_row(folder / f"sr_seed{s}{ANCHOR_OFF}") for s in range(5)]
    old = [resleep_row(folder / f"sr_seed{s}{NEEDLE_EPISODES}") for s in range(5)]
    regrasp = []
    for s in range(5):
        woke = load_results(folder / f"sr_seed{s}")["extra"]["success_matrix_after_wake"][-1]
        for suffix, ok in ((ANCHOR_OFF, True), (NEEDLE_EPISODES, None)):
            record = read_checked_json(folder / f"sr_seed{s}{suffix}" / "sleep.json")
            before = [record["success"][k]["before"] for k in record["sleep"]["skills"]]
            if ok:
                assert before == woke
            else:
                assert [b - w for b, w in zip(before, woke, strict=True) if b != w] == [
                    b - w for b, w in zip(before[1:2], woke[1:2], strict=True) if b != w]  # regrasp only
                regrasp.append(round(before[1] - woke[1], 3))
        assert (new[s]["loss_after"], new[s]["stop_iteration"]) == (old[s]["loss_after"], old[s]["stop_iteration"])
    assert regrasp == [-0.233, 0.0, -0.033, 0.133, 0.0]
    assert [r["newest_after_sleep"] for r in new] == [1.0] * 5
    diff = [a["older_mean_change"] - b["older_mean_change"] for a, b in zip(on, new, strict=True)]
    ahead = (sum(d > 1e-9 for d in diff), sum(abs(d) <= 1e-9 for d in diff), sum(d < -1e-9 for d in diff))
    assert ahead == (2, 2, 1)
    _states("orders-resleep-episodes", "-0.233", "-0.033", "+0.133", _signed([r["older_mean_change"] for r in new]),
            _signed([r["older_mean_change"] for r in old]).split(" ")[0], _signed(diff))


def test_the_mt5_seed1_entry_recomputes():
    """Seed 1's final AFSR in both orders, the reverse order's last sleep with and without the anchor, and the check
    that sr-sleep repeats the run's own final sleep exactly on both reverse seeds."""
    from experiments.final_sleep_screening import order_rows
    from sr_imitation.reporting.last_sleep import ANCHOR_OFF, last_sleep_row, resleep_row
    from sr_imitation.reporting.results import load_results

    results = DOCS / "results"
    afsr = {(a, v): np.mean(load_results(results / a / f"{v}_seed1")["success_matrix"][-1])
            for a in ("lerobot06_mt5_imitation", "order_mt5_imitation_reverse") for v in ("sr", "wake_only")}
    reverse = results / "order_mt5_imitation_reverse"
    run, off = last_sleep_row(reverse / "sr_seed1"), resleep_row(reverse / f"sr_seed1{ANCHOR_OFF}")
    assert run["newest"] == "reach-v3" and off["newest_after_sleep"] == run["newest_after_wake"]
    both = [last_sleep_row(reverse / f"sr_seed{s}")["newest_change"] for s in (0, 1)]
    rows = order_rows(reverse)
    assert all(rows["own"][s] == rows["C0"][s] for s in (0, 1))
    for s in (0, 1):
        own = read_checked_json(reverse / f"sr_seed{s}_final_sleep_own" / "sleep.json")["sleep"]["final_memory_losses"]
        assert own == load_results(reverse / f"sr_seed{s}")["stages"][-1]["sleep"]["final_memory_losses"]
    f = lambda x: f"{x:.3f}"  # noqa: E731
    _states("orders-mt5-seed1", *(f(afsr[k]) for k in afsr), f(run["newest_after_wake"]), f(run["newest_after_sleep"]),
            f"{run['older_change']['button-press-topdown-v3']:+.3f}", f"{run['older_change']['door-open-v3']:+.3f}",
            f"{run['older_mean_change']:+.3f}", f(off["newest_after_sleep"]), f"{off['older_mean_change']:+.3f}",
            _signed(both))


def test_the_mt5_seed2_entry_recomputes():
    """Seed 2's final AFSR in both orders, the reverse last sleep with and without the anchor, seeds 0-2's newest
    change both ways, and own repeating the run's sleep on seed 2."""
    from experiments.final_sleep_screening import order_rows
    from sr_imitation.reporting.last_sleep import ANCHOR_OFF, last_sleep_row, resleep_row
    from sr_imitation.reporting.results import load_results

    results = DOCS / "results"
    afsr = [np.mean(load_results(results / a / f"{v}_seed2")["success_matrix"][-1])
            for a in ("lerobot06_mt5_imitation", "order_mt5_imitation_reverse") for v in ("sr", "wake_only")]
    reverse = results / "order_mt5_imitation_reverse"
    run, off = last_sleep_row(reverse / "sr_seed2"), resleep_row(reverse / f"sr_seed2{ANCHOR_OFF}")
    with_anchor = [last_sleep_row(reverse / f"sr_seed{s}")["newest_change"] for s in range(3)]
    without = [resleep_row(reverse / f"sr_seed{s}{ANCHOR_OFF}")["newest_change"] for s in range(3)]
    rows = order_rows(reverse)
    assert rows["own"][2] == rows["C0"][2]
    f = lambda x: f"{x:.3f}"  # noqa: E731
    wc = "window-close-v3"
    woke_wc = load_results(reverse / "sr_seed2")["extra"]["success_matrix_after_wake"][-1][1]
    assert run["skills"][1] == wc
    _states("orders-mt5-seed2", *map(f, afsr), f(run["newest_after_wake"]), f(run["newest_after_sleep"]), f(woke_wc),
            f(woke_wc + run["older_change"][wc]), f"{run['older_change'][wc]:+.3f}", f"{run['older_mean_change']:+.3f}",
            f(off["newest_after_sleep"]), f"{off['older_change'][wc]:+.3f}", f"{off['older_mean_change']:+.3f}",
            _signed(with_anchor), _signed(without))


def test_the_stream_orders_mt5_o3_entry_recomputes():
    """The family's entry (MT5 reverse, seeds 0-4): every seed's final AFSR, O3's statistics, the three Holm p values
    from the archived family (equal to a recompute), and the reverse last sleep with and without the anchor, with the
    memory-loss ratios it quotes and the trigger's reading."""
    from sr_imitation.experiments.hypotheses import format_p

    results = DOCS / "results"
    family = _stream_order_family()
    stored = json.loads((results / "stream_orders" / "hypotheses" / "hypotheses.json").read_text())["tests"]
    assert [t["p_holm"] for t in stored] == pytest.approx([t["p_holm"] for t in family], rel=1e-12)
    assert (results / "stream_orders" / "hypotheses" / "hypotheses.md").read_text().startswith("Pre-registered")
    o1, o2, o3 = family
    sr, wake = o3["a_values"], o3["b_values"]
    assert o3["seeds"] == [0, 1, 2, 3, 4] and [a > b for a, b in zip(sr, wake, strict=True)].count(True) == 4
    assert o2["significant_holm"] and not o3["significant_holm"] and not o1["significant_holm"]
    on, off = _last_sleeps(MT5_REVERSE)
    assert all(r["newest"] == "reach-v3" and r["newest_change"] < 0 for r in on)
    assert sum(r["newest_change"] == 0 for r in off) == 4
    assert np.mean([r["newest_change"] for r in on]) <= -0.10  # the trigger
    ratios = [a["loss_after"] / b["loss_after"] for a, b in zip(on, off, strict=True)]
    newest_loss = [r["newest_loss_after"] for r in on]
    assert all(r["newest_loss_before"] == 0 for r in on)
    f = lambda x: f"{x:.3f}"  # noqa: E731
    _states("orders-mt5-o3", " / ".join(map(f, sr)), f"({_mean_se(sr)})", " / ".join(map(f, wake)),
            f"({_mean_se(wake)})", f"{sr[4] - wake[4]:+.3f}", f"{o3['mean']:+.3f} +- {o3['sem']:.3f}",
            f"t = {o3['t']:.2f}", f"p = {format_p(o3['p'])}", f"p = {format_p(o3['sign_flip_p'])}",
            f"[{o3['ci_low']:+.3f}, {o3['ci_high']:+.3f}]", f"p = {format_p(o2['p_holm'])}",
            f"{format_p(o2['sign_flip_p'])}", f"p = {format_p(o3['p_holm'])}", f"O1 {format_p(o1['p_holm'])}",
            *(f"{r['newest_after_wake']:.3f} -> {r['newest_after_sleep']:.3f}" for r in on),
            _signed([r["newest_change"] for r in on]), _signed([r["older_mean_change"] for r in on]),
            f"seed 3 {on[3]['older_mean_change']:+.3f}", f"seed 4 {on[4]['older_mean_change']:+.3f}",
            _signed([r["newest_change"] for r in off]), _signed([r["older_mean_change"] for r in off]),
            f"{min(ratios):.1f}-{max(ratios):.1f}x", f"{min(newest_loss):.1e}-{max(newest_loss):.1e}",
            f"{np.mean([r['newest_change'] for r in on]):.3f}")


def _replication_arms(archive: Path, seeds: int) -> tuple[dict, dict, list[str], dict]:
    """SR and wake-only of a replication archive on seeds 0..seeds-1: final AFSR by seed, the values in seed order,
    the numbers its entry states first (each arm's values and mean, +- SE from three seeds on; mean BWT against the
    stage before, then against each skill's own wake) and the paired one-sided test SR > wake-only."""
    arms = ("sr", "wake_only")
    afsr = {v: archived_values(archive, v, "afsr") for v in arms}
    assert all(sorted(afsr[v]) == list(range(seeds)) for v in arms)
    values = {v: [afsr[v][s] for s in range(seeds)] for v in arms}
    mean = (lambda x: f"({_mean_se(x)})") if seeds > 2 else (lambda x: f"(mean {np.mean(x):.3f})")
    numbers = [x for v in arms for x in (" / ".join(f"{a:.3f}" for a in values[v]), mean(values[v]))]
    for metric in ("bwt", "bwt_wake"):
        numbers += [f"{np.mean(list(archived_values(archive, v, metric).values())):.3f}" for v in arms]
    (t,) = run_tests(HypothesesConfig(archive=archive, tests=[f"sr>wake_only@0-{seeds - 1}"]))
    return afsr, values, numbers, t


def test_the_lerobot06_replication_r2_recomputes():
    """R2 of the LeRobot 0.6 replication (MT5 by imitation, descriptive, seeds 0-4): each arm's final AFSR per seed and
    mean +- SE, BWT against both references, the paired differences with the protocol's "holds" rule and the
    descriptive p values, the change from LeRobot 0.4.4's archived runs on the same seeds, and the newest skill kept
    across every final sleep with and without the anchor, from the archive and its re-sleeps."""
    archive = DOCS / "results" / "lerobot06_mt5_imitation"
    arms = ("sr", "wake_only")
    afsr, values, numbers, t = _replication_arms(archive, seeds=5)
    diffs = np.subtract(t["a_values"], t["b_values"])
    assert t["mean"] > 0 and sum(diffs > 0) == 5  # "five of five positive": holds
    numbers += [" / ".join(f"{d:+.3f}" for d in diffs), f"{t['mean']:+.3f} +- {t['sem']:.3f}",
                f"p = {t['p']:.4f}", f"p = {t['sign_flip_p']:.4f}"]
    for v in arms:  # what the stack changed: 0.6.1 - 0.4.4 on the same seeds
        old = archived_values(MT5_IMITATION, v, "afsr")
        numbers += [_signed([afsr[v][s] - old[s] for s in range(5)]),
                    f"{np.mean(values[v]):.3f} against {np.mean([old[s] for s in range(5)]):.3f}"]
    _states("r2-complete", *numbers)
    _states("ev-lerobot06", *(_mean_se(values[v]) for v in arms), f"{t['mean']:+.3f} +- {t['sem']:.3f}")
    readme = (DOCS.parent / "README.md").read_text().split("## Which method where", 1)[1]
    (row,) = [line for line in readme.splitlines() if line.startswith("| [Meta-World MT5 by imitation]")]
    assert f"LeRobot 0.6.1: {_mean_se(values['sr'])} (seeds 0-4)" in row
    assert f"LeRobot 0.6.1: wake-only {_mean_se(values['wake_only'])}" in row
    assert "replicated on LeRobot 0.6.1 (descriptive, seeds 0-4)" in row
    for on, off in zip(*_last_sleeps(archive), strict=True):
        assert on["newest"] == "button-press-topdown-v3"
        assert on["newest_after_wake"] == on["newest_after_sleep"] == off["newest_after_sleep"] == 1.0
    assert (archive / "last_sleep" / "last_sleep.md").is_file()


VISION_044 = DOCS / "results" / "needle_cpu_vision_compare"


def test_the_lerobot06_replication_r3_recomputes():
    """R3 of the LeRobot 0.6 replication (the camera preset, descriptive, seeds 0-1): each arm's final AFSR per seed,
    BWT against both references, the paired differences with the protocol's rule for R3 (holds: both pairs > 0;
    weakened: mean > 0 with fewer) and the descriptive p values, where seed 1's pair went, the change from LeRobot
    0.4.4's archived runs on the same seeds; README's camera row and the evidence page state the same outcome."""
    from sr_imitation.reporting.results import load_results

    archive = DOCS / "results" / "lerobot06_needle_vision"
    arms = ("sr", "wake_only")
    afsr, values, numbers, t = _replication_arms(archive, seeds=2)
    diffs = np.subtract(t["a_values"], t["b_values"])
    outcome = "holds" if t["mean"] > 0 and all(diffs > 0) else "weakened" if t["mean"] > 0 else "not seen"
    assert outcome == "weakened" and sum(diffs > 0) == 1  # the entry's words: "one of the two pairs positive"
    numbers += [" / ".join(f"{d:+.3f}" for d in diffs), f"{t['mean']:+.3f} +- {t['sem']:.3f}", f"**{outcome}**",
                f"p = {t['p']:.4f}", f"p = {t['sign_flip_p']:.4f}"]
    sr1, wake1 = (load_results(archive / f"{v}_seed1") for v in arms)
    regrasp = sr1["skills"].index("regrasp")
    others = [x for i, x in enumerate(sr1["success_matrix"][-1]) if i != regrasp]
    assert wake1["success_after_own_wake"][regrasp] == 1.0
    numbers += [f"regrasp to {sr1['success_after_own_wake'][regrasp]:.2f}",
                f"{wake1['success_after_own_wake'][regrasp]:.2f})",
                f"at {sr1['success_matrix'][-1][regrasp]:.2f}", f"at {min(others):.2f}-{max(others):.2f}",
                f"wake is {archived_values(archive, 'sr', 'bwt_wake')[1]:.3f}"]
    for v in arms:  # what the stack changed: 0.6.1 - 0.4.4 on the same seeds
        old = archived_values(VISION_044, v, "afsr")
        numbers += [" / ".join(f"{afsr[v][s] - old[s]:+.3f}" for s in range(2)),
                    f"{np.mean(values[v]):.3f} against {np.mean([old[s] for s in range(2)]):.3f}"]
    _states("r3-complete", *numbers)
    _states("ev-lerobot06", f"{np.mean(values['sr']):.3f} against {np.mean(values['wake_only']):.3f}")
    readme = (DOCS.parent / "README.md").read_text().split("## Which method where", 1)[1]
    (row,) = [line for line in readme.splitlines() if line.startswith("| [needle with a camera]")]
    assert f"LeRobot 0.6.1: {np.mean(values['sr']):.3f} (seeds 0-1)" in row
    assert f"LeRobot 0.6.1: wake-only {np.mean(values['wake_only']):.3f}" in row
    assert f"{outcome} on LeRobot 0.6.1 (descriptive, seeds 0-1): SR ahead on {sum(diffs > 0)} of 2 seeds" in row


def test_the_lerobot06_replication_r4_main_job_recomputes():
    """R4's main job (``configs/needle_cpu.json``, seed 1000) on LeRobot 0.6.1: every success cell 1.00, AFSR and BWT,
    the run's wall time from the queue's log, and LeRobot 0.4.4's run of the same preset and seed; README's line for
    that preset states both."""
    from datetime import datetime

    from sr_imitation.reporting.results import load_results
    from tests.tool_loader import load_tool

    archive = DOCS / "results" / "lerobot06_main_job"
    new, old = load_results(archive / "sr_seed1000"), load_results(DOCS / "results" / "needle_cpu_main_41b435c")
    assert new["seed"] == old["seed"] == 1000 and new["config"]["torch_threads"] == 1
    assert all(x == 1.0 for row in new["success_matrix"] for x in row if x is not None)
    assert all(x == 1.0 for x in new["success_after_own_wake"])
    m, o = new["metrics"], old["metrics"]
    assert m["bwt"]["final"] == m["bwt_wake"]["final"] == 0.0
    _, finished = load_tool("experiments/queue_status").runs(archive / "queue_log.txt")
    (run,) = [r for r in finished if r["name"] == "l06_main_sr_1000"]
    wall = datetime.fromisoformat(run["ended"]) - datetime.fromisoformat(run["started"])
    minutes, seconds = divmod(int(wall.total_seconds()), 60)
    insert = old["skills"].index("insert")
    _states("r4-main-job", f"{minutes} min {seconds} s", _afsr_cell(m), _afsr_cell(o),
            f"(insert {old['success_matrix'][-1][insert]:.2f})")
    readme = " ".join((DOCS.parent / "README.md").read_text().split())
    assert (f"configs/needle_cpu.json` runs the older single SR run with 1024 stored frames a skill (seed 1000 on "
            f"LeRobot 0.6.1: every skill at 1.00 at the end; AFSR {o['afsr']['final']:.3f} on LeRobot 0.4.4)") in readme


def test_the_stream_orders_complete_entry_recomputes():
    """The closing descriptive entry: MT5's means in both orders and the interaction, the needle's interaction, MT5's
    forward last sleep with and without the anchor (the newest skill kept everywhere) and the reverse order's
    with-minus-without, the last-sleep tables beside every archive, and the archived order table it names."""
    from experiments.stream_orders import interaction
    from sr_imitation.reporting.last_sleep import ANCHOR_OFF

    results = DOCS / "results"
    names = {"needle": ("lerobot06_needle_m16", "order_needle_m16_reverse"),
             "mt5": ("lerobot06_mt5_imitation", "order_mt5_imitation_reverse")}
    arms = ("sr", "wake_only")
    def both(stream: str) -> dict[str, dict[str, dict[int, float]]]:
        return {o: {v: archived_values(results / n, v, "afsr") for v in arms}
                for o, n in zip(("f", "r"), names[stream], strict=True)}

    mt5, needle = both("mt5"), both("needle")
    numbers = [_mean_se(list(mt5[o][v].values())) for o in ("f", "r") for v in arms]
    for values in (mt5, needle):
        inter = interaction(values["f"], values["r"])
        assert inter["seeds"] == [0, 1, 2, 3, 4]
        numbers.append(f"{inter['mean']:+.3f} +- {inter['sem']:.3f}")
    rows = {order: _last_sleeps(results / name) for order, name in zip(("f", "r"), names["mt5"], strict=True)}
    on, off = rows["f"]
    assert all(r["newest_after_wake"] == r["newest_after_sleep"] == 1.0 for r in on + off)
    numbers += [_signed([r["older_mean_change"] for r in on]), _signed([r["older_mean_change"] for r in off]),
                _signed([a["older_mean_change"] - b["older_mean_change"] for a, b in zip(on, off, strict=True)])]
    on, off = rows["r"]
    numbers += [_signed([a[k] - b[k] for a, b in zip(on, off, strict=True)])
                for k in ("older_mean_change", "newest_change")]
    _states("orders-complete", *numbers)
    for name in (*names["needle"], *names["mt5"]):
        table = read_checked_json(results / name / "last_sleep" / "last_sleep.json")
        runs = [Path(r["run"]).name for r in table["rows"]]
        assert [f"sr_seed{s}" for s in range(5)] == [r for r in runs if r.startswith("sr_seed") and "_final" not in r]
        assert [f"sr_seed{s}{ANCHOR_OFF}" for s in range(5)] == [r for r in runs if r.endswith(ANCHOR_OFF)], name
        assert (results / name / "last_sleep" / "last_sleep.png").is_file(), name
    orders = (results / "stream_orders" / "orders.md").read_text()
    assert "## mt5" in orders and orders.count("the ranking of sr, wake_only held") == 1


def test_own_repeats_the_final_sleep_of_every_mt5_reverse_run():
    """Entry ``orders-own-all``: on each of the five MT5 reverse seeds, the ``own`` re-sleep's success values equal the
    run's final sleep's (the screening's reader) and its memory losses after the sleep equal the run's exactly."""
    from experiments.final_sleep_screening import order_rows
    from sr_imitation.reporting.results import load_results

    reverse = DOCS / "results" / "order_mt5_imitation_reverse"
    rows = order_rows(reverse)
    seeds = sorted(rows["own"])
    assert seeds == sorted(rows["C0"]) == [0, 1, 2, 3, 4]
    for s in seeds:
        assert rows["own"][s] == rows["C0"][s], s
        own = read_checked_json(reverse / f"sr_seed{s}_final_sleep_own" / "sleep.json")["sleep"]["final_memory_losses"]
        assert own == load_results(reverse / f"sr_seed{s}")["stages"][-1]["sleep"]["final_memory_losses"], s
    _states("orders-own-all", f"all {len(seeds)} MT5 reverse seeds")


def test_the_final_sleep_screening_entry_recomputes():
    """Entry ``screening-read``: the screening's table and verdict recomputed from the six runs and their eighteen
    re-sleeps (every seed of both orders present), equal to the stored screening.json, and the entry's numbers in its
    order: per order C0's and each candidate's mean final AFSR, the difference to C0 with the seeds above it, the
    newest skill's mean change; then the verdict."""
    from experiments.final_sleep_screening import CANDIDATES, ScreeningConfig, run_screening

    results = DOCS / "results"
    cfg = ScreeningConfig(orders=[f"forward={results / 'order_mt5_screening_forward'}",
                                  f"reverse={results / 'order_mt5_screening_reverse'}"], trigger_order="reverse")
    orders, decision = run_screening(cfg)
    assert decision["missing"] == []
    stored = read_checked_json(results / "order_mt5_screening" / "screening.json")
    assert stored["decision"] == json.loads(json.dumps(decision))
    seeds = (100, 101, 102)
    numbers = []
    for o in ("reverse", "forward"):
        numbers += [f"{np.mean([orders[o]['C0'][s]['afsr'] for s in seeds]):.3f}",
                    f"{np.mean([orders[o]['C0'][s]['newest_change'] for s in seeds]):+.3f}"]
        for c in CANDIDATES:
            v = decision["candidates"][c]["orders"][o]
            assert v["seeds"] == list(seeds)
            numbers += [f"{v['mean']:.3f}", f"{v['diff']:+.3f}", f"{v['seeds_above']} of 3",
                        f"{v['newest_change']:+.3f}"]
    verdict = f"{decision['winner']} wins" if decision["winner"] else "no candidate passes"
    _states("screening-read", *numbers, verdict)
