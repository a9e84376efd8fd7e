"""A run directory that cannot change silently: settings fingerprint, stored config, progress, leftovers.

Fresh run: the directory is created, the settings fingerprint (:mod:`sr_imitation.infra.fingerprint`) and the stored
config are written once, in that order: the fingerprint is the start's commit point. Resume: the requested settings
are checked against the fingerprint *before anything is written* (a refused resume leaves the directory
byte-identical), ``progress.json`` is read, and temporary files left by a killed atomic write are removed. Nothing
stored at the start is ever rewritten; a start killed after its fingerprint and before its config (no phase
recorded) gets its config on resume, from the settings that have just matched the fingerprint
(:meth:`RunDirectory.start_unfinished`). A kill at any moment of the start thus leaves an empty directory or one
holding only the fingerprint's temporary file (a plain rerun starts there: :meth:`RunDirectory.occupied`), or a
fingerprinted run that resumes to the files of an uninterrupted one.

``progress.json`` records every completed phase under ``"<stage>.<phase>"`` (1-based stage), written atomically
after the phase's files, so a phase is either recorded with all its outputs or redone.

Overwrite (``--overwrite=true``) never deletes what a user owns. The directory is replaced only if it is a run of
this package, recognised by its own files (:func:`run_entries_problem`: its settings fingerprint, or the progress
and config of a run from before fingerprints, and nothing at its top level that no run writes), and only if it
neither is, holds, nor lies inside one of the run's inputs (:func:`check_not_an_input`). :meth:`RunDirectory.prepare`
runs after the substrate has checked every input; the old run is then renamed to a hidden sibling
(``.<name>.replaced-<time>``), deleted once the new run has recorded its first phase, and renamed back if the start
fails before that (:meth:`RunDirectory.restore_replaced`). A directory holding only what a killed atomic write
leaves (the fingerprint's temporary file) holds no run: a plain start proceeds there.
"""

from __future__ import annotations

import contextlib
import fnmatch
import logging
import os
import shutil
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

