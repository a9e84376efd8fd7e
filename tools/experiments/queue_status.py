"""Where the experiment queue stands, in one screen (tools/experiments/queue_worker.sh's files; reads only):

    python3 tools/experiments/queue_status.py                      # outputs/queue.txt, logs in outputs/qlogs
    python3 tools/experiments/queue_status.py <queue file> <log folder>

For each run in flight (started in ``<queue>.done`` with no exit line after its last start): when it started, on
which CPU, the stage and phase its log reached last, and its last progress line (the wake's "n/N (p%) ... left");
whether its worker still runs (a ``python`` process whose command line holds the run's ``--output_root``) or the run
was cut (a session's end: requeue it). A cut run already put back in the queue (``queue_requeue.sh``: in the queue,
not in ``<queue>.taken``) is not in flight: it is listed as requeued, with where its outputs stopped. Then the queued
lines, with an estimate of the core-hours they hold (``HOURS_PER_RUN``); apart from them the lines that name other CPU
types than this machine's (``cpu=<family>/<model>,...``: tools/experiments/cpu_type.sh), which no worker here takes;
and the last finished runs with their exit status.
Standard library only, so it works before the environment is built.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from collections import Counter
from datetime import UTC, datetime
from pathlib import Path

STAGE = re.compile(r"stage (\d+) \(([^)]+)\): ([\w.]+)")
PROGRESS = re.compile(r"(\d+/\d+ \(\d+%\).*?left)")
START = re.compile(r"^(\S+) start (\S+)(?: on (.*))?$")
END = re.compile(r"^(\S+) (\S+) rc=(-?\d+)$")
PRESET = re.compile(r"--preset=(\S+)")
CPU_TYPES = re.compile(r"^\S+(?: @\S+)? cpu=(\S+)")
# One run's wall time on one core, by preset: measured on the Intel Xeon family 6 model 167 with the libraries capped
# at AVX2 (2026-11-30; docs/RESULTS.md's dated lines give each run's start and end). An estimate for planning only.
HOURS_PER_RUN = {"configs/sac_mt5_gate.json": 2.3, "configs/metaworld_mt5_imitation.json": 1.0,
                 "configs/needle_cpu_m16.json": 0.25}


def _lines(path: Path) -> list[str]:
    return [line for line in path.read_text().splitlines() if line.strip()] if path.is_file() else []


def _queued(queue: Path) -> list[str]:
    """The queue's run lines (comments dropped), read once so that the names and the estimate agree."""
    return [line for line in _lines(queue) if not line.startswith("#")]


def cpu_type(cpuinfo: Path = Path("/proc/cpuinfo")) -> str:
    """This machine's ``<family>/<model>``, as tools/experiments/cpu_type.sh reads it (``SR_CPU_TYPE`` overrides)."""
    if override := os.environ.get("SR_CPU_TYPE"):
        return override
    fields = dict(re.findall(r"^(cpu family|model)\s*: (\S+)", cpuinfo.read_text(), re.M))
    return f"{fields.get('cpu family', '?')}/{fields.get('model', '?')}"


def line_cpu_types(line: str) -> list[str]:
    """The CPU types a queue line names (``cpu=6/167,6/207`` after its name and ``@commit``); [] when it names none."""
    return m[1].split(",") if (m := CPU_TYPES.match(line)) else []


def queued_hours(lines: list[str], hours: dict[str, float] = HOURS_PER_RUN) -> str:
    """One line: the queued ``lines``' core-hours by preset (``HOURS_PER_RUN``); runs of other presets are counted
    apart."""
    count = Counter(m[1] if (m := PRESET.search(line)) and m[1] in hours else None for line in lines)
    unknown = count.pop(None, 0)
    parts = [f"{n} x {k} ~{hours[k]:g} h" for k, n in count.items()]
    if unknown:
        parts.append(f"{unknown} of no known preset, not counted")
    total = sum(hours[k] * n for k, n in count.items())
    return f"  queued work: about {total:.1f} core-hours ({'; '.join(parts)}), runs in flight not counted"


def runs(done: Path) -> tuple[dict[str, dict], list[dict]]:
    """``(in_flight, finished)`` from the worker's start and exit lines, oldest first (a finished run's ``started`` is
    its last start, None if the file has none: a run resumed after a kill starts more than once)."""
    flight: dict[str, dict] = {}
    finished = []
    for line in _lines(done):
        if m := START.match(line):
            flight[m[2]] = {"name": m[2], "started": m[1], "cpu": m[3] or "not named"}
        elif m := END.match(line):
            started = flight.pop(m[2], {}).get("started")
            finished.append({"name": m[2], "started": started, "ended": m[1], "rc": int(m[3])})
    return flight, finished


