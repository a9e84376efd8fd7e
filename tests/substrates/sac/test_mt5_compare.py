"""The MT5 comparison runner: every variant's flags parse, finished runs are skipped, killed runs resume, the memory
table names the bytes each method stores (tiny preset written from the test's tiny configuration)."""

from __future__ import annotations

import json

import pytest

from sr_imitation.experiments.mt5_compare import VARIANTS, MT5CompareConfig, run_args, run_compare
from sr_imitation.reporting.summary import memory_table
from sr_imitation.stream import METHODS
from sr_imitation.substrates.sac.cli import parse
from tests.substrates.sac.test_trainer import tiny_config


@pytest.fixture
def tiny_preset(tmp_path):
    from sr_imitation.substrates.sac.config import EvalConfig

    cfg = tiny_config(tmp_path / "unused", eval=EvalConfig(episodes=1, videos_per_skill=0))
    stored = cfg.stored_config()
    stored.pop("output_dir", None)
    path = tmp_path / "tiny.json"
    path.write_text(json.dumps(stored))
    return path


def test_every_variant_parses_to_its_method_and_settings(tmp_path, tiny_preset):
    cfg = MT5CompareConfig(preset=tiny_preset, seeds=[0], variants=list(VARIANTS), output_root=tmp_path / "c")
    for variant, flags in VARIANTS.items():  # every variant's flags name a registered method (checked cheaply)
        methods = [f.split("=", 1)[1] for f in flags if f.startswith("--method=")]
        assert all(m in METHODS for m in methods), variant
    for variant in ("sr", "wake_only", "sequential", "ewc", "componet", "sr_no_exc", "sr_no_wake_exc"):
        run = parse(run_args(cfg, variant, 0))
        assert run.output_dir == tmp_path / "c" / f"{variant}_seed0" and run.seed == 0
        assert run.method == {"wake_only": "sr", "sequential": "sequential_bc"}.get(
            variant, variant if variant in ("ewc", "agem", "der", "clear", "reset_distill", "progress_compress",
                                            "nash_mtl", "pcgrad", "componet") else "sr")
        baseline = run.method not in ("sr", "componet")  # CompoNet's actor has no excitable layers at all
        assert run.excitability.enabled == (not baseline and variant != "sr_no_exc"), variant
    assert parse(run_args(cfg, "wake_only", 0)).sleep.enabled is False
    # a run killed before its first phase completed holds only its fingerprint (and config): it resumes, because a
    # fresh start would refuse the existing directory
    assert "--resume=true" not in run_args(cfg, "der", 0)
    (tmp_path / "c" / "der_seed0").mkdir(parents=True)
    (tmp_path / "c" / "der_seed0" / "settings_fingerprint.json").write_text("{}")
    assert "--resume=true" in run_args(cfg, "der", 0)
    assert parse(run_args(cfg, "sr_mean_grad", 0)).sleep.aggregator == "mean_grad"
    assert parse(run_args(cfg, "sr_mt8", 0)).stream.extend_from == tmp_path / "c" / "sr_seed0"
    # issue 59's candidates as whole runs: the screening's flags (a1..b2), c = Reset & Distill's wake + a candidate's
    from experiments.sleep_screening import CANDIDATES

    for name in ("a1", "a2", "b1", "b2"):
        assert VARIANTS[f"sr_{name}"] == CANDIDATES[name]
    a1, a2, b1, b2, c, c_b1 = (parse(run_args(cfg, v, 0)) for v in ("sr_a1", "sr_a2", "sr_b1", "sr_b2", "sr_c",
                                                                      "sr_c_b1"))
    assert a1.sleep.early_stop_tol == 0 and a2.sleep.early_stop_scale == "memory_scale"
    assert (b1.method_options, b2.method_options) == ({"expert_memory": "instead"}, {"expert_memory": "beside"})
    assert c.method_options == {"reset_wake": True} and c_b1.method_options == {"reset_wake": True,
                                                                                 "expert_memory": "instead"}
    assert parse(run_args(cfg, "sr_c_a1", 0)).sleep.early_stop_tol == 0
    assert all(r.method == "sr" and r.excitability.enabled for r in (a1, a2, b1, b2, c, c_b1))
    pw = parse(run_args(cfg, "sr_c_b1_pw", 0))  # c_b1 with Reset & Distill's plain actor in the wakes only
    assert pw.method_options == c_b1.method_options and c_b1.excitability.wake_enabled
    assert pw.excitability.enabled and pw.excitability.sleep_enabled and not pw.excitability.wake_enabled
    with pytest.raises(ValueError, match="list sr before it"):
        MT5CompareConfig(variants=["sr_mt8", "sr"])
    with pytest.raises(ValueError, match="unknown"):
        MT5CompareConfig(variants=["sr", "lwf"])


