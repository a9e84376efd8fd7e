"""sr-grid (sr_imitation.experiments.grid) on a tiny needle preset: a grid on a local Ray gives the plain loop's
results, a worker killed mid-run is retried and its run resumes to the same results, runs in the archive are never
submitted. The module's tests share one local Ray (fixture ``module_ray``), stopped after them; they run on one pytest
worker because .ci/test.sh hands each test file to one worker (``--dist loadfile``; tests/test_ci_dist.py checks it)."""

from __future__ import annotations

import json
import logging
import re
import subprocess
from pathlib import Path

import draccus
import pytest
import torch
from safetensors.torch import load_file

from sr_imitation.experiments.archive import archive_run
from sr_imitation.experiments.grid import (
    KILL_HOOK_ENV,
    LOCAL_RAY_SYSTEM_CONFIG,
    GridConfig,
    RayOptions,
    completed_phases,
    run_grid,
    substrate_of_preset,
)
from sr_imitation.experiments.mt5_compare import MT5CompareConfig
from sr_imitation.experiments.needle_compare import CompareConfig
from sr_imitation.infra.fingerprint import SettingsMismatchError
from sr_imitation.main_job import preset_with_datasets
from tests.experiments.toy_grid import TINY_NEEDLE_TRAIN

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
VARIANTS = ["sr", "wake_only"]

@pytest.fixture(scope="module")
def preset(tmp_path_factory) -> Path:
    """A two-skill state-only needle preset of a few seconds a run; its datasets recorded here, once."""
    tmp = tmp_path_factory.mktemp("grid_preset")
    config = {
        "record": {"num_episodes": 2, "root": str(tmp / "datasets"), "image_size": 32},
        "train": TINY_NEEDLE_TRAIN,
    }
    path = tmp / "preset.json"
    path.write_text(json.dumps(config))
    preset_with_datasets(path, [])
    return path


@pytest.fixture(scope="module")
def loop_runs(preset, tmp_path_factory) -> Path:
    """The reference: the grid run by the plain loop, in this process, at the Ray tasks' thread count (one, their
    ``--ray.num_cpus``): results repeat at a fixed thread count only (at 2 threads this tiny run's SPI moves by 1e-7),
    and .ci/test.sh's OMP_NUM_THREADS=1 is not there when a test is run by hand."""
    out = tmp_path_factory.mktemp("loop")
    threads = torch.get_num_threads()
    torch.set_num_threads(int(RayOptions().num_cpus))
    try:
        run_grid(GridConfig(preset=preset, variants=VARIANTS, seeds=[0], output_root=out, runner="loop"))
    finally:
        torch.set_num_threads(threads)
    return out


def _ray_processes() -> list[str]:
    ps = subprocess.run(["ps", "-eo", "pid,args"], capture_output=True, text=True, check=True).stdout
    return [line for line in ps.splitlines() if "raylet" in line or "gcs_server" in line]


@pytest.fixture(scope="module")
def module_ray():
    """One local Ray on 2 cores for the module's tests that submit to a Ray they did not start (a Ray start and stop
    is about 10 s here); stopped, with no Ray process left, after the module. The module's tests run on one pytest
    worker (.ci/test.sh: ``--dist loadfile``), so no other Ray runs beside it."""
    import ray

    assert not ray.is_initialized() and _ray_processes() == []
    yield
    ray.shutdown()
    assert _ray_processes() == []


@pytest.fixture
def local_ray(module_ray):
    """``start()`` connects the test to the module's local Ray, started on first use (a run's worker reads the kill
    hook's setting from the environment the runner passes each task, so a test may set it after the start)."""
    import ray

    def start() -> None:
        if not ray.is_initialized():
            ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False,
                     _system_config=LOCAL_RAY_SYSTEM_CONFIG)

    return start