def last_position(log: Path) -> tuple[str, str]:
    """The last ``stage k (skill): phase`` of a run's log and the last progress text since it ("" where none)."""
    stage = progress = ""
    for line in _lines(log):
        if m := STAGE.search(line):
            stage, progress = f"stage {m[1]} ({m[2]}) {m[3]}", ""  # an earlier phase's progress is not this one's
        if m := PROGRESS.search(line):
            progress = line[line.find(": ", line.find(" INFO ")) + 2:] if " INFO " in line else m[1]
    return stage, progress


def _output_root(line: str) -> str | None:
    """The ``--output_root`` of a queue line as a worker took it (``<queue>.taken``)."""
    return next((a for a in line.split() if a.startswith("--output_root=")), None)


def _since(stamp: str, now: datetime) -> str:
    try:
        then = datetime.strptime(stamp, "%Y-%m-%dT%H:%M:%SZ").replace(tzinfo=UTC)
    except ValueError:
        return "?"
    minutes = int((now - then).total_seconds() // 60)
    return f"{minutes // 60} h {minutes % 60:02d} min ago"


def _entry(run: dict, state: str, logs: Path, now: datetime) -> list[str]:
    """A started run's two lines: its state, start and CPU; the stage and progress its log reached last."""
    stage, progress = last_position(logs / f"{run['name']}.log")
    return [f"  {run['name']}: {state}; last started {run['started']} ({_since(run['started'], now)}) on {run['cpu']}",
            f"    {stage or 'no stage yet'}{': ' + progress if progress else ''}"]


def report(queue: Path, logs: Path, now: datetime | None = None, last: int = 5) -> str:
    now = now or datetime.now(UTC)
    flight, finished = runs(queue.with_name(queue.name + ".done"))
    here = cpu_type()
    every = _queued(queue)
    waiting = [ln for ln in every if (types := line_cpu_types(ln)) and here not in types]
    lines = [ln for ln in every if ln not in waiting]
    queued = [line.split()[0] for line in every]
    taken = {ln.split()[0]: ln for ln in _lines(queue.with_name(queue.name + ".taken"))}
    requeued = {n: r for n, r in flight.items() if n in queued and n not in taken}
    flight = {n: r for n, r in flight.items() if n not in requeued}
    out = [f"queue {queue}: {len(flight)} in flight, {len(queued)} queued ({len(requeued)} of them requeued), "
           f"{len(finished)} finished"]
    ps = [p for p in subprocess.run(["ps", "-eo", "args"], capture_output=True, text=True, check=False).stdout
          .splitlines() if "python" in p]
    for r in flight.values():
        # a run's process is the python whose command line holds its output root
        root = _output_root(taken.get(r["name"], ""))
        alive = root is not None and any(root in p for p in ps)
        out += _entry(r, "running" if alive else "NOT running (cut: queue_requeue.sh puts it back)", logs, now)
    for r in requeued.values():
        out += _entry(r, "requeued (resumes from its outputs when a worker takes it)", logs, now)
    runnable = [line.split()[0] for line in lines]
    if runnable:
        more = f" (+{len(runnable) - 8} more)" if len(runnable) > 8 else ""
        out.append("  next: " + ", ".join(runnable[:8]) + more)
        out.append(queued_hours(lines))
    if waiting:
        out.append(f"  waiting for another CPU type (this machine: {here}): "
                   + ", ".join(f"{ln.split()[0]} (cpu={','.join(line_cpu_types(ln))})" for ln in waiting))
    for r in finished[-last:]:
        out.append(f"  ended {r['ended']}: {r['name']} rc={r['rc']}")
    return "\n".join(out)


def main(argv: list[str]) -> int:
    root = Path(__file__).resolve().parents[2]
    queue = Path(argv[0]) if argv else root / "outputs" / "queue.txt"
    logs = Path(argv[1]) if len(argv) > 1 else queue.parent / "qlogs"
    if not queue.is_file() and not queue.with_name(queue.name + ".done").is_file():
        sys.stderr.write(f"queue_status: {queue}: no queue here (tools/experiments/queue_resume.sh starts one)\n")
        return 2
    sys.stdout.write(report(queue, logs) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
