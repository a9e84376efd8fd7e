"""The README's test command hands each test file to one pytest-xdist worker, as .ci/test.sh says: a module's shared
fixtures (recorded datasets, tiny trained runs) are then built once, and the grid's Ray tests never run beside each
other (tests/experiments/test_grid.py). Checked by a small pytest session of its own under .ci/test.sh's flags.

Why a test: ``--dist loadgroup`` with ``xdist_group`` marks, used before, silently distributed a group's tests over
both workers under pytest 9.2 with pytest-xdist 3.8 (xdist renames ``item._nodeid``, which pytest 9 no longer reads);
a dependency update could do the same to ``loadfile``."""

from __future__ import annotations

import json
import re
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


def _dist_flags() -> list[str]:
    """The ``--dist <mode>`` of .ci/test.sh's line that runs pytest in workers."""
    lines = [line for line in (ROOT / ".ci" / "test.sh").read_text().splitlines()
             if line.startswith("exec ") and " -n " in line]
    found = [m for line in lines for m in re.findall(r"--dist[ =](\S+)", line)]
    assert len(found) == 1, f".ci/test.sh: expected one --dist flag, found {found}"
    return ["--dist", found[0]]


def test_each_test_file_runs_on_one_worker(tmp_path):
    for name in ("test_one", "test_two", "test_three"):
        (tmp_path / f"{name}.py").write_text(_TEST_FILE)
    (tmp_path / "pytest.ini").write_text("[pytest]\n")  # not the project's settings
    log = tmp_path / "where.jsonl"
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-n", "2", *_dist_flags(),
                           "-c", str(tmp_path / "pytest.ini"), "--rootdir", str(tmp_path), str(tmp_path)],
                          cwd=tmp_path, env={**_env(), "WHERE_LOG": str(log)}, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    rows = [json.loads(line) for line in log.read_text().splitlines()]
    assert len(rows) == 18
    pids = {module: {pid for m, _, pid in rows if m == module} for module in {m for m, _, _ in rows}}
    assert len(pids) == 3 and all(len(p) == 1 for p in pids.values()), pids  # one worker per file
    assert len(set().union(*pids.values())) == 2, pids  # and both workers had files


def _env() -> dict[str, str]:
    import os

    return {k: v for k, v in os.environ.items() if not k.startswith("PYTEST_")}