def _assert_same_run(reference: Path, run: Path) -> None:
    """The same numbers (results.json's metrics and success) and bit-identical weights (every checkpoint, memory
    and statistics file of the run)."""
    a, b = (json.loads((r / "results.json").read_text()) for r in (reference, run))
    for key in ("metrics", "success_matrix", "success_after_own_wake", "memory_bytes", "extra"):
        assert a[key] == b[key], key
    files = sorted(p.relative_to(reference) for p in reference.rglob("*.safetensors"))
    assert files and files == sorted(p.relative_to(run) for p in run.rglob("*.safetensors"))
    assert any(f.parts[0] in ("skill_2_place", "stages") for f in files)  # the last stage's checkpoints
    for file in files:
        x, y = load_file(reference / file), load_file(run / file)
        assert x.keys() == y.keys() and all(torch.equal(x[k], y[k]) for k in x), file


@pytest.mark.slow
def test_a_killed_worker_is_retried_and_the_run_resumes_to_the_same_results(preset, loop_runs, local_ray, tmp_path,
                                                                             monkeypatch, caplog):
    marker = tmp_path / "killed"
    local_ray()  # started first: the setting reaches the run's worker through the task's environment
    monkeypatch.setenv(KILL_HOOK_ENV, f"sr_seed0:1.wake:{marker}")  # the first attempt dies after stage 1's wake
    out = tmp_path / "ray"
    with caplog.at_level(logging.INFO, logger="sr_imitation.experiments"):
        run_grid(GridConfig(preset=preset, variants=["sr"], seeds=[0], output_root=out))
    assert marker.is_file()  # the worker did die
    finished = [r.message for r in caplog.records if r.message.startswith("finished sr seed 0")]
    assert len(finished) == 1
    # the retry continued the killed run: the watcher thread kills the worker once stage 1's wake is recorded, and a
    # tiny run may record a phase or two more before the kill lands, but never all of them
    resumed = re.search(r"resumed with (\d+) phases? done", finished[0])
    assert resumed and 1 <= int(resumed.group(1)) < len(completed_phases(out / "sr_seed0")), finished[0]
    _assert_same_run(loop_runs / "sr_seed0", out / "sr_seed0")


@pytest.mark.slow
def test_runs_in_the_archive_are_not_submitted_and_a_grid_on_ray_gives_the_loops_results(preset, loop_runs, local_ray,
                                                                                           tmp_path, caplog):
    import ray

    archive = tmp_path / "archive"
    archive_run(loop_runs / "sr_seed0", archive, "sr_seed0")
    # another value of a setting is refused before anything is submitted (Ray not even needed)
    with pytest.raises(SettingsMismatchError, match=r"sr_seed0/settings_fingerprint.json.*sleep.lr"):
        run_grid(GridConfig(preset=preset, variants=VARIANTS, seeds=[0], output_root=tmp_path / "other",
                            archive=archive, extra=["--sleep.lr=0.001"]))
    assert not (tmp_path / "other").exists()
    local_ray()
    out = tmp_path / "ray"
    with caplog.at_level(logging.INFO, logger="sr_imitation.experiments"):
        summary = run_grid(GridConfig(preset=preset, variants=VARIANTS, seeds=[0], output_root=out, archive=archive))
    assert [r.message for r in caplog.records if r.message.startswith("submitted")] == [
        f"submitted wake_only seed 0 -> {out / 'wake_only_seed0'}"]
    assert not (out / "sr_seed0").exists()
    assert summary["variants"]["sr"]["runs"] == {"0": str(archive / "sr_seed0")}
    assert summary["variants"]["wake_only"]["runs"] == {"0": str(archive / "wake_only_seed0")}  # archived at once
    # the run on Ray gives the loop's results (sr's on Ray: the killed-worker test), with its own log and a line
    _assert_same_run(loop_runs / "wake_only_seed0", out / "wake_only_seed0")
    assert (out / "logs" / "wake_only_seed0.log").stat().st_size > 0  # the run's log, not the console's
    finished = [r.message for r in caplog.records if r.message.startswith("finished ")]
    assert len(finished) == 1 and "AFSR" in finished[0] and " s (" in finished[0], finished
    assert set(summary["variants"]) == set(VARIANTS) and (out / "summary.md").is_file()
    assert ray.is_initialized()  # a Ray the runner did not start is left to its owner


