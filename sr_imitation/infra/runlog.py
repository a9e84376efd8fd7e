"""The per-step log of a run: always-on JSON lines next to the run's files, optionally mirrored to Weights & Biases.

Every record is one JSON object on its own line of ``<run>/log.jsonl``:

    {"time": 1763887200.1, "kind": "sleep", "stage": 3, "step": 120, "objective": 0.0012, "alpha": [...], ...}

``kind`` names what is logged (``wake``, ``sleep``, ``eval``, ``phase``, ...), ``stage`` the 1-based stage and
``step`` the step within that phase; the other keys are the values. Lines are flushed as they are written, so
``tail -f log.jsonl`` follows a run, and a killed run loses at most the line being written. A resumed run appends:
records of a phase that was interrupted and re-run appear twice, the later ones being the phase that completed
(:func:`read_log` keeps the last occurrence of each ``(kind, stage, step)``); a record torn by the kill is cut
before appending.

Weights & Biases (``WandbConfig(enable=True)``) gets the same records, keyed ``<kind>/<name>`` with a global step
counter; ``mode="offline"`` (the default) writes under ``<run>/wandb`` and sends nothing anywhere
(``wandb sync`` uploads later, if the user wants). wandb is imported only when enabled.
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sr_imitation.io import read_checked_json, write_checked_json

logger = logging.getLogger(__name__)

LOG_NAME = "log.jsonl"


@dataclass
class WandbConfig:
    """Experiment tracking with Weights & Biases (LeRobot's ``--wandb.*`` flags)."""

    enable: bool = False
    """Mirror the run log to wandb."""
    project: str = "sleeping_robots"
    """wandb project name."""
    mode: str = "offline"
    """``offline`` (default: nothing leaves the machine), ``online`` or ``disabled``."""
    run_name: str | None = None
    """Display name of the run (default: the output directory's name)."""

    def __post_init__(self) -> None:
        if self.mode not in ("offline", "online", "disabled"):
            raise ValueError(f"wandb.mode must be offline, online or disabled, got {self.mode!r}")


def _drop_torn_tail(path: Path) -> None:
    """A run killed while writing leaves a last line without its newline: cut it before appending."""
    if not path.is_file() or path.stat().st_size == 0:
        return
    data = path.read_bytes()
    if data.endswith(b"\n"):
        return
    keep = data.rfind(b"\n") + 1
    logger.warning("%s: dropping a torn last record (%d bytes) before appending", path, len(data) - keep)
    with path.open("r+b") as f:
        f.truncate(keep)


def _jsonable(value: Any) -> Any:
    if isinstance(value, float):
        return value if math.isfinite(value) else str(value)  # JSON has no NaN/Inf
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if hasattr(value, "tolist"):  # numpy / torch scalars and arrays
        return _jsonable(value.tolist())
    if isinstance(value, str | int | bool) or value is None:
        return value
    return str(value)


WANDB_ID_FILE = "wandb_run.json"
"""The run's wandb id, written when wandb is first enabled for it; a resume continues that wandb run."""


def _records(path: Path) -> int:
    """The number of records in a log (the wandb step a resumed run continues after)."""
    if not path.is_file():
        return 0
    with path.open("rb") as f:
        return sum(1 for _ in f)


class RunLog:
    """Append-only JSON-lines log of a run (module docstring); use as a context manager or call :meth:`close`."""

    def __init__(self, run_dir: str | Path, wandb: WandbConfig | None = None,
                 config: Mapping[str, Any] | None = None) -> None:
        self.path = Path(run_dir) / LOG_NAME
        self.path.parent.mkdir(parents=True, exist_ok=True)
        _drop_torn_tail(self.path)
        self._file = self.path.open("a", encoding="utf-8")
        self._wandb = None
        self._global_step = 0
        if wandb is not None and wandb.enable and wandb.mode != "disabled":
            if wandb.mode == "offline":  # nothing leaves the machine: no crash reports to wandb's Sentry either
                os.environ.setdefault("WANDB_ERROR_REPORTING", "false")
            import wandb as wandb_lib  # noqa: PLC0415 - optional, imported only when enabled

            id_path = Path(run_dir) / WANDB_ID_FILE
            run_id = read_checked_json(id_path)["id"] if id_path.is_file() else None
            # a resumed run continues the same wandb run (LeRobot's run_id), its steps after the logged records
            self._global_step = _records(self.path) if run_id is not None else 0
            self._wandb = wandb_lib.init(
                project=wandb.project, name=wandb.run_name or Path(run_dir).name, dir=str(run_dir),
                mode=wandb.mode, config=_jsonable(dict(config or {})), reinit="finish_previous",
                id=run_id, resume="allow" if run_id is not None else None,
            )
            if run_id is None:
                write_checked_json(id_path, {"id": self._wandb.id})
            logger.info("wandb (%s) logging to %s", wandb.mode, Path(run_dir) / "wandb")

    def log(self, kind: str, stage: int | None = None, step: int | None = None, **values: Any) -> None:
        """Write one record (and mirror its numeric values to wandb when enabled)."""
        record = {"time": round(time.time(), 3), "kind": kind, "stage": stage, "step": step, **values}
        self._file.write(json.dumps(_jsonable(record), sort_keys=False) + "\n")
        self._file.flush()
        if self._wandb is not None:
            self._global_step += 1
            scalars = {f"{kind}/{k}": v for k, v in values.items()
                       if isinstance(v, int | float) and not isinstance(v, bool)}
            if stage is not None:
                scalars[f"{kind}/stage"] = stage
            if scalars:
                self._wandb.log(scalars, step=self._global_step)

    def close(self) -> None:
        if not self._file.closed:
            self._file.close()
        if self._wandb is not None:
            self._wandb.finish()
            self._wandb = None

    def __enter__(self) -> RunLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def read_log(path: str | Path) -> list[dict[str, Any]]:
    """The records of a run log, the last occurrence of each ``(kind, stage, step)`` (re-run phases replace the
    interrupted ones), in file order. A torn last line (a kill while writing) is skipped."""
    records: dict[tuple, dict[str, Any]] = {}
    lines = Path(path).read_text(encoding="utf-8").splitlines()
    for i, line in enumerate(lines):
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            if i == len(lines) - 1:
                continue
            raise
        key = (rec.get("kind"), rec.get("stage"), rec.get("step"))
        if key[2] is None:  # unnumbered records (phase starts, evaluations) are all kept
            key = (*key, i)
        records.pop(key, None)
        records[key] = rec
    return list(records.values())