def test_the_runner_skips_finished_runs_and_writes_the_tables(tmp_path, tiny_preset, monkeypatch):
    cfg = MT5CompareConfig(preset=tiny_preset, seeds=[0], variants=["wake_only", "der"], output_root=tmp_path / "c")
    summary = run_compare(cfg)
    assert set(summary["variants"]) == {"wake_only", "der"}
    md = (tmp_path / "c" / "summary.md").read_text()
    # the paper's tables, each led by the paired baseline (here wake_only: no sr run); a table of it alone is dropped
    assert "**Continual baselines (the paper's Table 1" in md and "**Ablations" not in md
    assert md.count("| wake_only | 0 |") == 2 and md.count("| der | 0 |") == 3  # final (+ paired), per run
    table = (tmp_path / "c" / "memory.md").read_text()
    assert "| wake_only | 0.00 | nothing | - |" in table
    assert "| der | " in table and "inputs (states or observations) + the policy's outputs on them" in table
    assert (tmp_path / "c" / "dynamics.png").stat().st_size > 0 and (tmp_path / "c" / "summary.png").is_file()
    curve = summary["variants"]["der"]["curves"]["afsr"]
    assert len(curve["mean"]) == 2 and curve["mean"][-1] == summary["variants"]["der"]["afsr"]["mean"]
    from sr_imitation.substrates.sac import cli

    monkeypatch.setattr(cli, "train", lambda cfg: pytest.fail(f"{cfg.output_dir} was re-run"))
    run_compare(cfg)  # everything finished: nothing runs again
    row = {"memory_bytes_total": {"mean": 2_000_000}, "memory_kinds": {"sac_critic": 2_000_000}}
    assert ("| sr | 2.00 | states + the frozen twin critic + the observation normalizer's snapshot (2.00) | 3.7 |"
            in memory_table({"variants": {"sr": row}}, {"sr": 3.7}))
    # results.json carries each kind's words (the summary imports no substrate); a kind's own words win
    assert summary["variants"]["der"]["memory_contents"] == {
        "output_distillation": "inputs (states or observations) + the policy's outputs on them"}
    new_kind = {"memory_bytes_total": {"mean": 1_000_000}, "memory_kinds": {"prototypes": 1_000_000},
                "memory_contents": {"prototypes": "one mean feature per class"}}
    assert "| x | 1.00 | one mean feature per class (1.00) | - |" in memory_table({"variants": {"x": new_kind}})
    legacy = {"memory_bytes_total": {"mean": 3_916_600}, "memory_kinds": None}  # results.json of older code
    assert "| sr | 3.92 | not recorded (the run predates per-kind memory accounting) | 3.7 |" in memory_table(
        {"variants": {"sr": legacy}}, {"sr": 3.7})


def test_the_archive_keeps_finished_runs_and_refuses_other_settings(tmp_path, tiny_preset, monkeypatch):
    from sr_imitation.experiments.archive import ARCHIVED_FILES
    from sr_imitation.infra.fingerprint import SettingsMismatchError
    from sr_imitation.substrates.sac import cli

    archive = tmp_path / "archive"
    cfg = MT5CompareConfig(preset=tiny_preset, seeds=[0], variants=["wake_only"], output_root=tmp_path / "a",
                           archive=archive)
    first = run_compare(cfg)
    kept = archive / "wake_only_seed0"
    # a finished run is copied at once: its report files, no checkpoints, no temporary folder left
    assert {p.name for p in kept.iterdir()} <= set(ARCHIVED_FILES) and (kept / "results.json").is_file()
    assert any((tmp_path / "a" / "wake_only_seed0").rglob("*.safetensors"))
    assert not any(kept.rglob("*.safetensors")) and [p.name for p in archive.iterdir()] == ["wake_only_seed0"]
    # a new session's scratch folder is empty: the archived run is skipped and summarized from the archive
    monkeypatch.setattr(cli, "train", lambda c: pytest.fail(f"{c.output_dir} was re-run"))
    again = run_compare(MT5CompareConfig(preset=tiny_preset, seeds=[0], variants=["wake_only"],
                                         output_root=tmp_path / "b", archive=archive))
    assert again["variants"]["wake_only"]["afsr"]["per_seed"] == first["variants"]["wake_only"]["afsr"]["per_seed"]
    assert again["variants"]["wake_only"]["runs"] == {"0": str(kept)}
    # the same run name under other settings is refused, naming the archived file and the key, before any run
    other = MT5CompareConfig(preset=tiny_preset, seeds=[0], variants=["wake_only"], output_root=tmp_path / "c",
                             archive=archive, extra=["--sac.batch_size=7"])
    with pytest.raises(SettingsMismatchError, match=r"wake_only_seed0/settings_fingerprint.json.*sac.batch_size"):
        run_compare(other)
    assert not (tmp_path / "c").exists()


def test_mt8_refuses_to_continue_an_archived_run_without_its_checkpoints(tmp_path, tiny_preset):
    archive = tmp_path / "archive"
    run_compare(MT5CompareConfig(preset=tiny_preset, seeds=[0], variants=["sr"], output_root=tmp_path / "a",
                                 archive=archive))
    later = MT5CompareConfig(preset=tiny_preset, seeds=[0], variants=["sr", "sr_mt8"], output_root=tmp_path / "b",
                             archive=archive)
    with pytest.raises(FileNotFoundError, match=r"sr_seed0: sr_mt8 seed 0 continues this sr run.*no checkpoints"):
        run_compare(later)
    assert not (tmp_path / "b").exists()  # refused before anything ran or was written


def test_the_memory_table_describes_critic_memories_when_every_run_is_archived():
    # a fresh interpreter with only the driver's own imports, as when every run is skipped from the archive
    import subprocess
    import sys

    script = """
import sr_imitation.experiments.mt5_compare as m
from sr_imitation.reporting.summary import memory_table
m.load_groups = lambda runs: {"agem": {}}
m.summary_of = lambda groups, baseline: {"variants": {"agem": {
    "memory_bytes_total": {"mean": 1e6}, "memory_kinds": {"sac_critic": 1000000}}}}
m.write_summary = lambda output, summary, paper, sections: print(memory_table(summary, paper))
m.summarize({}, None)
"""
    table = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True).stdout
    assert "| agem | 1.00 | states + the frozen twin critic" in table