@pytest.mark.slow
def test_waiting_runs_start_after_theirs_and_a_failed_run_stops_only_its_own(module_ray, tmp_path, caplog):
    import ray

    from tests.experiments import toy_grid

    # the runner starts its own local Ray here, and stops it
    ray.shutdown()
    assert _ray_processes() == []
    out, archive = tmp_path / "grid", tmp_path / "archive"
    cfg = GridConfig(preset=tmp_path / "unused.json", variants=["after_a", "a", "fails", "after_fails", "b"],
                     seeds=[0], output_root=out, archive=archive, ray=RayOptions(local_cpus=2))
    with pytest.raises(RuntimeError, match=r"2 of 5 runs failed .*fails_seed0: .*toy failure; "
                                           r"after_fails_seed0: not started: fails_seed0 failed"):
        run_grid(cfg, toy_grid.GRID)
    results = {v: json.loads((out / f"{v}_seed0" / "results.json").read_text()) for v in ("a", "b", "after_a")}
    assert results["after_a"]["waited"] and results["after_a"]["start"] >= results["a"]["end"]
    # with patient health checks: on two busy cores Ray's defaults (5 misses 3 s apart) declared the raylet dead
    want = [LOCAL_RAY_SYSTEM_CONFIG[k] for k in ("health_check_period_ms", "health_check_failure_threshold")]
    assert all(r["ray_health_checks"] == want for r in results.values())
    assert sorted(p.name for p in archive.iterdir()) == ["a_seed0", "after_a_seed0", "b_seed0"]  # the others kept
    assert not (out / "after_fails_seed0").exists()
    assert "toy failure" in (out / "logs" / "fails_seed0.log").read_text()  # the traceback in the run's log
    assert not ray.is_initialized() and _ray_processes() == []  # the Ray the runner started is stopped


@pytest.mark.slow
def test_the_sac_grid_on_ray_gives_the_loops_results(local_ray, tmp_path):
    from sr_imitation.substrates.sac.config import EvalConfig
    from tests.substrates.sac.test_trainer import tiny_config

    stored = tiny_config(tmp_path / "unused", eval=EvalConfig(episodes=1, videos_per_skill=0)).stored_config()
    stored.pop("output_dir", None)
    preset = tmp_path / "sac.json"
    preset.write_text(json.dumps(stored))
    assert substrate_of_preset(preset) == "sac"
    run_grid(GridConfig(preset=preset, variants=["sr"], seeds=[0], output_root=tmp_path / "loop", runner="loop"))
    local_ray()
    run_grid(GridConfig(preset=preset, variants=["sr"], seeds=[0], output_root=tmp_path / "ray"))
    _assert_same_run(tmp_path / "loop" / "sr_seed0", tmp_path / "ray" / "sr_seed0")


def test_the_command_line_and_the_summary_on_request(loop_runs, preset, caplog):
    assert substrate_of_preset(CONFIGS / "needle_cpu.json") == "act"
    assert substrate_of_preset(CONFIGS / "sac_mt5_cpu.json") == "sac"
    assert substrate_of_preset(loop_runs / "sr_seed0" / "train_config.json") == "act"  # a run's sr-train config
    (loop_runs / "other.json").write_text(json.dumps({"policy": {"type": "act_sr"}}))
    with pytest.raises(ValueError, match="neither an sr-main preset"):
        substrate_of_preset(loop_runs / "other.json")
    cfg = draccus.parse(GridConfig, args=["--preset=p.json", "--variants=[sr,ewc]", "--seeds=[0,1]",
                                          "--ray.address=auto", "--ray.num_gpus=1", "--ray.memory_gb=4"])
    assert (cfg.runner, cfg.ray.address, cfg.ray.num_gpus, cfg.ray.num_cpus) == ("ray", "auto", 1, 1)
    # the comparison modules keep their defaults, with the loop unless asked
    assert draccus.parse(CompareConfig, args=[]).runner == "loop"
    assert draccus.parse(MT5CompareConfig, args=["--runner=ray", "--ray.num_cpus=2"]).ray.num_cpus == 2
    with pytest.raises(ValueError, match="runner: unknown"):
        GridConfig(runner="slurm")
    with pytest.raises(ValueError, match="variants: unknown"):
        run_grid(GridConfig(preset=preset, variants=["sr_typo"], output_root=loop_runs, summary_only=True))
    with caplog.at_level(logging.WARNING):
        summary = run_grid(GridConfig(preset=preset, variants=[*VARIANTS, "sequential_bc"], seeds=[0],
                                      output_root=loop_runs, summary_only=True))
    assert set(summary["variants"]) == set(VARIANTS) and "summary without sequential_bc_seed0" in caplog.text


