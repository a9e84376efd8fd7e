"""Where runs stand, read from their files: ``python -m sr_imitation.reporting.status RUN_OR_FOLDER [...]``.

A run is a directory with ``progress.json`` (any substrate, any method, the MT-Joint oracle included), or one that
has started and recorded no phase yet (only its settings fingerprint: "started" in the last-phase column); a folder of
runs (a grid's ``output_root``, an archive) is searched one level down, else two. One row per run: its variant, the
stages it has done (or "finished" with its final AFSR, or its validation l1 for a run without evaluation), the last
recorded phase and how long ago it was recorded (a run whose last phase ended long ago may have been killed:
``--resume`` continues it), the compute time of its recorded phases, and for an unfinished run a rough time left:
its completed stages' times (two at least) extrapolated linearly in the stage index (later stages distil from more
memories and sleep over more of them; our choice) over the stages left, less what the current stage has recorded. A
stage is complete when its last phase is recorded: its sleep's evaluation where the run sleeps (``sleep.enabled``,
stage >= 2), else its wake's (a method with other phases gets a rougher estimate). A ``results.json`` is read as the
summaries read it (:func:`~sr_imitation.reporting.results.load_results`): one that does not match its seal is shown as
not trusted, without its numbers; one of a schema before seals is marked unsealed. Reads only; writes nothing.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sr_imitation.infra.fingerprint import FINGERPRINT_FILE
from sr_imitation.io import JSON_CHECKSUM, CorruptFileError
from sr_imitation.progress import format_duration
from sr_imitation.reporting.results import final_headline, load_results, variant_label
from sr_imitation.stream.rundir import PROGRESS_FILE, RUN_CONFIG_FILE, check_run_config, read_progress
from sr_imitation.stream.substrate import PHASE_IDS


def find_runs(paths: Sequence[str | Path]) -> list[Path]:
    """The run directories among ``paths``, else in the folders one level below them, else two (a grid's
    ``output_root``; ``<root>/<name>/<run>`` as an experiment queue lays them out), in order, each once."""
    runs: list[Path] = []
    for path in map(Path, paths):
        found = [path] if is_run(path) else []
        for pattern in ("*", "*/*"):
            if not found and path.is_dir():
                found = sorted(p for p in path.glob(pattern) if is_run(p))
        if not found:
            raise FileNotFoundError(f"{path}: no run here ({PROGRESS_FILE} or {FINGERPRINT_FILE} in it or up to two "
                                    "levels below)")
        runs += [r for r in found if r not in runs]
    return runs


def is_run(path: Path) -> bool:
    """A run directory: it has recorded a phase (``progress.json``), or has started (its settings fingerprint is the
    first file a run writes; a long first phase, an MT-Joint oracle's one wake, records nothing for an hour)."""
    return (path / PROGRESS_FILE).is_file() or (path / FINGERPRINT_FILE).is_file()


def run_status(run: Path, now: float | None = None) -> dict[str, Any]:
    """One run's state (see the module docstring) as a dictionary."""
    now = time.time() if now is None else now
    progress = run / PROGRESS_FILE
    completed = (read_progress(progress).get("completed") or {}) if progress.is_file() else {}
    config, config_problem = _read_config(run / RUN_CONFIG_FILE)
    skills = list((config.get("stream") or {}).get("skills") or [])
    oracle = bool(config.get("mt_joint"))
    total = 1 if oracle else len(skills)
    label = "mt_joint" if oracle else variant_label(str(config.get("method", "?")),
                                                    bool((config.get("sleep") or {}).get("enabled", False)))
    per_stage: dict[int, float] = {}
    for key, record in completed.items():
        stage = int(key.split(".", 1)[0])
        seconds = record.get("seconds") if isinstance(record, dict) else None
        per_stage[stage] = per_stage.get(stage, 0.0) + (seconds if isinstance(seconds, (int, float)) else 0.0)
    last = max(completed, key=lambda k: (int(k.split(".", 1)[0]), PHASE_IDS.get(k.split(".", 1)[1], len(PHASE_IDS))),
               default=None)
    sleeps = bool((config.get("sleep") or {}).get("enabled", False)) and not oracle

    def complete(k: int) -> bool:
        return f"{k}.sleep.eval" in completed if sleeps and k >= 2 else f"{k}.wake.eval" in completed

    n_done = 0
    while n_done < total and complete(n_done + 1):
        n_done += 1
    out: dict[str, Any] = {"run": str(run), "variant": label, "seed": config.get("seed"), "stages": total,
                           "done": n_done, "last_phase": last, "seconds": sum(per_stage.values()),
                           "since_last": now - (progress if progress.is_file() else run / FINGERPRINT_FILE
                                                ).stat().st_mtime, "finished": False,
                           "final": None, "left": None, "config_problem": config_problem}
    if (run / "results.json").is_file():
        try:
            results = load_results(run)
        except (CorruptFileError, ValueError) as exc:  # a damaged or edited file: its numbers are not shown
            out.update(finished=True, final=f"results.json not trusted ({getattr(exc, 'problem', exc)})")
            return out
        mark = " (unsealed: a schema before seals)" if results.get("unsealed") else ""
        out.update(finished=True, final=final_headline(results) + mark)
        return out
    if n_done >= 2:  # one stage says nothing about the growth
        times = [per_stage.get(k, 0.0) for k in range(1, n_done + 1)]
        slope = float(np.polyfit(np.arange(1, n_done + 1), times, 1)[0])
        ahead = [max(0.0, times[-1] + slope * (k - n_done)) for k in range(n_done + 1, total + 1)]
        out["left"] = max(0.0, sum(ahead) - per_stage.get(n_done + 1, 0.0))
    return out


def _read_config(path: Path) -> tuple[dict[str, Any], str | None]:
    """A run's stored config for the labels, and why it is not trusted (``None`` if it is): one that fails the
    resume's check (:func:`~sr_imitation.stream.rundir.check_run_config`: a sealed file whose seal does not match, one
    written before seals that differs from the run's fingerprint), or one that does not read, gives no labels
    (variant and seed "?")."""
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        return {}, None
    except (OSError, ValueError) as exc:
        return {}, f"{path.name} unreadable ({type(exc).__name__})"
    if not isinstance(data, dict):
        return {}, f"{path.name} is not a JSON object"
    try:
        check_run_config(path.parent, path.name)
    except CorruptFileError as exc:
        where = "" if exc.path.name == path.name else f"{exc.path.name}: "
        return {}, f"{path.name} not trusted ({where}{exc.problem})"
    return {k: v for k, v in data.items() if k != JSON_CHECKSUM}, None


def render(rows: Sequence[dict[str, Any]]) -> str:
    """The markdown table of :func:`run_status` rows."""
    lines = ["| run | variant | seed | stages done | last phase (ago) | compute | state |", "|---" * 7 + "|"]
    for r in rows:
        state = f"finished: {r['final']}" if r["finished"] else (
            "running or stopped" + (f", ~{format_duration(r['left'])} left" if r["left"] is not None else ""))
        if r.get("config_problem"):
            state += f"; {r['config_problem']}"
        last = f"{r['last_phase'] or 'started'} ({format_duration(r['since_last'])} ago)"
        lines.append(f"| {r['run']} | {r['variant']} | {r['seed']} | {r['done']}/{r['stages']} | {last} | "
                     f"{format_duration(r['seconds'])} | {state} |")
    return "\n".join(lines) + "\n"


def main(args: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help="run directories, or folders of runs (a grid's output_root)")
    ns = parser.parse_args(args)
    print(render([run_status(r) for r in find_runs(ns.runs)]), end="")  # noqa: T201 (command output)


if __name__ == "__main__":
    from sr_imitation.infra.cli_errors import run_cli

    run_cli("sr_imitation.reporting.status", main)
