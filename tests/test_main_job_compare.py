"""The main job's comparison (SR beside wake-only, both at once; comparison.png and results.md), its resume, sr-grid's
``processes`` runner under it, and .ci/main.sh's choice between the comparison and the single-run sr-main."""

from __future__ import annotations

import dataclasses
import json
import logging
import re
import shutil
import subprocess
from pathlib import Path

import pytest

from sr_imitation.experiments.grid import KILL_HOOK_ENV, GridConfig, run_grid
from sr_imitation.experiments.main_compare import DEFAULT_PRESET, MainCompareConfig, main, run_dirs
from sr_imitation.experiments.needle_compare import run_config
from sr_imitation.substrates.act.cli import parse_config
from tests.experiments.toy_grid import TINY_NEEDLE_TRAIN, ToyGrid

REPO = Path(__file__).resolve().parents[1]
TINY = {
    "record": {"num_episodes": 2, "image_size": 32},
    "train": {**TINY_NEEDLE_TRAIN, "seed": 0,
              "wake": {"max_epochs": 1, "min_epochs": 1, "batch_size": 8, "max_steps_per_epoch": 2}},
    "expert_video": False,
}
"""A two-skill state-only needle preset of seconds a run."""


@pytest.fixture(scope="module")
def job(tmp_path_factory):
    """The comparison on the tiny preset, interrupted (wake_only's process killed after stage 1's wake, sr finished
    beside it), refused without --train.resume=true, then resumed; what each step left is returned."""
    tmp = tmp_path_factory.mktemp("main_compare")
    preset = tmp / "preset.json"
    preset.write_text(json.dumps({**TINY, "record": {**TINY["record"], "root": str(tmp / "datasets")}}))
    out = tmp / "job"
    args = [f"--config_path={preset}", f"--output_dir={out}"]
    marker = tmp / "killed"
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("HF_HOME", str(tmp / "hf"))  # caches inside the test's folder (the runs' processes inherit it)
        mp.setenv(KILL_HOOK_ENV, f"wake_only_seed0:1.wake:{marker}")  # the first attempt dies after stage 1's wake
        with pytest.raises(RuntimeError, match=r"1 of 2 runs failed.*wake_only_seed0: its process ended with status 1"):
            main(args)
        interrupted = {"killed": marker.is_file(), "sr_results": (out / "sr_seed0" / "results.json").read_bytes(),
                       "sr_progress": (out / "sr_seed0" / "progress.json").stat().st_mtime_ns,
                       "wake_only_phases": list(json.loads((out / "wake_only_seed0" / "progress.json").read_text())
                                                ["completed"]),
                       "figure": (out / "comparison.png").exists()}
        with pytest.raises(FileExistsError, match="--train.resume=true continues this comparison"):
            main(args)
        logger = logging.getLogger("sr_imitation.experiments.grid")
        records: list[logging.LogRecord] = []
        handler = logging.Handler()
        handler.emit = records.append  # type: ignore[method-assign]
        logger.addHandler(handler)
        try:
            main([*args, "--train.resume=true"])
        finally:
            logger.removeHandler(handler)
    return {"out": out, "preset": preset, "interrupted": interrupted, "log": [r.getMessage() for r in records]}


def _table(markdown: str) -> dict[str, list[str]]:
    """results.md's first table: run -> its cells after the name."""
    rows = [line for line in markdown.splitlines() if line.startswith("| ") and "AFSR after each stage" not in line]
    cells = [[c.strip() for c in row.strip().strip("|").split("|")] for row in rows]
    return {c[0]: c[1:] for c in cells if c[0] in ("sr", "wake_only") and len(c) == 4}


