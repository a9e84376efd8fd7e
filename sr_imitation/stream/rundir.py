"""A run directory that cannot change silently: settings fingerprint, stored config, progress, leftovers.

Fresh run: the directory is created, the settings fingerprint (:mod:`sr_imitation.infra.fingerprint`) and the stored
config are written once. Resume: the requested settings are checked against the fingerprint *before anything is
written* (a refused resume leaves the directory byte-identical), ``progress.json`` is read, and temporary files
left by a killed atomic write are removed. Nothing stored at the start is ever rewritten.

``progress.json`` records every completed phase under ``"<stage>.<phase>"`` (1-based stage), written atomically
after the phase's files, so a phase is either recorded with all its outputs or redone.
"""

from __future__ import annotations

import logging
import os
import shutil
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from sr_imitation.infra.fingerprint import (
    FINGERPRINT_FILE,
    SettingsFingerprint,
    check_settings,
    read_fingerprint,
    write_fingerprint,
)
from sr_imitation.io import (
    JSON_CHECKSUM,
    CorruptFileError,
    WriteError,
    atomic_write_json,
    fsync_directory,
    read_checked_json,
    read_json,
    write_checked_json,
)
from sr_imitation.stream.verify import verify_run_files

logger = logging.getLogger(__name__)

PROGRESS_FILE = "progress.json"
PROGRESS_VERSION = 2
"""2: always sealed (1: the first version; some of its committed files carry no seal, read by reports only)."""
REGENERATED_FILES = ("results.json",)
"""Files a run rewrites from its recorded phases at its end (not inputs of a resume, so not verified before it)."""
RUN_CONFIG_FILE = "train_config.json"
"""The run's stored config, on every substrate (LeRobot's name; ``--config_path=<run>/train_config.json --resume=true``
resumes the run)."""
LEGACY_CONFIG_FILES = ("config.json",)
"""Where SAC runs written before issue 29 stored their config (not sealed, not rewritten: read by ``--config_path``)."""
LAST_POINTER = "last"
"""``<run>/last``: the newest consolidated policy's checkpoint folder (LeRobot's ``checkpoints/last``)."""
TEMPORARY_PATTERNS = (".*.tmp", ".*.tmp.*", ".wake.*", ".sleep.*")
"""Names of what an interrupted atomic write leaves (temp files of ``atomic_write_bytes``, staging directories of
checkpoints): removed on resume, never read."""


def point_last(run: Path, checkpoint: Path) -> None:
    """Point ``<run>/last`` (:data:`LAST_POINTER`) at ``checkpoint``, a folder below ``run``, as LeRobot points
    ``checkpoints/last``: a relative symbolic link (the run stays movable), replaced atomically by renaming a new
    link ``.last.tmp`` over it (a leftover of that name is removed on resume). A real folder of that name (a run
    copied without following links) is replaced. ``WriteError`` naming the link on failure."""
    run = Path(run)
    link, tmp = run / LAST_POINTER, run / f".{LAST_POINTER}.tmp"
    try:
        if tmp.is_symlink() or tmp.exists():
            tmp.unlink()
        os.symlink(os.path.relpath(checkpoint, run), tmp, target_is_directory=True)
        if link.is_dir() and not link.is_symlink():
            shutil.rmtree(link)
        os.replace(tmp, link)
        fsync_directory(run)
    except OSError as exc:
        raise WriteError(link, exc) from exc


def read_progress(path: Path) -> dict[str, Any]:
    """A ``progress.json`` for reading (reports, sleep replays of committed runs): checked against its seal, except
    that files of the first progress version may lack one (some committed raw outputs were written before seals;
    decided by the recorded version, never by the missing key alone). A resume always requires the seal."""
    data = read_json(path)
    if isinstance(data, dict) and data.get("version") == 1 and JSON_CHECKSUM not in data:
        return data
    return read_checked_json(path)


