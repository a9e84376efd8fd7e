"""Two writers of one run folder at once, through ``sr-train``'s run entry on the toy substrate (``toy.main`` under
``run_cli("sr-train", ...)``, as ``sr-train --substrate=toy`` runs it), in real processes started together: a fresh
start against a fresh start, a resume against a resume, an overwrite against an overwrite and an overwrite against a
resume. One holds the folder's lock (:mod:`sr_imitation.infra.folder_lock`) for its whole life; the other is refused
in one line naming the folder and the holder, before it writes anything; the survivor ends with the files of a run
that had the folder to itself, its ``log.jsonl`` line for line (wall-clock fields aside).

Before: two resumes both finished rc 0, every record of ``log.jsonl`` twice (1244 lines instead of 625); two
overwrites moved each other's new run aside; two fresh starts were told apart only by a folder-exists check made
milliseconds before the folder was created."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
FLAGS = ["--stream.skills=[a,b,c]", "--progress=false", "--wake_steps=10"]
WALL_CLOCK = ("time", "seconds")
"""Fields of a log record that measure time, not what the run computed."""

WRITER = textwrap.dedent("""
    import os, sys, time
    from pathlib import Path
    from sr_imitation.infra.cli_errors import run_cli
    from sr_imitation.stream import rundir
    from tests.stream import toy
    go, kill_at, args = Path(sys.argv[1]), sys.argv[2], sys.argv[3:]
    wake, evaluate = toy.ToySubstrate.wake, toy.ToySubstrate.evaluate

    def slow_wake(self, *a, **k):  # each wake outlasts the other writer's start by far
        time.sleep(0.4)
        return wake(self, *a, **k)

    def dying_evaluate(self, k, phase, skills):  # kill_at "<k>:<phase>": the process dies there (as by kill -9)
        if kill_at == f"{k}:{phase}":
            os._exit(137)
        return evaluate(self, k, phase, skills)

    toy.ToySubstrate.wake, toy.ToySubstrate.evaluate = slow_wake, dying_evaluate
    rundir.RUN_ENTRIES = (*rundir.RUN_ENTRIES, "stage*")  # the toy's stage folders: a run --overwrite may replace
    print("ready", flush=True)
    while not go.exists():
        time.sleep(0.002)
    run_cli("sr-train", toy.main, args)
""")


def start_writers(go: Path, *commands: list[str], kill_at: str = "-") -> list[subprocess.Popen]:
    """One ``sr-train`` process per command line, each started once all have imported everything (``go`` is made
    then): they reach the run folder at the same moment."""
    procs = [subprocess.Popen([sys.executable, "-c", WRITER, str(go), kill_at, *FLAGS, *args], cwd=REPO,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for args in commands]
    for proc in procs:
        if proc.stdout.readline().strip() != "ready":
            pytest.fail(f"a writer did not start: {proc.communicate()[1][-2000:]}")
    go.touch()
    return procs


def finish(procs: list[subprocess.Popen]) -> list[tuple[int, str]]:
    """Each process's exit status and stderr, once all have ended."""
    out = []
    for proc in procs:
        _, err = proc.communicate(timeout=300)
        out.append((proc.returncode, err))
    return out


def run_alone(tmp: Path, *args: str, kill_at: str = "-") -> int:
    """One writer with the folder to itself; its exit status."""
    go = tmp / f"go_{time.monotonic_ns()}"
    ((code, err),) = finish(start_writers(go, list(args), kill_at=kill_at))
    if code not in (0, 137):
        pytest.fail(err[-2000:])
    return code


def log_lines(run: Path) -> list[dict]:
    """``log.jsonl`` without its wall-clock fields."""
    lines = (run / "log.jsonl").read_text().splitlines()
    return [{k: v for k, v in json.loads(line).items() if k not in WALL_CLOCK} for line in lines]


def files(run: Path) -> list[str]:
    return sorted(str(p.relative_to(run)) for p in run.rglob("*"))


