"""The README's test command hands each test file to one pytest-xdist worker, as .ci/test.sh says: a module's shared
fixtures (recorded datasets, tiny trained runs) are then built once, and the grid's Ray tests never run beside each
other (tests/experiments/test_grid.py). Checked by a small pytest session of its own under .ci/test.sh's flags.

Why a test: ``--dist loadgroup`` with ``xdist_group`` marks, used before, silently distributed a group's tests over
both workers under pytest 9.2 with pytest-xdist 3.8 (xdist renames ``item._nodeid``, which pytest 9 no longer reads);
a dependency update could do the same to ``loadfile``."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.tool_loader import load_tool

ROOT = Path(__file__).resolve().parents[1]

_TEST_FILE = '''
import json, os, pytest

@pytest.mark.parametrize("i", range(6))
def test_where(i):
    with open(os.environ["WHERE_LOG"], "a") as f:
        f.write(json.dumps([__name__, i, os.getpid()]) + "\\n")
'''


def _worker_flags() -> list[str]:
    """The flags of .ci/test.sh's line that runs pytest in workers, with two workers."""
    lines = [line for line in (ROOT / ".ci" / "test.sh").read_text().splitlines()
             if line.startswith("exec ") and " -n " in line]
    assert len(lines) == 1, f".ci/test.sh: expected one pytest line with workers, found {lines}"
    flags = [f for f in lines[0].split(" -m pytest ", 1)[1].split() if not f.startswith('"${tier')]  # the tier: -m
    assert flags[:2] == ["-n", '"$workers"'] and flags[-1] == '"$@"', flags
    return ["-n", "2", *flags[2:-1]]


def test_each_test_file_runs_on_one_worker(tmp_path):
    log = tmp_path / "where.jsonl"
    _inner_session(tmp_path, _TEST_FILE, ("test_one", "test_two", "test_three"), {"WHERE_LOG": str(log)})
    rows = [json.loads(line) for line in log.read_text().splitlines()]
    assert len(rows) == 18
    pids = {module: {pid for m, _, pid in rows if m == module} for module in {m for m, _, _ in rows}}
    assert len(pids) == 3 and all(len(p) == 1 for p in pids.values()), pids  # one worker per file
    assert len(set().union(*pids.values())) == 2, pids  # and both workers had files


class _Item:
    def __init__(self, nodeid: str):
        self.nodeid = nodeid


def test_the_heaviest_files_go_first_each_in_its_own_order():
    from tests.conftest import heaviest_files_first

    items = [_Item(n) for n in ("a.py::t1", "b.py::t1", "a.py::t2", "c.py::t1", "b.py::t2", "d.py::t[1]")]
    order = [i.nodeid for i in heaviest_files_first(items, {"b.py": 30.0, "c.py": 5.0, "a.py": 5.0, "gone.py": 99})]
    # b (30 s), then a and c (5 s each) in collection order, then d (not measured: 0 s)
    assert order == ["b.py::t1", "b.py::t2", "a.py::t1", "a.py::t2", "c.py::t1", "d.py::t[1]"]
    assert [i.nodeid for i in heaviest_files_first(items, {})] == [  # no measurements: files in collection order
        "a.py::t1", "a.py::t2", "b.py::t1", "b.py::t2", "c.py::t1", "d.py::t[1]"]


def test_the_durations_come_from_pytests_report(tmp_path):
    tool = load_tool("test_durations")
    log = ("12.50s call     tests/x/test_a.py::test_one[p-1]\n3.30s setup    tests/x/test_a.py::test_two\n"
           "0.20s teardown tests/test_b.py::test_b\nnot a duration line tests/test_c.py::t\n"
           "1010 passed in 783.00s\n")
    assert tool.file_seconds(log) == {"tests/test_b.py": 0.2, "tests/x/test_a.py": 15.8}
    measured = json.loads((ROOT / "tests" / "durations.json").read_text())
    gone = [name for name in measured if not (ROOT / name).is_file()]
    assert measured and not gone, f"tests/durations.json names files that have gone: {gone} (tools/test_durations.py)"


def _env() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if not k.startswith("PYTEST_")}


