"""The shared results schema and the multi-run summary (substrate-free)."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from sr_imitation.infra.cli_errors import run_cli
from sr_imitation.infra.provenance import process_code_version
from sr_imitation.io import CorruptFileError, read_checked_json, write_checked_json
from sr_imitation.reporting.results import (
    RESULTS_VERSION,
    SEALED_SINCE,
    build_results,
    load_results,
    render_markdown,
    upgrade_results,
    write_results,
)
from sr_imitation.reporting.summary import (
    group_runs,
    load_groups,
    main,
    phase_seconds,
    section_figures,
    summarize,
    write_summary,
)
from sr_imitation.reporting.summary import render_markdown as render_markdown_summary

DOCS = Path(__file__).resolve().parents[2] / "docs" / "results"
N = np.nan
SKILLS = ["a", "b", "c"]


def _results(seed: int = 0, method: str = "sr", sleep: bool = True, shift: float = 0.0, **kw) -> dict:
    s = np.array([[[0.8, N, N], [0.6, 0.9, N], [0.5, 0.7, 1.0]],
                  [[1.0, N, N], [0.8, 0.7, N], [0.7, 0.5, 0.8]]]) + shift
    wake = np.array([[0.9, 1.0, 1.0], [0.9, 0.8, 0.8]]) + shift
    spi = np.array([[N, 0.9, 0.8], [N, 0.7, 0.6]])
    args = dict(substrate="toy", method=method, sleep_enabled=sleep, seed=seed, skills=SKILLS,
                pairs=[("a", "b"), ("b", "c")], success=s, after_wake=wake, spi=spi, spi_features=[0, 1],
                memory_bytes={"a": 10, "b": 20}, stages=[{}, {}, {}], config={"eval": {"episodes": 5}})
    args.update(kw)
    return build_results(**args)


def test_metrics_are_per_unit_then_mean_and_se():
    r = _results()
    m = r["metrics"]
    # AFSR per unit: (0.5 + 0.7 + 1.0) / 3 and (0.7 + 0.5 + 0.8) / 3; mean and SE over the two units
    units = [(0.5 + 0.7 + 1.0) / 3, (0.7 + 0.5 + 0.8) / 3]
    assert m["afsr"]["final_per_unit"] == pytest.approx(units)
    assert m["afsr"]["final"] == pytest.approx(np.mean(units))
    assert m["afsr"]["final_sem"] == pytest.approx(np.std(units, ddof=1) / math.sqrt(2))
    # BWT against S[i][i] after stage i; BWT_wake against the after-own-wake success
    bwt = [((0.5 - 0.8) + (0.7 - 0.9)) / 2, ((0.7 - 1.0) + (0.5 - 0.7)) / 2]
    bwt_wake = [((0.5 - 0.9) + (0.7 - 1.0)) / 2, ((0.7 - 0.9) + (0.5 - 0.8)) / 2]
    assert m["bwt"]["final_per_unit"] == pytest.approx(bwt)
    assert m["bwt_wake"]["final_per_unit"] == pytest.approx(bwt_wake)
    assert m["spi"]["final"] == pytest.approx(0.7) and m["spi"]["curve"][0] is None
    assert m["prs"]["curve"][0] is None  # no pair before stage 2
    assert r["success_matrix"][2] == pytest.approx([0.6, 0.6, 0.9]) and r["success_matrix"][0][1] is None
    assert (r["results_version"], r["label"], r["memory_bytes_total"]) == (RESULTS_VERSION, "sr", 30)
    assert "NaN" not in json.dumps(r)


def test_labels_and_an_unmeasured_after_wake_reference():
    assert _results(method="sr", sleep=False)["label"] == "wake_only"
    assert _results(method="sequential_bc", sleep=False)["label"] == "sequential_bc"
    wake = np.array([[0.9, N, 1.0], [0.9, N, 0.8]])  # skill b's after-wake success was not measured
    r = _results(after_wake=wake)
    assert r["metrics"]["bwt_wake"]["final"] is None and r["metrics"]["bwt"]["final"] is not None


def test_results_md_says_why_prs_is_not_available():
    """A pair list with no pair of the stream's skills (the default ``surgicai`` on Meta-World skills) leaves PRS n/a;
    results.md says so and names the flag, instead of a bare "n/a"; with pairs there is no such line."""
    assert "PRS is n/a" not in render_markdown(_results())
    r = _results(pairs=[], config={"eval": {"episodes": 5}, "stream": {"pairs": "surgicai"}})
    assert r["metrics"]["prs"]["final"] is None
    assert ("PRS is n/a: the pair list (--stream.pairs=surgicai) holds no pair of this stream's skills; "
            "--stream.pairs=mt5") in render_markdown(r)


def test_written_files_agree(tmp_path):
    r = _results()
    write_results(tmp_path, r)
    assert read_checked_json(tmp_path / "results.json") == r
    md = (tmp_path / "results.md").read_text()
    assert md == render_markdown(r) and f"{r['metrics']['afsr']['final']:.3f}" in md
    assert (tmp_path / "metrics.png").stat().st_size > 1000 and (tmp_path / "success_matrix.png").stat().st_size > 1000


def _write_run(root: Path, name: str, results: dict) -> Path:
    run = root / name
    run.mkdir()
    write_checked_json(run / "results.json", results)
    return run


def test_summary_mean_se_over_seeds_and_paired_differences(tmp_path):
    runs = [_write_run(tmp_path, f"sr{s}", _results(seed=s, shift=-0.05 * s)) for s in (0, 1)]
    runs += [_write_run(tmp_path, f"wo{s}", _results(seed=s, sleep=False, shift=-0.1)) for s in (0, 1)]
    groups = group_runs(runs)
    assert set(groups) == {"sr", "wake_only"}
    summary = summarize(groups)
    sr = summary["variants"]["sr"]
    finals = [groups["sr"][s]["metrics"]["afsr"]["final"] for s in ("0", "1")]
    assert sr["afsr"]["per_seed"] == pytest.approx(finals) and sr["afsr"]["mean"] == pytest.approx(np.mean(finals))
    diffs = summary["paired"]["sr"]["afsr"]["per_seed"]
    assert diffs == pytest.approx([finals[0] - groups["wake_only"]["0"]["metrics"]["afsr"]["final"],
                                   finals[1] - groups["wake_only"]["1"]["metrics"]["afsr"]["final"]])
    assert diffs == pytest.approx([0.1, 0.05])  # shifts are additive in AFSR
    write_summary(tmp_path / "out", summary)
    assert (tmp_path / "out" / "summary.png").stat().st_size > 1000
    assert "| sr | 0,1 |" in (tmp_path / "out" / "summary.md").read_text()
    # each run names the commit that wrote it (results.json "code"); runs from before that show "-"
    assert groups["sr"]["0"]["code"] == process_code_version()
    old = {**_results(seed=0), "code": {"commit": "0123456789abcdef" * 2 + "01234567", "dirty": True}}
    md = render_markdown_summary(summarize(group_runs([_write_run(tmp_path, "old", {
        k: v for k, v in _results(seed=1).items() if k != "code"}), _write_run(tmp_path, "dirty", old)])))
    rows = {line.split(" | ")[1]: line for line in md.splitlines() if line.startswith("| sr | ")
            and ("/old" in line or "/dirty" in line)}
    assert rows["0"].endswith(" | 0123456 (dirty) |") and rows["1"].endswith(" | - | - |")  # time, commit
    # NAME=DIR names a variant (ablations share their method's label); a duplicate variant/seed is refused
    named = group_runs([f"no_anchor={runs[0]}", runs[1]])
    assert set(named) == {"no_anchor", "sr"}
    with pytest.raises(ValueError, match="second sr run with seed 0"):
        group_runs([runs[0], _write_run(tmp_path, "again", _results(seed=0))])


def test_summary_of_runs_without_evaluation_reports_their_final_losses(tmp_path):
    """--eval.env=none: no success to average, so the summary shows each variant's final validation l1 and memory
    loss (mean over skills of the last row of ``losses``), mean +- SE over seeds and paired to the baseline."""
    def run(name: str, seed: int, last_l1: list[float], last_memory: list[float | None]) -> Path:
        losses = {"validation_l1": [[0.1, N, N], [0.2, 0.1, N], last_l1],
                  "memory_loss": [[0.0, N, N], [0.01, 0.0, N], last_memory]}
        return _write_run(tmp_path, name, _results(seed=seed, sleep=name.startswith("sr"), success=None,
                                                   after_wake=None, spi=None, evaluation="none", losses=losses))

    runs = [run("sr0", 0, [0.3, 0.2, 0.1], [0.02, 0.01, None]), run("sr1", 1, [0.3, 0.3, 0.3], [0.03, 0.01, None]),
            run("wo0", 0, [0.6, 0.3, 0.3], [0.05, 0.03, None]), run("wo1", 1, [0.5, 0.4, 0.3], [0.04, 0.02, None])]
    summary = summarize(group_runs(runs), "sr")
    sr, wo = summary["variants"]["sr"]["offline"], summary["variants"]["wake_only"]["offline"]
    assert sr["val_l1"]["per_seed"] == pytest.approx([0.2, 0.3]) and wo["val_l1"]["mean"] == pytest.approx(0.4)
    assert sr["memory_loss"]["per_seed"] == pytest.approx([0.015, 0.02])  # the skill without a memory left out
    assert summary["paired"]["wake_only"]["val_l1"]["per_seed"] == pytest.approx([0.2, 0.1])
    md = render_markdown_summary(summary)
    assert "| wake_only | 0,1 | 0.400 +- 0.000 | 0.035 +- 0.005 | 0.150 +- 0.050 | 0.018 +- 0.008 |" in md
    evaluated = render_markdown_summary(summarize(group_runs([_write_run(tmp_path, "e", _results(seed=0))])))
    assert "without closed-loop evaluation" not in evaluated  # evaluated runs: no such table


def test_summary_of_streams_with_other_skills_or_order(tmp_path):
    """Reverse and longer streams (MT5 reversed, MT8) share one summary: per-skill cells by name, '-' elsewhere."""
    runs = [_write_run(tmp_path, "fwd", _results(seed=0)),
            _write_run(tmp_path, "rev", _results(seed=0, skills=["c", "b", "a"], pairs=[("c", "b"), ("b", "a")])),
            _write_run(tmp_path, "other", _results(seed=0, skills=["a", "b", "d"], pairs=[("a", "b"), ("b", "d")]))]
    summary = summarize(group_runs([f"sr={runs[0]}", f"sr_reverse={runs[1]}", f"sr_long={runs[2]}"]), "sr")
    assert summary["skills"] == ["a", "b", "c", "d"]
    rev = summary["variants"]["sr_reverse"]
    assert rev["skills"] == ["c", "b", "a"] and rev["final_success"]["c"]["mean"] == pytest.approx(
        summary["variants"]["sr"]["final_success"]["a"]["mean"])  # same matrix, skills renamed: by name
    md = render_markdown_summary(summary)
    assert "| sr_long | 0.600 | 0.600 | - | 0.900 |" in md and "not in the variant's stream" in md
    assert "| sr | 0.600 | 0.600 | 0.900 | - |" in md
    write_summary(tmp_path / "out", summary)
    assert (tmp_path / "out" / "summary.png").stat().st_size > 1000
    assert "not in the variant's stream" not in render_markdown_summary(summarize(group_runs(runs[:1])))
    # sections: one table per section, each with the baseline's row first; unplaced variants last; empty ones dropped
    md = render_markdown_summary(summary, {"Streams": ["sr_reverse"], "Empty": ["nothing"]})
    streams, other = md.index("**Streams**"), md.index("**Other variants**")
    assert "**Empty**" not in md and streams < other < md.index("| sr_long | 0 |")
    assert md.index("| sr | 0 |", streams) < md.index("| sr_reverse | 0 |", streams) < other
    assert md.index("| sr | 0 |", other) < md.index("| sr_long | 0 |", other)
    assert md.count("| sr_reverse | 0 |") == 3  # final row, paired difference, per-run row: not again under Other
    # figures per section as well: the baseline and the section's variants, over their skills only
    sections = {"Streams (order)": ["sr_reverse"], "Empty": ["nothing"], "All": ["sr_reverse", "sr_long"]}
    parts = section_figures(summary, sections)
    assert list(parts) == ["streams"]  # Empty has no runs; All would repeat the whole summary
    assert list(parts["streams"]["variants"]) == ["sr", "sr_reverse"] and parts["streams"]["skills"] == ["a", "b", "c"]
    write_summary(tmp_path / "parts", summary, sections=sections)
    assert sorted(p.name for p in (tmp_path / "parts").glob("*.png")) == [
        "dynamics.png", "dynamics_streams.png", "summary.png", "summary_streams.png"]
    assert "sr_reverse" in summary["paired"] and "sr_long" not in summary["paired"]  # other skills: nothing paired


def test_summary_reports_each_runs_phase_time(tmp_path):
    timed = _write_run(tmp_path, "timed", _results(seed=0))
    write_checked_json(timed / "progress.json", {"version": 1, "completed": {
        "1.wake": {"seconds": 90.0, "steps": 10}, "1.wake.eval": {"seconds": 30}, "2.memory": {"bytes": 5}}})
    untimed = _write_run(tmp_path, "untimed", _results(seed=1))
    assert phase_seconds(timed) == 120.0 and phase_seconds(untimed) is None
    # a SAC wake resumed from its snapshot: the phase's time counts from the resume, the wake's own record from its
    # start (SR seed 0 of the SAC gate's follow-up: 1060 s and 2565 s); the larger is the wake's compute time
    resumed = _write_run(tmp_path, "resumed", _results(seed=2))
    write_checked_json(resumed / "progress.json", {"version": 1, "completed": {
        "2.wake": {"seconds": 1060.0, "wake": {"seconds": 2565.0, "episodes": 800}},
        "2.wake.eval": {"seconds": 5.0}, "3.wake": {"seconds": 100.0, "wake": {"seconds": 99.5}}}})
    assert phase_seconds(resumed) == 2565.0 + 5.0 + 100.0
    summary = summarize(group_runs([timed, untimed]))
    assert summary["variants"]["sr"]["phase_seconds"] == {"0": 120.0, "1": None}
    md = render_markdown_summary(summary)
    assert f"| {timed} | " in md and " | 2.0 |" in md and " | - |" in md and "All runs above: 0.03 h." in md
    # the experiment drivers' path (load_groups) names the run and times it too
    assert summarize(load_groups({"sr": {"0": timed}}))["variants"]["sr"]["runs"] == {"0": str(timed)}


def test_a_results_file_without_its_seal_is_refused_unless_its_schema_predates_seals(tmp_path):
    """A file whose ``sha256`` key is renamed and whose AFSR (or BWT, either reference) is edited is not read as the
    run's result. Whether a file may lack its seal is decided by its recorded schema version, never by the missing
    key; such runs are marked unsealed."""
    run = _write_run(tmp_path, "run", _results())
    data = json.loads((run / "results.json").read_text())
    assert data["results_version"] == RESULTS_VERSION >= SEALED_SINCE and not load_results(run)["unsealed"]
    data["sha_256"] = data.pop("sha256")
    data["metrics"]["afsr"]["final"] = 0.999
    (run / "results.json").write_text(json.dumps(data))
    with pytest.raises(CorruptFileError, match=r"run/results.json: has no sha256"):
        load_results(run)
    with pytest.raises(SystemExit, match="2"):  # the command: one line naming the file, exit status 2
        run_cli("sr_imitation.reporting.summary", main, [str(run), f"--output={tmp_path / 'summary'}"])
    old = {k: v for k, v in data.items() if k != "sha_256"} | {"results_version": 4}  # claims a schema before seals
    (run / "results.json").write_text(json.dumps(old))  # ... with the edited AFSR: not what that schema wrote
    with pytest.raises(CorruptFileError, match=r"results.json: unsealed \(results_version 4\) and its final AFSR"):
        load_results(run)
    old["metrics"]["afsr"]["final"] = _results()["metrics"]["afsr"]["final"]  # as written before seals
    for name, edit in (("bwt", ("final",)), ("bwt_wake", ("curve", 1))):  # an edited BWT is refused too
        edited = json.loads(json.dumps(old))
        target = edited["metrics"][name]
        if edit[0] == "final":
            target["final"] += 0.01
        else:
            target["curve"][edit[1]] += 0.01
        (run / "results.json").write_text(json.dumps(edited))
        where = "final " + name if edit[0] == "final" else f"{name} after stage 2"
        with pytest.raises(CorruptFileError, match=rf"unsealed \(results_version 4\) and its {where}"):
            load_results(run)
    (run / "results.json").write_text(json.dumps(old))
    assert load_results(run)["unsealed"]
    summary = summarize(load_groups({"sr": {"0": run}}))
    assert summary["variants"]["sr"]["unsealed"] == {"0": True}
    write_summary(tmp_path / "s", summary)
    md = (tmp_path / "s" / "summary.md").read_text()
    assert "Unsealed: sr seed 0" in md and "| sr | 0* |" in md  # marked in its rows, not only below the tables


def test_unknown_versions_and_missing_files_are_named(tmp_path):
    run = _write_run(tmp_path, "future", {**_results(), "results_version": 99})
    with pytest.raises(ValueError, match="future/results.json: results_version 99"):
        load_results(run)
    with pytest.raises(FileNotFoundError, match="unfinished run"):
        load_results(tmp_path / "nowhere")


@pytest.mark.parametrize("run, label, substrate", [
    ("needle_cpu_compare/sr_seed0", "sr", "act"),                 # ACT, unversioned (FW-5 era)
    ("needle_cpu_compare/wake_only_seed1", "wake_only", "act"),
    ("needle_cpu_compare_exact/sr_seed0", "sr", "act"),           # ACT schema 2
    ("sac_mt5_cpu/sleep_s0", "sr", "sac"),                        # SAC, unversioned
    ("sac_mt5_cpu/wake_s0", "wake_only", "sac"),
])
def test_the_committed_raw_results_of_older_schemas_are_read(run, label, substrate):
    raw = json.loads((DOCS / run / "results.json").read_text())
    r = load_results(DOCS / run)
    assert (r["label"], r["substrate"]) == (label, substrate)
    old = raw["metrics"]["afsr"]
    assert r["metrics"]["afsr"]["final"] == pytest.approx(old["final_mean"] if isinstance(old, dict) else old)
    if substrate == "sac" and label == "wake_only":  # bwt_wake = bwt for wake-only (same policy)
        assert r["metrics"]["bwt_wake"]["final"] == raw["metrics"]["bwt"]
    assert upgrade_results(r) == r


def test_summary_command_over_the_committed_needle_runs(tmp_path, capsys):
    runs = [str(DOCS / "needle_cpu_compare" / f"{v}_seed{s}") for v in ("sr", "wake_only") for s in (0, 1, 2)]
    main([*runs, f"--output={tmp_path}"])
    out = capsys.readouterr().out
    saved = json.loads((tmp_path / "summary.json").read_text())
    old = json.loads((DOCS / "needle_cpu_compare" / "summary.json").read_text())["summary"]
    for variant in ("sr", "wake_only"):  # the same numbers the old per-driver summary wrote
        for m in ("afsr", "prs", "bwt"):
            assert saved["variants"][variant][m]["mean"] == pytest.approx(old[variant][m]["mean"]), (variant, m)
    assert "Paired difference variant - wake_only" in out


def test_results_md_states_the_binomial_noise_of_a_success_cell():
    from sr_imitation.reporting.results import render_markdown

    md = render_markdown(_results())  # config: 5 episodes per unit, two units: 10 episodes per cell
    assert "A success cell pools 10 episodes (5 per evaluation unit): its binomial SE is up to 0.158" in md
    assert "pools" not in render_markdown(_results(config={}))  # unknown episode count: nothing claimed


def test_summary_states_the_binomial_noise_of_one_seed_s_per_skill_success(tmp_path):
    runs = [_write_run(tmp_path, f"sr{s}", _results(seed=s)) for s in (0, 1)]
    runs += [_write_run(tmp_path, "wo0", _results(seed=0, sleep=False, config={"eval": {"episodes": 50}}))]
    summary = summarize(group_runs(runs))
    assert summary["variants"]["sr"]["episodes_per_cell"] == [10]  # 5 episodes x 2 evaluation units
    md = render_markdown_summary(summary)
    assert "a rate over 10 episodes (binomial SE up to 0.158 at 0.5 success): sr" in md
    assert "100 episodes (binomial SE up to 0.050 at 0.5 success): wake_only" in md
    alone = render_markdown_summary(summarize(group_runs(runs[:2])))
    assert "a rate over 10 episodes (binomial SE up to 0.158 at 0.5 success). The SE" in alone
    unknown = render_markdown_summary(summarize(group_runs([_write_run(tmp_path, "u", _results(config={}))])))
    assert "Evaluation noise" not in unknown  # unknown episode count: nothing claimed


def test_an_unsealed_file_of_another_schema_relabelled_older_is_one_line_in_every_reader(tmp_path, capsys):
    """A current file without its seal and with ``results_version: 3`` (whose metrics are bare numbers) is refused
    naming the file by status, compare and summary. Before: ``TypeError: float() argument must be ... not 'dict'``
    with a traceback in all three."""
    from sr_imitation.reporting import compare, status
    from sr_imitation.stream.rundir import PROGRESS_FILE

    run = _write_run(tmp_path, "run", _results())
    write_checked_json(run / PROGRESS_FILE, {"version": 2, "completed": {"1.wake": {"seconds": 1.0}}})
    data = {k: v for k, v in json.loads((run / "results.json").read_text()).items() if k != "sha256"}
    (run / "results.json").write_text(json.dumps(data | {"results_version": 3}))
    expected = "results.json: unsealed (results_version 3) and does not read as its schema (metrics.afsr.final is dict"
    with pytest.raises(CorruptFileError, match=re.escape(expected)):
        load_results(run)
    for prog, command, args in (("summary", main, [str(run)]), ("compare", compare.main, [str(run), str(run)])):
        with pytest.raises(SystemExit) as exc:
            run_cli(f"sr_imitation.reporting.{prog}", command, args)
        err = capsys.readouterr().err
        assert exc.value.code == 2 and err.count("\n") == 1 and f"{run / 'results.json'}: unsealed" in err, prog
    row = status.run_status(run)  # status shows the run, its result not trusted
    assert row["final"].startswith("results.json not trusted (unsealed (results_version 3)")


def test_summary_refuses_a_run_whose_train_config_was_edited(tmp_path, capsys):
    """As a resume does: an edited sealed ``train_config.json``, or an unsealed one that differs from the run's
    fingerprint, is one line naming it. Before: a normal table."""
    from sr_imitation.infra.fingerprint import FINGERPRINT_FILE, settings_fingerprint, write_fingerprint

    run = _write_run(tmp_path, "run", _results())
    config = {"method": "sr", "seed": 0, "sleep": {"enabled": True}, "output_dir": "."}
    write_fingerprint(run / FINGERPRINT_FILE, settings_fingerprint(config, ("output_dir",)))
    write_checked_json(run / "train_config.json", config)
    assert summarize(group_runs([run]))["variants"]["sr"]["runs"] == {"0": str(run)}
    path = run / "train_config.json"
    sealed = path.read_text()
    edits = {"contents do not match its sha256": sealed.replace('"seed": 0', '"seed": 1'),
             "differs from settings_fingerprint.json in seed": json.dumps(config | {"seed": 1})}  # unsealed
    for problem, text in edits.items():
        path.write_text(text)
        with pytest.raises(CorruptFileError, match=re.escape(f"{path}: {problem}")):
            group_runs([run])
        with pytest.raises(SystemExit) as exc:
            run_cli("sr_imitation.reporting.summary", main, [str(run)])
        err = capsys.readouterr().err
        assert exc.value.code == 2 and err.count("\n") == 1 and f"{path}: {problem}" in err
