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
    flags = lines[0].split(" -m pytest ", 1)[1].split()
    assert flags[:2] == ["-n", '"$workers"'] and flags[-1] == '"$@"', flags
    return ["-n", "2", *flags[2:-1]]


def test_each_test_file_runs_on_one_worker(tmp_path):
    (tmp_path / "files").mkdir()
    for name in ("test_one", "test_two", "test_three"):
        (tmp_path / "files" / f"{name}.py").write_text(_TEST_FILE)
    (tmp_path / "pytest.ini").write_text("[pytest]\n")  # not the project's settings
    log = tmp_path / "where.jsonl"
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-n", "2", *_worker_flags(),
                           "-c", str(tmp_path / "pytest.ini"), "--rootdir", str(tmp_path),
                           # its own temporary folder, not a numbered one beside this session's
                           f"--basetemp={tmp_path / 'basetemp'}", str(tmp_path / "files")],
                          cwd=tmp_path, env={**_env(), "WHERE_LOG": str(log)}, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
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
    import importlib.util

    spec = importlib.util.spec_from_file_location("test_durations", ROOT / "tools" / "test_durations.py")
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    log = ("12.50s call     tests/x/test_a.py::test_one[p-1]\n3.30s setup    tests/x/test_a.py::test_two\n"
           "0.20s teardown tests/test_b.py::test_b\nnot a duration line tests/test_c.py::t\n"
           "1010 passed in 783.00s\n")
    assert tool.file_seconds(log) == {"tests/test_b.py": 0.2, "tests/x/test_a.py": 15.8}
    measured = json.loads((ROOT / "tests" / "durations.json").read_text())
    gone = [name for name in measured if not (ROOT / name).is_file()]
    assert measured and not gone, f"tests/durations.json names files that have gone: {gone} (tools/test_durations.py)"


def _env() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if not k.startswith("PYTEST_")}