def _inner_session(tmp_path: Path, text: str, names: tuple[str, ...], env: dict[str, str], *flags: str) -> None:
    """A pytest session of its own under .ci/test.sh's worker flags (two workers) over the test files ``names``, each
    holding ``text``; not the project's settings, its own temporary folder. Fails unless every test passes."""
    (tmp_path / "files").mkdir()
    for name in names:
        (tmp_path / "files" / f"{name}.py").write_text(text)
    (tmp_path / "pytest.ini").write_text("[pytest]\n")
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *flags, *_worker_flags(),
                           "-c", str(tmp_path / "pytest.ini"), "--rootdir", str(tmp_path),
                           f"--basetemp={tmp_path / 'basetemp'}", str(tmp_path / "files")],
                          cwd=tmp_path, env={**_env(), **env}, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]


_COST_FILE = '''
import subprocess, sys

def test_starts_one():
    subprocess.run([sys.executable, "-c", "sum(range(2_000_000))"], check=True)

def test_works_here():
    sum(range(2_000_000))
'''


def test_the_cost_plugin_records_each_test_once_with_its_children_under_two_workers(tmp_path):
    out = tmp_path / "cost"
    _inner_session(tmp_path, _COST_FILE, ("test_one", "test_two"),
                   {"PYTHONPATH": str(ROOT / "tools"), "SR_TEST_COST": str(out)}, "-p", "test_cost")
    records = [json.loads(line) for path in out.glob("*.jsonl") for line in path.read_text().splitlines()]
    assert len(list(out.glob("*.jsonl"))) == 2  # the two workers wrote; the controller, which runs no test, did not
    assert sorted(r["nodeid"].rsplit("/", 1)[-1] for r in records) == [  # each test once
        "test_one.py::test_starts_one", "test_one.py::test_works_here",
        "test_two.py::test_starts_one", "test_two.py::test_works_here"]
    for r in records:
        started = r["nodeid"].endswith("test_starts_one")
        assert (len(r["started"]) == 1) == started and (r["child"] > 0) == started, r
        assert r["cpu"] > 0 and r["wall"] > 0, r
        if started:
            assert r["started"][0].startswith(sys.executable) and "sum(range" in r["started"][0], r


def test_the_cost_report_sums_per_file_and_gives_the_in_process_floor():
    tool = load_tool("test_cost")
    records = [{"nodeid": "tests/a.py::t1", "wall": 10.0, "cpu": 8.0, "child": 0.0, "started": []},
               {"nodeid": "tests/a.py::t2[x]", "wall": 30.0, "cpu": 2.0, "child": 25.0,
                "started": ["/venv/bin/lerobot-train --steps=4", "/usr/bin/git status"]},
               {"nodeid": "tests/b.py::t", "wall": 4.0, "cpu": 4.0, "child": 0.0, "started": ["<os.fork>"]}]
    assert tool.per_file(records) == {
        "tests/a.py": {"tests": 2, "wall": 40.0, "cpu": 10.0, "child": 25.0, "started": 2},
        "tests/b.py": {"tests": 1, "wall": 4.0, "cpu": 4.0, "child": 0.0, "started": 1}}
    text = tool.report(records, workers=2)
    assert text.startswith("3 tests: 14 s CPU in the test processes, 25 s CPU in the processes they started and "
                           "reaped, 3 processes started\nin-process CPU alone on 2 perfectly balanced workers: 7 s")
    assert text.index("| tests/a.py | 2 | 40.0 | 10.0 | 25.0 | 2 |") < text.index("| tests/b.py |")
    assert "started: lerobot-train x1, git x1, <os.fork> x1" in text


def test_the_readme_command_keeps_temporary_files_on_a_ram_disk_when_there_is_one():
    """.ci/test.sh exports TMPDIR=/dev/shm/sr_tests where /dev/shm is writable with 4 GB free (unless SR_TEST_TMPDIR
    says otherwise): small files' fsync and unlink cost milliseconds on this project's VMs' disks."""
    import shutil
    import tempfile

    if not os.environ.get("SR_TEST_OVERLAY") or "SR_TEST_TMPDIR" in os.environ:
        pytest.skip("not under .ci/test.sh's defaults")
    room = os.access("/dev/shm", os.W_OK) and shutil.disk_usage("/dev/shm").free >= 4000000 * 1024
    assert (tempfile.gettempdir() == "/dev/shm/sr_tests") == bool(room), (tempfile.gettempdir(), room)