def weights(run: Path) -> bytes:
    return (run / "stage2" / "sleep.safetensors").read_bytes()


@pytest.fixture(scope="module")
def clean(tmp_path_factory) -> dict[str, Path]:
    """Runs that had their folder to themselves: ``fresh`` (started and finished), ``killed`` (died at stage 2's
    wake evaluation) and ``resumed`` (a copy of ``killed``, resumed)."""
    tmp = tmp_path_factory.mktemp("clean")
    runs = {name: tmp / name for name in ("fresh", "killed", "resumed")}
    assert run_alone(tmp, f"--output_dir={runs['fresh']}") == 0
    assert run_alone(tmp, f"--output_dir={runs['killed']}", kill_at="1:wake.eval") == 137
    shutil.copytree(runs["killed"], runs["resumed"], symlinks=True)
    assert run_alone(tmp, f"--output_dir={runs['resumed']}", "--resume=true") == 0
    return runs


def check_one_refused(results: list[tuple[int, str]], procs: list[subprocess.Popen], run: Path) -> int:
    """Exactly one writer finished (rc 0) and the other was refused in one line naming ``run`` and the survivor;
    returns the survivor's index."""
    codes = [code for code, _ in results]
    assert sorted(codes) == [0, 2], results
    survivor, loser = codes.index(0), codes.index(2)
    lines = results[loser][1].strip().splitlines()
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"sr-train: error: {run}: in use by ")
    assert f"(pid {procs[survivor].pid} on " in lines[0]
    return survivor


def check_same_run(run: Path, reference: Path) -> None:
    """``run`` holds what the clean ``reference`` run holds: its files, its log line for line, its final weights;
    and nothing was left beside it (no run set aside, no lock)."""
    assert files(run) == files(reference)
    assert log_lines(run) == log_lines(reference)
    assert weights(run) == weights(reference)
    assert sorted(p.name for p in run.parent.iterdir() if p.name.startswith(f".{run.name}")) == []


@pytest.mark.slow
def test_two_fresh_starts_at_once(tmp_path, clean):
    run = tmp_path / "run"
    procs = start_writers(tmp_path / "go", [f"--output_dir={run}"], [f"--output_dir={run}"])
    check_one_refused(finish(procs), procs, run)
    check_same_run(run, clean["fresh"])


@pytest.mark.slow
def test_two_resumes_at_once(tmp_path, clean):
    run = tmp_path / "run"
    shutil.copytree(clean["killed"], run, symlinks=True)
    procs = start_writers(tmp_path / "go", [f"--output_dir={run}", "--resume=true"],
                          [f"--output_dir={run}", "--resume=true"])
    check_one_refused(finish(procs), procs, run)
    check_same_run(run, clean["resumed"])
    assert len(log_lines(run)) == len(log_lines(clean["fresh"]))  # not every record twice


@pytest.mark.slow
def test_two_overwrites_at_once(tmp_path, clean):
    run = tmp_path / "run"
    shutil.copytree(clean["fresh"], run, symlinks=True)
    (run / "stage0" / "wake.safetensors").write_bytes(b"an older run's")  # the survivor replaces it as a whole
    procs = start_writers(tmp_path / "go", [f"--output_dir={run}", "--overwrite=true"],
                          [f"--output_dir={run}", "--overwrite=true"])
    check_one_refused(finish(procs), procs, run)
    check_same_run(run, clean["fresh"])


@pytest.mark.slow
def test_an_overwrite_and_a_resume_at_once(tmp_path, clean):
    run = tmp_path / "run"
    shutil.copytree(clean["killed"], run, symlinks=True)
    procs = start_writers(tmp_path / "go", [f"--output_dir={run}", "--overwrite=true"],
                          [f"--output_dir={run}", "--resume=true"])
    survivor = check_one_refused(finish(procs), procs, run)
    check_same_run(run, clean["fresh"] if survivor == 0 else clean["resumed"])
