"""Do two runs agree? ``python -m sr_imitation.reporting.compare RUN_A RUN_B [--tol 0]``.

Two folders of runs (two grids' ``output_root``, an archive and its re-run) are compared run by run, paired by their
path below the folder: a row per run and exit 0 when every pair agrees and both hold the same runs.

A reproducibility check (a rerun, a resume, another machine or commit, CPU against CUDA) compares what two runs
measured, not how long they took:

- ``results.json``: the success matrices per evaluation unit (and their means), the success right after each own
  wake, every metric, the memory sizes;
- ``progress.json``: every number each phase recorded (each wake's best validation l1 and epoch, each sleep's
  memory losses, bargaining weights, stop iteration and solver statuses, each evaluation's success), except its
  ``seconds``.

Numbers agree when ``|a - b| <= tol`` (0: exactly); anything else must be equal. The settings both runs recorded
(``settings_fingerprint.json``: the names of those that differ) and their code commits (``results.json``) are printed
as context, not compared: two runs of different settings may agree. Every seal is checked as a resume checks it: a
fingerprint or a ``train_config.json`` that does not match its seal, or an unsealed ``train_config.json`` that
differs from its run's fingerprint (:func:`~sr_imitation.stream.rundir.check_run_config`), refuses the comparison.
Prints the differing values (the first ``--show``), a count and the largest numeric difference; exits 0 when the runs
agree, 1 when they do not (a user error, such as a folder without ``progress.json``, an edited ``train_config.json``
or a ``results.json`` that does not match its seal, is one line naming the file and exit 2; one of a schema before
seals is read as the summaries read it and marked unsealed, or refused when it does not read as its schema). Reads
only; writes nothing.
"""

from __future__ import annotations

import argparse
import math
import re
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from sr_imitation.infra.fingerprint import FINGERPRINT_FILE, read_fingerprint
from sr_imitation.io import read_json
from sr_imitation.reporting.results import read_results_file
from sr_imitation.reporting.status import find_runs, is_run  # the same run search as status (one or two levels down)
from sr_imitation.stream.rundir import PROGRESS_FILE, check_run_config, read_progress

RESULTS_KEYS = ("success_matrix", "success_matrix_per_unit", "success_after_own_wake",
                "success_after_own_wake_per_unit", "metrics", "memory_bytes", "skills", "stages")
"""The parts of ``results.json`` that are measurements (the rest is the run's config, labels and seal)."""
TIMING_KEYS = frozenset({"seconds"})
"""Keys that measure time, not the run (a phase record's, and each stage's in ``results.json``): skipped anywhere."""


def leaves(value: Any, path: str = "") -> Iterator[tuple[str, Any]]:
    """``(path, leaf)`` for every non-container value in nested dicts and lists (``a.b[2].c``)."""
    if isinstance(value, dict):
        for key in sorted(value, key=str):
            yield from leaves(value[key], f"{path}.{key}" if path else str(key))
    elif isinstance(value, (list, tuple)):
        for i, item in enumerate(value):
            yield from leaves(item, f"{path}[{i}]")
    else:
        yield path, value


def measured(run: Path) -> dict[str, Any]:
    """What ``run`` measured (see the module docstring), keyed by source file and path."""
    if not is_run(run):
        raise FileNotFoundError(f"{run}: not a run directory (no {PROGRESS_FILE})")
    if (run / FINGERPRINT_FILE).is_file():
        read_fingerprint(run / FINGERPRINT_FILE)  # its seal
    check_run_config(run)  # its seal, or (unsealed) the fingerprint's settings: an edited config is refused
    progress = run / PROGRESS_FILE  # a run that has started and recorded no phase has measured nothing yet
    completed = (read_progress(progress).get("completed") or {}) if progress.is_file() else {}
    found = [(f"progress:{p}", v) for p, v in leaves(completed)]
    results_path = run / "results.json"
    if results_path.is_file():  # checked as the summaries check it: a file that does not match its seal is refused
        results, _ = read_results_file(results_path)
        found += [(f"results:{p}", v) for key in RESULTS_KEYS if key in results for p, v in leaves(results[key], key)]
    return {p: v for p, v in found if not TIMING_KEYS & set(re.split(r"[.:\[]", p))}


def _agree(a: Any, b: Any, tol: float) -> tuple[bool, float | None]:
    """Whether two leaves agree, and their numeric difference (None when not both numbers)."""
    numbers = all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in (a, b))
    if not numbers:
        return a == b, None
    if math.isnan(a) or math.isnan(b):
        return math.isnan(a) and math.isnan(b), None
    diff = abs(a - b)
    return diff <= tol, diff


def compare_runs(run_a: Path, run_b: Path, tol: float = 0.0) -> dict[str, Any]:
    """``{"compared", "differences": [(path, a, b, diff)], "only_a", "only_b", "max_diff", "max_path"}``."""
    a, b = measured(run_a), measured(run_b)
    differences = []
    max_diff, max_path = 0.0, None
    for path in sorted(a.keys() & b.keys()):
        ok, diff = _agree(a[path], b[path], tol)
        if diff is not None and diff > max_diff:
            max_diff, max_path = diff, path
        if not ok:
            differences.append((path, a[path], b[path], diff))
    unsealed = [side for side, run in (("A", run_a), ("B", run_b))
                if (run / "results.json").is_file() and read_results_file(run / "results.json")[1]]
    return {"compared": len(a.keys() & b.keys()), "differences": differences,
            "only_a": sorted(a.keys() - b.keys()), "only_b": sorted(b.keys() - a.keys()),
            "max_diff": max_diff, "max_path": max_path, "unsealed": unsealed}