def test_the_comparison_writes_both_runs_a_figure_and_results_md_with_the_runs_numbers(job):
    out = job["out"]
    results = {v: json.loads((out / f"{v}_seed0" / "results.json").read_text()) for v in ("sr", "wake_only")}
    for variant, res in results.items():
        assert res["skills"] == ["approach", "place"] and len(res["success_matrix"]) == 2, variant
        assert (out / "logs" / f"{variant}_seed0.log").stat().st_size > 0
    # the same preset, only sleep differs (needle_compare's VARIANTS), each at one torch thread
    configs = {v: json.loads((out / f"{v}_seed0" / "train_config.json").read_text()) for v in results}
    assert configs["sr"]["sleep"]["enabled"] and not configs["wake_only"]["sleep"]["enabled"]
    assert configs["sr"]["torch_threads"] == configs["wake_only"]["torch_threads"] == 1
    sleeps = {v: [p for p in json.loads((out / f"{v}_seed0" / "progress.json").read_text())["completed"]
                  if p.endswith(".sleep")] for v in results}
    assert sleeps == {"sr": ["2.sleep"], "wake_only": []}
    assert (out / "comparison.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    md = (out / "results.md").read_text()
    finals = {v: res["metrics"]["afsr"]["final"] for v, res in results.items()}
    table = _table(md)
    for variant, res in results.items():
        assert table[variant][0] == f"{finals[variant]:.3f}", md
        assert table[variant][1] == ", ".join(f"{x:.3f}" for x in res["metrics"]["afsr"]["curve"]), md
    diff = round(finals["sr"] - finals["wake_only"], 3)
    assert f"sr ends at AFSR {finals['sr']:.3f}, wake_only at {finals['wake_only']:.3f}" in md
    assert f"(difference sr - wake_only = {diff:+.3f})" in md
    assert "illustration, not evidence" in md and "Which method where" in md and "docs/RESULTS.md" in md


def test_a_resumed_comparison_continues_only_the_unfinished_run(job):
    before = job["interrupted"]
    out = job["out"]
    assert before["killed"] and not before["figure"]  # the interrupted job wrote no comparison
    # killed once stage 1's wake is recorded (the kill hook watches from another thread: its memory may be recorded too)
    assert "1.wake" in before["wake_only_phases"] and set(before["wake_only_phases"]) <= {"1.wake", "1.memory"}
    # sr had finished: skipped, not touched; wake_only resumed from its recorded phases
    assert (out / "sr_seed0" / "results.json").read_bytes() == before["sr_results"]
    assert (out / "sr_seed0" / "progress.json").stat().st_mtime_ns == before["sr_progress"]
    assert any("1 finished in" in line and "1 to run" in line for line in job["log"]), job["log"]
    finished = [line for line in job["log"] if line.startswith("finished ")]
    assert len(finished) == 1 and finished[0].startswith("finished wake_only seed 0")
    done = len(before["wake_only_phases"])
    assert f"resumed with {done} phase{'s' if done > 1 else ''} done" in finished[0], finished[0]


def test_the_job_s_flags_and_defaults(job, tmp_path):
    """The default preset is the small-memory one; two different variants only; train.overwrite is refused; the
    wake_only run is needle_compare's variant (sleep off, nothing else changed)."""
    cfg = parse_config(MainCompareConfig, str(REPO / DEFAULT_PRESET), [], prog="x")
    assert cfg.train.memory.buffer_size == 16 and cfg.variants == ["sr", "wake_only"]
    assert cfg.output_dir == Path("outputs/needle_main")
    assert run_dirs(cfg) == {"sr": Path("outputs/needle_main/sr_seed1000"),
                             "wake_only": Path("outputs/needle_main/wake_only_seed1000")}
    grid = GridConfig(output_root=tmp_path)
    sr, wake = (dataclasses.asdict(run_config(grid, cfg, v, 1000)) for v in ("sr", "wake_only"))
    assert sr["sleep"].pop("enabled") and not wake["sleep"].pop("enabled")
    assert {k: v for k, v in sr.items() if k != "output_dir"} == {k: v for k, v in wake.items() if k != "output_dir"}
    with pytest.raises(ValueError, match="variants: give two different ones"):
        MainCompareConfig(variants=["sr"])
    with pytest.raises(ValueError, match="variants: unknown"):
        MainCompareConfig(variants=["sr", "wake_onyl"])
    with pytest.raises(ValueError, match="train.overwrite: this job never overwrites"):
        main([f"--config_path={job['preset']}", f"--output_dir={job['out']}", "--train.overwrite=true"])


def test_the_processes_runner_runs_at_once_and_a_failed_run_fails_alone(tmp_path, monkeypatch):
    """Two toy runs are alive at the same time (two processes; each waits to see the other, so the load cannot make
    it pass or fail); a failing run is named at the end while the others finish, and the run waiting for it is not
    started."""
    run_grid(GridConfig(variants=["meet_a", "meet_b"], seeds=[0], output_root=tmp_path / "ok", runner="processes",
                        processes=2), ToyGrid())
    a, b = (json.loads((tmp_path / "ok" / f"{v}_seed0" / "results.json").read_text()) for v in ("meet_a", "meet_b"))
    assert a["met"] is True and b["met"] is True  # each saw the other alive
    monkeypatch.setenv("TOY_GRID_MEET_TIMEOUT", "1")
    run_grid(GridConfig(variants=["meet_a", "meet_b"], seeds=[0], output_root=tmp_path / "one", runner="processes",
                        processes=1), ToyGrid())
    first = json.loads((tmp_path / "one" / "meet_a_seed0" / "results.json").read_text())
    assert first["met"] is False  # one process at a time: the first run never sees the second (the check can fail)
    with pytest.raises(RuntimeError, match=r"2 of 3 runs failed.*fails_seed0: its process ended with status 1.*"
                                           r"after_fails_seed0: not started: fails_seed0 failed"):
        run_grid(GridConfig(variants=["fails", "a", "after_fails"], seeds=[0], output_root=tmp_path / "bad",
                            runner="processes", processes=1), ToyGrid())
    assert (tmp_path / "bad" / "a_seed0" / "results.json").is_file()
    assert not (tmp_path / "bad" / "after_fails_seed0").exists()
    assert "ValueError: toy failure" in (tmp_path / "bad" / "logs" / "fails_seed0.log").read_text()
    with pytest.raises(ValueError, match="processes: must be >= 1"):
        GridConfig(runner="processes", processes=0)


@pytest.mark.parametrize(("args", "expected"), [
    ([], "python -m sr_imitation.experiments.main_compare"),
    (["--train.resume=true"], "python -m sr_imitation.experiments.main_compare --train.resume=true"),
    (["--config_path=configs/needle_cpu.json"], "sr-main --config_path=configs/needle_cpu.json"),
    (["--train.seed=3", "--config_path=configs/needle_paper.json"],
     "sr-main --train.seed=3 --config_path=configs/needle_paper.json"),
])
def test_ci_main_sh_runs_the_comparison_by_default_and_sr_main_with_a_config_path(tmp_path, args, expected):
    """.ci/main.sh (a copy, its environment set-up replaced by one whose programs print their command line)."""
    ci = tmp_path / ".ci"
    ci.mkdir()
    shutil.copy(REPO / ".ci" / "main.sh", ci / "main.sh")
    bin_dir = tmp_path / "venv" / "bin"
    bin_dir.mkdir(parents=True)
    for name in ("python", "sr-main"):
        (bin_dir / name).write_text(f'#!/usr/bin/env bash\necho "{name} $*"\n')
        (bin_dir / name).chmod(0o755)
    (ci / "env.sh").write_text(f'venv="{tmp_path / "venv"}"\n')
    proc = subprocess.run(["bash", str(ci / "main.sh"), *args], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == expected
    assert re.search(r"^source \.ci/env\.sh$", (REPO / ".ci" / "main.sh").read_text(), re.M)  # the real set-up
