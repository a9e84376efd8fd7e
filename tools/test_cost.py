"""Where the test suite's CPU goes: each test's wall time, the CPU its own process spent, the CPU of the processes it
started and waited for, and what it started. A pytest plugin and its report:

    PYTHONPATH=tools SR_TEST_COST=/tmp/cost bash .ci/test.sh -p test_cost -q -p no:cacheprovider
    python3 tools/test_cost.py /tmp/cost

The plugin appends one JSON line per test to ``$SR_TEST_COST/<pid>.jsonl`` (one file per pytest worker): ``nodeid``,
``wall`` (set-up, call and teardown), ``cpu`` (this process, every thread), ``child`` (user + system CPU of the
processes it started and reaped: ``getrusage(RUSAGE_CHILDREN)``; a daemon it did not wait for, such as a Ray worker,
is not counted) and ``started`` (the commands of ``subprocess.Popen`` and ``os.fork`` / ``os.posix_spawn``, from
Python's audit hooks). The report sums them per file and says how long two perfectly balanced workers would need for
the in-process part alone: a floor that no reduction of process starts can go below."""

from __future__ import annotations

import json
import os
import resource
import sys
import time
from collections import Counter, defaultdict
from pathlib import Path

_started: list[str] = []
"""The commands the current test started (audit hook)."""


def _audit(event: str, args: tuple) -> None:
    if event == "subprocess.Popen":
        argv = args[1]
        _started.append(" ".join(map(str, argv)) if isinstance(argv, (list, tuple)) else str(argv))
    elif event in ("os.fork", "os.posix_spawn"):
        _started.append(f"<{event}>")


def _children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


_open: dict = {}
"""Whether this process records (``active``) and the current test's ``nodeid`` and starting clocks."""


def pytest_configure(config) -> None:
    """Loaded as a plugin (``-p test_cost``): watch the processes this one starts. Under pytest-xdist only the workers
    record (the controller also hears each worker's start and finish of a test, but runs none)."""
    _open["active"] = hasattr(config, "workerinput") or not getattr(config.option, "numprocesses", None)
    sys.addaudithook(_audit)


def pytest_runtest_logstart(nodeid: str, location) -> None:
    if not _open.get("active"):
        return
    _started.clear()
    _open.update(nodeid=nodeid, wall=time.perf_counter(), cpu=time.process_time(), child=_children_cpu())


def pytest_runtest_logfinish(nodeid: str, location) -> None:
    """One line per test, after its teardown: set-up, call and teardown together."""
    if not _open.get("active") or _open.get("nodeid") != nodeid:
        return
    record = {"nodeid": nodeid, "wall": round(time.perf_counter() - _open["wall"], 3),
              "cpu": round(time.process_time() - _open["cpu"], 3), "child": round(_children_cpu() - _open["child"], 3),
              "started": [command[:300] for command in _started]}
    out = Path(os.environ.get("SR_TEST_COST", "test_cost"))
    out.mkdir(parents=True, exist_ok=True)
    with open(out / f"{os.getpid()}.jsonl", "a") as f:
        f.write(json.dumps(record) + "\n")


def per_file(records: list[dict]) -> dict[str, dict]:
    """Each test file's summed ``wall``, ``cpu``, ``child`` and number of ``started`` processes."""
    files: dict[str, dict] = defaultdict(lambda: {"tests": 0, "wall": 0.0, "cpu": 0.0, "child": 0.0, "started": 0})
    for record in records:
        row = files[record["nodeid"].split("::", 1)[0]]
        row["tests"] += 1
        for key in ("wall", "cpu", "child"):
            row[key] += record[key]
        row["started"] += len(record["started"])
    return dict(files)


def report(records: list[dict], workers: int = 2, top: int = 25) -> str:
    """The totals, the floor of the in-process part on ``workers`` workers, the heaviest files and what was started."""
    cpu, child = sum(r["cpu"] for r in records), sum(r["child"] for r in records)
    started = Counter(command.split(maxsplit=1)[0].rsplit("/", 1)[-1] for r in records for command in r["started"]
                      if command.strip())
    lines = [f"{len(records)} tests: {cpu:.0f} s CPU in the test processes, {child:.0f} s CPU in the processes they "
             f"started and reaped, {sum(started.values())} processes started",
             f"in-process CPU alone on {workers} perfectly balanced workers: {cpu / workers:.0f} s of wall time",
             "", "| file | tests | wall s | own CPU s | children's CPU s | started |", "|---|---|---|---|---|---|"]
    files = sorted(per_file(records).items(), key=lambda kv: -(kv[1]["cpu"] + kv[1]["child"]))
    for name, row in files[:top]:
        lines.append(f"| {name} | {row['tests']} | {row['wall']:.1f} | {row['cpu']:.1f} | {row['child']:.1f} | "
                     f"{row['started']} |")
    lines += ["", "started: " + ", ".join(f"{name} x{n}" for name, n in started.most_common())]
    return "\n".join(lines) + "\n"


def main(argv: list[str]) -> int:
    if len(argv) != 1 or not Path(argv[0]).is_dir():
        sys.stderr.write("usage: python3 tools/test_cost.py <the folder SR_TEST_COST named>\n")
        return 2
    records = [json.loads(line) for path in sorted(Path(argv[0]).glob("*.jsonl"))
               for line in path.read_text().splitlines() if line.strip()]
    if not records:
        sys.stderr.write(f"{argv[0]}: no records (run the tests with -p test_cost, PYTHONPATH=tools)\n")
        return 1
    sys.stdout.write(report(records))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