def run_commit(run: Path) -> str:
    """The code that wrote the run's results (``results.json``'s ``code``; "dirty": with uncommitted changes), else
    "unknown commit" (an unfinished run, or one written before the commit was recorded)."""
    results = run / "results.json"
    code = (read_json(results).get("code") or {}) if results.is_file() else {}
    if not code.get("commit"):
        return "unknown commit"
    return f"commit {code['commit'][:10]}" + (" (dirty)" if code.get("dirty") else "")


def settings_differences(run_a: Path, run_b: Path) -> list[str] | None:
    """The recorded settings (``settings_fingerprint.json``) whose values differ between the runs; None when a run
    recorded none."""
    paths = [r / FINGERPRINT_FILE for r in (run_a, run_b)]
    if not all(p.is_file() for p in paths):
        return None
    a, b = (read_fingerprint(p) for p in paths)
    return sorted(k for k in a.keys() | b.keys() if a.get(k, "<unset>") != b.get(k, "<unset>"))


def render(report: dict[str, Any], show: int = 20) -> str:
    lines = []
    for path, a, b, diff in report["differences"][:show]:
        lines.append(f"  {path}: {a!r} != {b!r}" + (f"  (|diff| {diff:.3g})" if diff is not None else ""))
    if len(report["differences"]) > show:
        lines.append(f"  ... and {len(report['differences']) - show} more")
    for side in ("only_a", "only_b"):
        if report[side]:
            lines.append(f"  only in run {side[-1].upper()}: {len(report[side])} values, e.g. {report[side][0]}")
    agree = _agrees(report)
    largest = (f"; largest numeric difference {report['max_diff']:.3g} ({report['max_path']})"
               if report["max_path"] else "; every number equal")
    verdict = ("the runs agree" if agree else "nothing measured yet" if not report["compared"] else
               f"the runs differ in {len(report['differences'])} values")
    lines.append(f"{report['compared']} measured values compared: {verdict}{largest}")
    for side in report.get("unsealed", []):
        lines.append(f"  run {side}'s results.json is unsealed (a schema before seals, checked against its own "
                     "success matrix only)")
    return "\n".join(lines) + "\n"


def _agrees(report: dict[str, Any]) -> bool:
    """No differing value, none on one side only, and something compared (two runs that measured nothing yet do not
    agree: they have not run)."""
    return report["compared"] > 0 and not (report["differences"] or report["only_a"] or report["only_b"])


def compare_folders(folder_a: Path, folder_b: Path, tol: float = 0.0) -> tuple[str, bool]:
    """Two folders of runs (grids' ``output_root``, archives): the runs of the same name paired, one row each, and
    whether every pair agrees and both folders hold the same runs."""
    runs_a, runs_b = ({r.relative_to(f).as_posix(): r for r in find_runs([f])} for f in (folder_a, folder_b))
    lines = ["| run | values compared | differing | largest numeric difference | verdict |", "|---" * 5 + "|"]
    ok = runs_a.keys() == runs_b.keys()
    for name in sorted(runs_a.keys() & runs_b.keys()):
        report = compare_runs(runs_a[name], runs_b[name], tol)
        ok &= _agrees(report)
        mark = f" (unsealed: {', '.join(report['unsealed'])})" if report["unsealed"] else ""
        lines.append(f"| {name} | {report['compared']} | {len(report['differences'])} | {report['max_diff']:.3g} | "
                     f"{'agree' if _agrees(report) else 'differ'}{mark} |")
    for name in sorted(runs_a.keys() ^ runs_b.keys()):
        lines.append(f"| {name} | - | - | - | only in {'A' if name in runs_a else 'B'} |")
    return "\n".join(lines) + "\n", ok


def report_text(run_a: Path, run_b: Path, tol: float = 0.0, show: int = 20) -> tuple[str, dict[str, Any]]:
    """Two runs' comparison as this command prints it (their paths and commits, whether their settings differ,
    :func:`render`), and the report (:func:`compare_runs`)."""
    report = compare_runs(run_a, run_b, tol)
    settings = settings_differences(run_a, run_b)
    context = ("settings: not recorded by both" if settings is None else
               "settings: the same" if not settings else f"settings differ in: {', '.join(settings)}")
    return (f"A = {run_a} ({run_commit(run_a)})\nB = {run_b} ({run_commit(run_b)})\n{context}\n"
            + render(report, show)), report


def main(args: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_a", help="a run directory, or a folder of runs (then run_b is one too)")
    parser.add_argument("run_b")
    parser.add_argument("--tol", type=float, default=0.0, help="largest numeric difference that still agrees")
    parser.add_argument("--show", type=int, default=20, help="differences printed")
    ns = parser.parse_args(args)
    run_a, run_b = Path(ns.run_a), Path(ns.run_b)
    if not is_run(run_a) and not is_run(run_b):
        table, ok = compare_folders(run_a, run_b, ns.tol)
        print(f"A = {run_a}\nB = {run_b}\n" + table, end="")  # noqa: T201 (command output)
        return 0 if ok else 1
    text, report = report_text(run_a, run_b, ns.tol, ns.show)
    print(text, end="")  # noqa: T201 (command output)
    return 0 if _agrees(report) else 1


if __name__ == "__main__":
    from sr_imitation.infra.cli_errors import run_cli

    sys.exit(run_cli("sr_imitation.reporting.compare", main))
