"""One run of an ``sr-grid`` grid: its name, the phases it has done, and running or resuming it as the only writer of
its directory, in this process or as the body of a Ray task or a process of its own."""

from __future__ import annotations

import copy
import importlib
import json
import logging
import os
import threading
import time
from pathlib import Path
from typing import Any

from sr_imitation.infra.folder_lock import hold_folder
from sr_imitation.offscreen import setup_offscreen_rendering
from sr_imitation.stream.rundir import PROGRESS_FILE, RunDirectory

logger = logging.getLogger(__name__)

KILL_HOOK_ENV = "SR_GRID_TEST_KILL"
"""Test hook (fault injection): ``<run name>:<phase key>:<marker file>`` makes the Ray task of that run kill its
own worker process (``os._exit(1)``) once ``progress.json`` records the phase (e.g. ``sr_seed0:1.wake``), unless
the marker file exists; the marker is written first, so only the first attempt dies."""


def run_name(variant: str, seed: int) -> str:
    """A run's directory name under ``output_root`` and in the archive."""
    return f"{variant}_seed{seed}"


def completed_phases(out: Path) -> list[str]:
    """The phases ``out/progress.json`` records as done (empty for a new run)."""
    try:
        return list(json.loads((Path(out) / PROGRESS_FILE).read_text()).get("completed", {}))
    except (OSError, ValueError, AttributeError):
        return []


def run_one(substrate: Any, variant: str, run: Any) -> dict[str, Any]:
    """Run or resume one run as the only writer of its directory (its lock, taken before the directory is looked at
    and held to the end): ``resume`` is decided now (a retried task finds its killed attempt's directory and
    continues it); returns the wall time and the phases that were already done. ``substrate``: a
    :class:`~sr_imitation.experiments.grid.GridSubstrate`."""
    run = copy.copy(run)
    with hold_folder(run.output_dir, "sr-grid"):
        run.resume = RunDirectory.occupied(run.output_dir)
        done = completed_phases(run.output_dir)
        start = time.perf_counter()
        substrate.run(variant, run)
        return {"wall_s": time.perf_counter() - start, "resumed_phases": done}


def _arm_kill_hook(out: Path) -> None:
    """:data:`KILL_HOOK_ENV` (tests only)."""
    spec = os.environ.get(KILL_HOOK_ENV)
    if not spec:
        return
    name, phase, marker = spec.split(":", 2)
    if Path(out).name != name or Path(marker).exists():
        return

    def watch() -> None:
        while phase not in completed_phases(out):
            time.sleep(0.01)
        Path(marker).write_text(str(os.getpid()))
        os._exit(1)

    threading.Thread(target=watch, daemon=True).start()


def run_task(module: str, variant: str, run: Any, log_file: str, threads: int) -> dict[str, Any]:
    """The body of one run's Ray task (a fresh worker process): threads, offscreen rendering, a log file, the run."""
    setup_offscreen_rendering()
    import torch

    torch.set_num_threads(threads)
    handler = logging.FileHandler(log_file)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    logging.getLogger().addHandler(handler)
    logging.getLogger().setLevel(logging.INFO)
    _arm_kill_hook(run.output_dir)
    try:
        info = run_one(importlib.import_module(module).GRID, variant, run)
    except BaseException:
        logger.exception("%s failed", run.output_dir)  # the whole traceback in the run's log
        raise
    return {**info, "node": os.uname().nodename, "pid": os.getpid()}