class RunDirectory:
    """One run's output directory.

    Args:
        path: the directory.
        fingerprint: the requested settings (the whole config minus its documented allow-list).
        config_file: the stored config's file name (:data:`RUN_CONFIG_FILE` for the substrates' runs);
            ``stored_config`` is its content.
        resume, overwrite: the per-invocation flags.
        check_inputs: ``check_inputs(fingerprint_file, stored_settings)`` is called on resume before the settings
            are compared, to refuse other input data with its own message (the ACT substrate's datasets:
            :func:`sr_imitation.imitation.dataset_identity.check_inputs`).

    A directory without ``settings_fingerprint.json`` is never resumed: the fingerprint is written first, before
    anything else, so its absence means the run was not made by this code or the file was deleted (one line naming
    it; its settings are never re-created from the stored config, which is not sealed).
    """

    def __init__(self, path: Path, fingerprint: SettingsFingerprint, config_file: str, stored_config: Mapping[str, Any],
                 resume: bool, overwrite: bool,
                 check_inputs: Callable[[Path, Mapping[str, Any]], None] | None = None) -> None:
        self.path = Path(path)
        self.fingerprint = fingerprint
        self.config_file = config_file
        self.stored_config = dict(stored_config)
        self.resume = resume
        self.overwrite = overwrite
        self.check_inputs = check_inputs
        self.progress: dict[str, Any] = {"version": PROGRESS_VERSION, "completed": {}}

    # -- set-up -------------------------------------------------------------------------------------------
    @staticmethod
    def occupied(path: Path) -> bool:
        """Whether ``path`` holds anything: :meth:`prepare` then continues it (``resume``) or replaces it
        (``overwrite``) and refuses a fresh start. Experiment drivers resume exactly these directories (a run killed
        before its first phase completed holds only its fingerprint and config)."""
        path = Path(path)
        return path.exists() and any(path.iterdir())

    def starts_fresh(self) -> bool:
        """Whether :meth:`prepare` will start a new run (nothing there yet, or ``overwrite``)."""
        return self.overwrite or not self.occupied(self.path)

    def prepare(self) -> None:
        """Create a fresh run or check a resumed one (see the module docstring)."""
        exists = self.occupied(self.path)
        if exists and self.overwrite:
            logger.warning("--overwrite: removing %s", self.path)
            shutil.rmtree(self.path)
            exists = False
        elif exists and not self.resume:
            raise FileExistsError(
                f"{self.path} already exists; pass --resume=true to continue it or --overwrite=true to replace it")
        elif not exists and self.resume:
            raise FileNotFoundError(f"--resume=true but {self.path} holds no run to resume")
        if exists:
            self.check_settings_against_run()
            progress_path = self.path / PROGRESS_FILE
            if progress_path.exists():
                self.progress = read_checked_json(progress_path)
                if not isinstance(self.progress.get("completed"), dict):
                    raise CorruptFileError(progress_path, "cannot resume: no 'completed' phases recorded")
            # every sealed file, before anything is written (the fingerprint: checked above by read_fingerprint)
            verify_run_files(self.path, (*REGENERATED_FILES, self.config_file, *LEGACY_CONFIG_FILES, FINGERPRINT_FILE))
            self._remove_leftovers()
            return
        self.path.mkdir(parents=True, exist_ok=True)
        write_fingerprint(self.path / FINGERPRINT_FILE, self.fingerprint)
        atomic_write_json(self.path / self.config_file, self.stored_config)

    def check_settings_against_run(self) -> None:
        """Compare with the stored fingerprint: its inputs first (:attr:`check_inputs`), then every setting; raise
        :class:`~sr_imitation.infra.fingerprint.SettingsMismatchError` naming every differing key."""
        path = self.path / FINGERPRINT_FILE
        if not path.is_file():
            configs = (self.config_file, *LEGACY_CONFIG_FILES)
            if not any((self.path / c).is_file() for c in configs) and not (self.path / PROGRESS_FILE).is_file():
                raise FileNotFoundError(f"--resume=true but {self.path} holds no run to resume (no {FINGERPRINT_FILE})")
            raise CorruptFileError(path, "missing: cannot resume a run without its settings fingerprint (deleted, or "
                                         "not written by this code); start a new run in another output_dir")
        stored = read_fingerprint(path)
        if self.check_inputs is not None:
            self.check_inputs(path, stored)
        check_settings(path, stored, self.fingerprint)

    def _remove_leftovers(self) -> None:
        for pattern in TEMPORARY_PATTERNS:
            for leftover in sorted(self.path.rglob(pattern)):
                logger.info("removing %s (left by an interrupted write)", leftover)
                if leftover.is_dir() and not leftover.is_symlink():
                    shutil.rmtree(leftover)
                else:
                    leftover.unlink()

    # -- progress -----------------------------------------------------------------------------------------
    @staticmethod
    def key(k: int, phase: str) -> str:
        return f"{k + 1}.{phase}"

    def done(self, k: int, phase: str) -> bool:
        return self.key(k, phase) in self.progress["completed"]

    def record(self, k: int, phase: str) -> dict[str, Any]:
        return self.progress["completed"][self.key(k, phase)]

    def mark(self, k: int, phase: str, record: dict[str, Any]) -> None:
        """Record a completed phase (after its files are written)."""
        self.mark_all({self.key(k, phase): record})

    def mark_all(self, records: dict[str, dict[str, Any]]) -> None:
        """Record several completed phases (keyed as :meth:`key`) in one write of ``progress.json``."""
        self.progress["completed"].update(records)
        write_checked_json(self.path / PROGRESS_FILE, self.progress)