def test_an_sr_train_config_on_your_own_datasets_is_a_grid_too(preset, loop_runs, tmp_path, capsys):
    """"Does sleep help on my skills?": an sr-train config naming its datasets by path (nothing to record) is a grid
    of the same variants, and gives the preset's runs bit for bit when it describes the same stream; the
    hypotheses command then reads its output folder."""
    from sr_imitation.experiments.hypotheses import main as hypotheses_main

    config = json.loads(preset.read_text())
    root = Path(config["record"]["root"])
    before = sorted(p.relative_to(root) for p in root.rglob("*"))
    stream = config["train"]["stream"]
    train = {**config["train"], "stream": {**stream, "dataset_paths": [str(root / s) for s in stream["skills"]]}}
    mine = tmp_path / "my_skills.json"
    mine.write_text(json.dumps(train))
    assert substrate_of_preset(mine) == "act"
    run_grid(GridConfig(preset=mine, variants=VARIANTS, seeds=[0], output_root=tmp_path / "grid", runner="loop"))
    for variant in VARIANTS:
        _assert_same_run(loop_runs / f"{variant}_seed0", tmp_path / "grid" / f"{variant}_seed0")
    assert sorted(p.relative_to(root) for p in root.rglob("*")) == before  # the user's datasets untouched
    hypotheses_main([f"--archive={tmp_path / 'grid'}", "--tests=[sr>wake_only]"])
    assert "| sr>wake_only (greater) | afsr | 0 |" in capsys.readouterr().out


def test_a_grid_without_an_evaluation_environment_reports_and_tests_validation_l1(preset, tmp_path, caplog, capsys):
    """No simulator (``--eval.env=none``): the grid logs each run's final validation l1, the summary tables it
    (paired to sr) and the hypotheses command tests it (lower is better)."""
    from sr_imitation.experiments.hypotheses import main as hypotheses_main

    config = json.loads(preset.read_text())
    root = Path(config["record"]["root"])
    train = {**config["train"], "stream": {**config["train"]["stream"], "dataset_root": str(root)},
             "eval": {"env": "none", "episodes": 0, "videos_per_skill": 0}}
    mine = tmp_path / "no_sim.json"
    mine.write_text(json.dumps(train))
    with caplog.at_level(logging.INFO):
        run_grid(GridConfig(preset=mine, variants=[*VARIANTS, "mt_joint"], seeds=[0], output_root=tmp_path / "grid",
                            runner="loop"))
    assert "finished wake_only seed 0: validation l1 " in caplog.text and "(no evaluation)" in caplog.text
    summary = (tmp_path / "grid" / "summary.md").read_text()
    assert "| variant | seeds | val_l1 | memory_loss | paired val_l1 | paired memory_loss |" in summary
    # the oracle's reference without a simulator: the joint policy's validation l1 on each skill's held-out episodes
    oracle = json.loads((tmp_path / "grid" / "mt_joint_seed0" / "results.json").read_text())
    evals = json.loads((tmp_path / "grid" / "mt_joint_seed0" / "mt_joint" / "wake" / "eval.json").read_text())
    assert oracle["losses"]["validation_l1"][-1] == [evals[s]["validation_l1"] for s in oracle["skills"]]
    assert oracle["evaluation"] == "none" and "| mt_joint | 0 | " in summary
    hypotheses_main([f"--archive={tmp_path / 'grid'}", "--tests=[sr<wake_only]", "--metric=val_l1"])
    assert "| sr<wake_only (less) | val_l1 | 0 |" in capsys.readouterr().out
