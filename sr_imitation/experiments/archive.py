"""An archive of finished runs for the comparison drivers: the folder of raw outputs the results are read from.

A comparison (``needle_compare``, ``mt5_compare``) is many runs over many sessions; a session's scratch directory
does not survive it. With ``--archive=docs/results/<comparison>`` a driver

* skips a (variant, seed) whose run the archive already holds, finished (``results.json``) **with the settings this
  run would have** (its ``settings_fingerprint.json``, checksum verified, against the fingerprint the driver
  computes for the run; a differing value is a one-line error naming the file and the keys), and summarizes it
  from there;
* copies every run it finishes into the archive at once (:data:`ARCHIVED_FILES`: results, progress with the
  per-phase seconds, settings, config, plots; no checkpoints, videos or logs), atomically (a temporary folder
  renamed into place), so a run's raw outputs land next to the earlier ones the moment it ends.

With a weight store (``--keep_weights=true``, the drivers' default) the archive also keeps what a later question
about the run needs and git should not carry: every checkpoint, memory and evaluation file of the run (the run
directory without videos, plots, reports and logs) goes to ``<archive>.weights/<run>/`` (git-ignored: see
``.gitignore``), and the tracked ``<archive>/<run>/weights.json`` lists each stored file with its size and sha256
(sealed), so the store of any machine can be checked against the archive (:func:`verify_weights`) before a re-sleep
reads it (:mod:`sr_imitation.substrates.sac.resleep`).

Keys the archived run does not have at all are settings added to the code after it ran (e.g.
``policy.backbone_norm``): they are named in a warning and the run counts as finished (our choice; the commits a
result spans are recorded with it in docs/RESULTS.md). Keys it has with another value always refuse.
"""

from __future__ import annotations

import logging
import shutil
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from sr_imitation.infra.fingerprint import (
    FINGERPRINT_FILE,
    SettingsFingerprint,
    check_settings,
    diff_settings,
    read_fingerprint,
)
from sr_imitation.infra.weight_store import WEIGHTS_FILE, staged_replacement, store_weights, weight_store
from sr_imitation.io import write_checked_json
from sr_imitation.stream.rundir import OverwriteRefusedError, few_names

logger = logging.getLogger(__name__)

RunKey = tuple[str, int]
"""(variant, training seed)."""

ARCHIVED_FILES = ("results.json", "results.md", "progress.json", "settings_fingerprint.json", "train_config.json",
                  "config.json", "metrics.png", "success_matrix.png", WEIGHTS_FILE)
"""The files of a run directory the archive keeps (those present): what the summaries and docs/RESULTS.md read."""
def archived_run(archive: Path | None, name: str, fingerprint: SettingsFingerprint) -> Path | None:
    """``archive / name`` if it holds a finished run with ``fingerprint``'s settings, else ``None``.

    Raises :class:`SettingsMismatchError` naming the archived fingerprint file if a setting both have differs,
    and ``CorruptFileError`` if that file is unreadable or fails its checksum."""
    if archive is None:
        return None
    run = Path(archive) / name
    if not (run / "results.json").is_file():
        return None
    stored = read_fingerprint(run / FINGERPRINT_FILE)
    added = diff_settings({}, {k: v for k, v in fingerprint.settings.items() if k not in stored})  # with values
    # a setting the run predates counts as equal; every other difference refuses, as on resume
    check_settings(run / FINGERPRINT_FILE, {**stored, **{k: fingerprint.settings[k] for k in added}}, fingerprint)
    if added:
        logger.warning("%s predates the settings %s (added to the code since it ran); counted as finished",
                       run, ", ".join(sorted(added)))
    return run


def archive_run(run: Path, archive: Path, name: str, keep_weights: bool = False) -> Path:
    """Copy a finished run's :data:`ARCHIVED_FILES` into ``archive / name`` (replacing an older copy, never a folder
    holding anything else) atomically; returns the archived directory. ``keep_weights``: also store its weights in
    :func:`weight_store` (before the archived copy, whose ``weights.json`` lists them)."""
    run, target = Path(run), Path(archive) / name
    if not (run / "results.json").is_file():
        raise FileNotFoundError(f"{run}: no results.json, the run has not finished; nothing archived")
    foreign = sorted(p.name for p in target.iterdir() if p.name not in ARCHIVED_FILES) if target.is_dir() else []
    if foreign or (target.exists() and not target.is_dir()):
        raise OverwriteRefusedError(f"{target}: not replaced by the archived run: it holds "
                                    f"{few_names(foreign) or 'a file'}, which an archived run does not; remove or "
                                    "move it yourself (nothing was removed)")
    with staged_replacement(target) as tmp:
        for file in ARCHIVED_FILES:
            if (run / file).is_file() and file != WEIGHTS_FILE:
                shutil.copy2(run / file, tmp / file)
        if keep_weights:
            write_checked_json(tmp / WEIGHTS_FILE, store_weights(run, weight_store(archive) / name))
    logger.info("archived %s -> %s", run, target)
    return target


def check_archive(plan: Mapping[RunKey, Any], archive: Path | None,
                  fingerprint: Callable[[str, Any], SettingsFingerprint]) -> dict[RunKey, Path | None]:
    """:func:`archived_run` for every planned run (``plan``: (variant, seed) -> its config, with ``output_dir``),
    all before the first one starts; ``fingerprint(variant, config)`` is the run's settings fingerprint."""
    return {key: archived_run(archive, Path(cfg.output_dir).name, fingerprint(key[0], cfg))
            for key, cfg in plan.items()}