from sr_imitation.infra.cli_errors import note_run_started
from sr_imitation.infra.fingerprint import (
    FINGERPRINT_FILE,
    SettingsFingerprint,
    check_settings,
    check_stack,
    diff_settings,
    flatten_settings,
    is_allowed,
    read_fingerprint,
    write_fingerprint,
)
from sr_imitation.io import (
    JSON_CHECKSUM,
    CorruptFileError,
    WriteError,
    fsync_directory,
    read_checked_json,
    read_config_json,
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
"""Where older SAC runs stored their config (not sealed, not rewritten: read by ``--config_path``)."""
LAST_POINTER = "last"
"""``<run>/last``: the newest consolidated policy's checkpoint folder (LeRobot's ``checkpoints/last``)."""
TEMPORARY_PATTERNS = (".*.tmp", ".*.tmp.*", ".wake.*", ".sleep.*")
"""Names of what an interrupted atomic write leaves (temp files of ``atomic_write_bytes``, staging directories of
checkpoints): removed on resume, never read."""
RUN_ENTRIES = (FINGERPRINT_FILE, RUN_CONFIG_FILE, *LEGACY_CONFIG_FILES, PROGRESS_FILE, *REGENERATED_FILES,
               "results.md", "*.png", "log.jsonl", "wandb", "videos", LAST_POINTER, "memories", "stages",
               "skill_*_*", "stream_stats.safetensors", "agent.safetensors", "expert_suture.mp4", "resleep.json")
"""What a run of this package writes at its top level (fnmatch patterns: the stream engine's files, the ACT
substrate's ``skill_<k>_<skill>`` stage folders, ``memories/``, statistics and ``last`` link, the SAC substrate's
``stages/``, the oracles' ``agent.safetensors``, ``sr-main``'s expert video), besides :data:`TEMPORARY_PATTERNS`.
``--overwrite`` refuses a directory holding anything else: it is not only a run."""
REPLACED_MARK = ".replaced-"
"""``.<name>.replaced-<time>``: where ``--overwrite`` keeps the old run until the new one has recorded a phase."""


class OverwriteRefusedError(ValueError):
    """``--overwrite=true`` on a directory that is not a run of this package, or that holds the run's inputs: one
    line naming it; nothing was removed."""


def _inside(path: Path, directory: Path) -> bool:
    """Whether ``path`` is ``directory`` or below it (both resolved: links and ``..`` followed)."""
    path, directory = Path(path).resolve(), Path(directory).resolve()
    return path == directory or directory in path.parents


def check_not_an_input(path: Path, inputs: Iterable[Path], overwrite: bool) -> None:
    """Refuse an output directory that lies inside one of ``inputs`` (the run would write into its own data, whose
    content identity it records) or, with ``overwrite``, one that is or holds an input (replacing it would delete
    the data the run reads): :class:`OverwriteRefusedError` naming both."""
    for source in inputs:
        if source is None:
            continue
        source = Path(source)
        if source.exists() and _inside(path, source):
            raise OverwriteRefusedError(
                f"output_dir {path} lies inside the input {source}; choose an output_dir outside the run's inputs")
        if overwrite and _inside(source, path):
            raise OverwriteRefusedError(
                f"{path}: --overwrite=true refused: it holds the input {source}, which replacing it would delete; "
                "choose another output_dir (nothing was removed)")


START_LEFTOVER = f".{FINGERPRINT_FILE}.*.tmp"
"""The temporary file of a start killed while writing its fingerprint (the run's first file): a directory holding
only such files holds no run (:meth:`RunDirectory.occupied`)."""


def _is_temporary(name: str) -> bool:
    return any(fnmatch.fnmatchcase(name, pattern) for pattern in TEMPORARY_PATTERNS)


def few_names(names: Sequence[str], most: int = 3) -> str:
    """``a, b, c and 4 more``: the first ``most`` of ``names`` for a one-line message."""
    extra = len(names) - most
    return ", ".join(names[:most]) + (f" and {extra} more" if extra > 0 else "")


def run_entries_problem(path: Path, entries: Iterable[str] = ()) -> str | None:
    """Why the occupied directory ``path`` is not recognisably a run of this package (``None`` if it is): it holds
    neither a settings fingerprint nor the progress and config of a run written before fingerprints, or it holds
    an entry no run writes (:data:`RUN_ENTRIES`, and ``entries``: patterns another substrate writes)."""
    patterns = (*RUN_ENTRIES, *entries)
    path = Path(path)
    if not path.is_dir() or path.is_symlink():
        return "not a directory"
    names = sorted(p.name for p in path.iterdir())
    has_config = any(n in names for n in (RUN_CONFIG_FILE, *LEGACY_CONFIG_FILES))
    if FINGERPRINT_FILE not in names and not (PROGRESS_FILE in names and has_config):
        return f"it holds no {FINGERPRINT_FILE}, so it is not a run of this package"
    foreign = [n for n in names if not _is_temporary(n) and not any(fnmatch.fnmatchcase(n, p) for p in patterns)]
    if foreign:
        return f"it holds {few_names(foreign)}, which no run writes"
    return None


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


def check_run_config(run: Path, config_file: str = RUN_CONFIG_FILE, ignore: Sequence[str] | None = None
                     ) -> dict[str, Any] | None:
    """``<run>/<config_file>`` (``train_config.json``), checked as a resume checks it, for every reader (resume,
    ``status``, ``compare``, ``summary``); ``None`` if the run has none (started before the file existed). A sealed
    one must match its seal; one written before configs were sealed must hold the settings of the run's fingerprint
    where it has one (an edit there would otherwise be reported as what the run trained with), compared on every
    setting but ``ignore`` (patterns; by default the allow-list and derived settings the fingerprint file records).
    :class:`~sr_imitation.io.CorruptFileError` naming the file."""
    path = Path(run) / config_file
    if not path.is_file():
        return None
    config, sealed = read_config_json(path)
    fingerprint = Path(run) / FINGERPRINT_FILE
    if not sealed and fingerprint.is_file():
        stored = read_fingerprint(fingerprint)
        if ignore is None:
            recorded = read_json(fingerprint)
            ignore = (*recorded.get("allow_list", ()), *recorded.get("derived", ()))
        written = {k: v for k, v in flatten_settings(config).items() if not is_allowed(k, ignore)}
        diffs = diff_settings({k: v for k, v in stored.items() if not is_allowed(k, ignore)}, written)
        if diffs:
            raise CorruptFileError(path, f"differs from {FINGERPRINT_FILE} in {', '.join(sorted(diffs)[:4])} "
                                         "(edited since the run started); restore it or start a new run")
    return config


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
            :func:`sr_imitation.substrates.act.dataset_identity.check_inputs`).
        inputs: the paths the run reads (datasets, a run it extends): the directory may not lie inside one, nor, to
            be replaced, be or hold one (:func:`check_not_an_input`).
        entries: top-level names (fnmatch patterns) the substrate writes beyond :data:`RUN_ENTRIES`, for
            recognising a run ``overwrite`` may replace.

    A directory without ``settings_fingerprint.json`` is never resumed: the fingerprint is written first, before
    anything else, so its absence means the run was not made by this code or the file was deleted (one line naming
    it; its settings are never re-created from the stored config, which is not sealed).
    """

    def __init__(self, path: Path, fingerprint: SettingsFingerprint, config_file: str, stored_config: Mapping[str, Any],
                 resume: bool, overwrite: bool,
                 check_inputs: Callable[[Path, Mapping[str, Any]], None] | None = None,
                 inputs: Sequence[Path | None] = (), entries: Sequence[str] = ()) -> None:
        self.path = Path(path)
        self.fingerprint = fingerprint
        self.config_file = config_file
        self.stored_config = dict(stored_config)
        self.resume = resume
        self.overwrite = overwrite
        self.check_inputs = check_inputs
        self.inputs = [Path(p) for p in inputs if p is not None]
        self.entries = tuple(entries)
        self.progress: dict[str, Any] = {"version": PROGRESS_VERSION, "completed": {}}
        self.replaced: Path | None = None
        """The old run ``--overwrite`` renamed aside, until the new run records its first phase."""

    # -- set-up -------------------------------------------------------------------------------------------
    @staticmethod
    def occupied(path: Path) -> bool:
        """Whether ``path`` holds anything but the temporary fingerprint of a start killed while writing it
        (:data:`START_LEFTOVER`: such a run has not started): :meth:`prepare`
        then continues it (``resume``) or replaces it (``overwrite``) and refuses a fresh start. Experiment drivers
        resume exactly these directories (a run killed before its first phase completed holds only its fingerprint
        and config)."""
        path = Path(path)
        if not path.is_dir():
            return path.exists() or path.is_symlink()
        return any(not fnmatch.fnmatchcase(p.name, START_LEFTOVER) for p in path.iterdir())

    @staticmethod
    def set_aside_runs(path: Path) -> list[Path]:
        """Old runs ``--overwrite`` renamed aside beside ``path`` (``.<name>.replaced-*``) and left there: a start
        killed between the rename and its first phase."""
        path = Path(path)
        return sorted(path.parent.glob(f".{path.name}{REPLACED_MARK}*")) if path.parent.is_dir() else []

    def starts_fresh(self) -> bool:
        """Whether :meth:`prepare` will start a new run (nothing there yet, or ``overwrite``)."""
        return self.overwrite or not self.occupied(self.path)

    def prepare(self) -> None:
        """Create a fresh run or check a resumed one (see the module docstring). Call it after every input was
        checked: with ``overwrite`` the old run is renamed aside here (:meth:`restore_replaced` undoes it)."""
        exists = self.occupied(self.path)
        check_not_an_input(self.path, self.inputs, self.overwrite and exists)
        for aside in self.set_aside_runs(self.path):
            logger.warning("%s holds a run an earlier --overwrite start set aside and did not get to delete or put "
                           "back (that start was killed); it is kept: rename it back to %s or remove it yourself",
                           aside, self.path.name)
        if exists and self.overwrite:
            problem = run_entries_problem(self.path, self.entries)
            if problem is not None:
                raise OverwriteRefusedError(f"{self.path}: --overwrite=true refused: {problem}; remove or move it "
                                            "yourself, or choose another output_dir (nothing was removed)")
            self._set_aside()
            exists = False
        elif exists and not self.resume:
            raise FileExistsError(self.exists_message())
        elif not exists and self.resume:
            raise FileNotFoundError(f"--resume=true but {self.path} holds no run to resume")
        if exists:
            self.check_settings_against_run()
            progress_path = self.path / PROGRESS_FILE
            if progress_path.exists():
                self.progress = read_checked_json(progress_path)
                if not isinstance(self.progress.get("completed"), dict):
                    raise CorruptFileError(progress_path, "cannot resume: no 'completed' phases recorded")
            self.check_stored_config()
            # every sealed file, before anything is written (the fingerprint: checked above by read_fingerprint)
            verify_run_files(self.path, (*REGENERATED_FILES, self.config_file, *LEGACY_CONFIG_FILES, FINGERPRINT_FILE))
            self._remove_leftovers()
            self._finish_start()
            note_run_started(self.path)
            return
        with self.undo_on_error():
            try:
                self.path.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise WriteError(self.path, exc) from exc
            for leftover in sorted(self.path.glob(START_LEFTOVER)):  # a start killed while writing the fingerprint
                leftover.unlink()
            write_fingerprint(self.path / FINGERPRINT_FILE, self.fingerprint)
            note_run_started(self.path)
            write_checked_json(self.path / self.config_file, self.stored_config)

    def exists_message(self) -> str:
        """Why a fresh start in the occupied ``path`` is refused, naming only the flags that would work: resume and
        overwrite for a run (its settings fingerprint is there), overwrite for what ``--overwrite`` may replace,
        neither for a folder of other files.

        Returns:
            The one-line refusal.
        """
        if (self.path / FINGERPRINT_FILE).is_file():
            return f"{self.path} already exists; pass --resume=true to continue it or --overwrite=true to replace it"
        problem = run_entries_problem(self.path, self.entries)
        if problem is None:
            return f"{self.path} already exists and holds no run to resume; pass --overwrite=true to replace it"
        return f"{self.path} already exists and holds no run ({problem}); choose another output_dir"

    def start_unfinished(self) -> bool:
        """Whether the run's start was killed after its fingerprint and before its stored config was in place: it
        holds no config of any name (:data:`LEGACY_CONFIG_FILES` included) and has recorded no phase. A run that
        recorded a phase without a config is one from before the file existed, and keeps its layout."""
        configs = (self.config_file, *LEGACY_CONFIG_FILES)
        return not any((self.path / c).is_file() for c in configs) and not (self.path / PROGRESS_FILE).exists()

    def _finish_start(self) -> None:
        """Write the stored config a start killed before it left out (:meth:`start_unfinished`), from this resume's
        settings, which have just matched the fingerprint: the fingerprint is the start's commit point, and the
        config holds nothing the fingerprint does not fix but the allow-listed, per-invocation settings, so the run
        ends with the same files as an uninterrupted one resumed with the same flags."""
        if not self.start_unfinished():
            return
        logger.warning("%s: its start was interrupted before %s was written; writing it now from the resumed "
                       "settings (they match %s)", self.path, self.config_file, FINGERPRINT_FILE)
        write_checked_json(self.path / self.config_file, self.stored_config)

    def _set_aside(self) -> None:
        """Rename the old run to a hidden sibling (:data:`REPLACED_MARK`), kept until the new run records a phase."""
        stamp = time.strftime("%Y%m%dT%H%M%S")
        aside = self.path.with_name(f".{self.path.name}{REPLACED_MARK}{stamp}-{os.getpid()}")
        try:
            os.replace(self.path, aside)
            fsync_directory(self.path.parent)
        except OSError as exc:
            raise WriteError(self.path, exc, "nothing was removed") from exc
        logger.warning("--overwrite: %s renamed to %s; it is deleted once the new run has recorded its first phase "
                       "and renamed back if the start fails", self.path, aside.name)
        self.replaced = aside

    def restore_replaced(self) -> None:
        """Undo :meth:`_set_aside` after a failed start: the new run's files are removed and the old run renamed back
        (nothing if no run was set aside, or the new run already recorded a phase)."""
        if self.replaced is None:
            return
        aside, self.replaced = self.replaced, None
        shutil.rmtree(self.path, ignore_errors=True)
        os.replace(aside, self.path)
        fsync_directory(self.path.parent)
        logger.warning("the new run did not start; %s restored as it was", self.path)

    @contextlib.contextmanager
    def undo_on_error(self) -> Iterator[None]:
        """Run a block (the start of a run); if it raises before the first phase is recorded, the run that
        ``--overwrite`` set aside is restored (:meth:`restore_replaced`)."""
        try:
            yield
        except BaseException:
            self.restore_replaced()
            raise

    def _drop_replaced(self) -> None:
        if self.replaced is not None:
            aside, self.replaced = self.replaced, None
            shutil.rmtree(aside, ignore_errors=True)
            logger.info("--overwrite: the replaced run %s deleted (the new run recorded its first phase)", aside.name)

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
        check_stack(path, stored, self.fingerprint)
        if self.check_inputs is not None:
            self.check_inputs(path, stored)
        check_settings(path, stored, self.fingerprint)

    def check_stored_config(self) -> dict[str, Any] | None:
        """The run's stored config (``train_config.json``), checked before a resume writes anything
        (:func:`check_run_config`, with this run's allow-list and derived settings)."""
        return check_run_config(self.path, self.config_file, (*self.fingerprint.allow, *self.fingerprint.derived))

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
        self._drop_replaced()
