"""One writer per run or output folder: an exclusive OS lock (``flock``) on ``.<name>.lock`` beside the folder."""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import json
import logging
import os
import re
import shlex
import shutil
import socket
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

from sr_imitation.io import WriteError

logger = logging.getLogger(__name__)

LOCK_SUFFIX = ".lock"
"""``.<name>.lock``: the lock of the folder ``<name>``, in the folder's parent (outside the folder, so that neither
the run's own entries (:func:`sr_imitation.stream.rundir.run_entries_problem`) nor its checksums see it, and so that
``--overwrite``, which renames the folder aside, cannot move the lock with it). Code that removes hidden leftovers
beside a folder (``.<name>.*``) must leave it alone: :func:`is_lock_file`."""

@dataclasses.dataclass
class _Hold:
    """One lock this process holds: its open file, how many holds are open (a command that locks its folder and then
    runs a stream that locks it again holds it once), and the folders above it that taking it made."""

    fd: int
    depth: int
    made: list[Path]


_HELD: dict[Path, _Hold] = {}
"""Lock path -> the hold of each lock this process holds."""
_HELD_GUARD = threading.Lock()


class FolderBusyError(ValueError):
    """Another process holds the folder's lock: one line naming the folder and the holder; nothing was written."""


def lock_path(folder: str | os.PathLike[str]) -> Path:
    """The lock file of ``folder``: ``<parent>/.<name>.lock``, with the parent resolved (links and ``..`` followed),
    so that every spelling of the same folder has the same lock.

    Args:
        folder: the run or output folder (it need not exist).

    Returns:
        The lock file's path.
    """
    folder = Path(os.path.abspath(folder))
    return folder.parent.resolve() / f".{folder.name}{LOCK_SUFFIX}"


def is_lock_file(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` names a folder lock (``.<name>.lock``).

    Args:
        path: a file name or path.

    Returns:
        True for a lock file's name.
    """
    name = Path(path).name
    return name.startswith(".") and name.endswith(LOCK_SUFFIX) and len(name) > 1 + len(LOCK_SUFFIX)


def holder_record(command: str | None = None) -> dict[str, object]:
    """What a lock file records about its holder (for the refusal of a second writer).

    Args:
        command: the command's name (``sr-train``); by default the program's (``sys.argv[0]``'s file name).

    Returns:
        The pid, host, command name, command line and start time of this process.
    """
    command = command or Path(sys.argv[0]).name or "python"
    return {"pid": os.getpid(), "host": socket.gethostname(), "command": command,
            "argv": shlex.join(sys.argv), "since": time.strftime("%Y-%m-%d %H:%M:%S")}


def describe_holder(text: str) -> str:
    """A one-line description of a lock file's holder record (``text``: the file's content).

    Args:
        text: what the holder wrote into the lock file (possibly empty: it has not written it yet).

    Returns:
        ``pid 123 on host (sr-train --output_dir=x, since ...)``, or a phrase for a record not (yet) readable.
    """
    try:
        record = json.loads(text)
    except ValueError:
        return "another process (it has not recorded itself yet)"
    if not isinstance(record, dict):
        return "another process (its record is unreadable)"
    argv = " ".join(str(record.get("argv", "")).split())
    return (f"{record.get('command', 'a command')} (pid {record.get('pid', '?')} on {record.get('host', '?')}, "
            f"since {record.get('since', '?')}: {argv})")


def _open_locked(path: Path, folder: Path) -> int:
    """Open and lock ``path`` without waiting; retried while the file it locked is no longer the one at ``path`` (a
    holder that released it removed it in between), or while the folder holding ``path`` vanishes (a holder that
    made it removed it, empty, as it gave the lock back).

    Args:
        path: the lock file.
        folder: the folder it locks (for the message).

    Returns:
        The locked file descriptor.

    Raises:
        FolderBusyError: another process holds the lock.
        WriteError: the lock file cannot be created.
    """
    vanished = 0
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        except FileNotFoundError as exc:
            vanished += 1
            if vanished > 10:
                raise WriteError(path, exc, f"cannot lock {folder}; nothing was written") from exc
            _make_parents(path, folder)
            continue
        except OSError as exc:
            raise WriteError(path, exc, f"cannot lock {folder}; nothing was written") from exc
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = describe_holder(_read_record(fd))
            os.close(fd)
            raise FolderBusyError(f"{folder}: in use by {holder}; wait for it to finish or stop it, then run this "
                                  f"again (lock: {path}; nothing was written)") from None
        if _same_file(fd, path):
            return fd
        os.close(fd)  # removed (and perhaps made again) by a holder that just released it: lock the current file


def _make_parents(path: Path, folder: Path) -> list[Path]:
    """Make the folders above the lock file ``path`` that are missing; returns them, deepest first.

    Args:
        path: the lock file.
        folder: the folder it locks (for the message).

    Returns:
        The folders made.

    Raises:
        WriteError: one cannot be made (a file in the way, no permission).
    """
    missing = [p for p in (path.parent, *path.parent.parents) if not p.exists()]
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise WriteError(path.parent, exc, f"cannot lock {folder}; nothing was written") from exc
    return missing


def _remove_made(made: list[Path]) -> None:
    """Remove the folders :func:`_make_parents` made that are still empty (deepest first): a command refused or
    failed before writing its folder leaves no empty folders behind."""
    for folder in made:
        try:
            folder.rmdir()
        except OSError:
            return  # not empty (the run was written there) or gone: the folders above hold it too


def _read_record(fd: int) -> str:
    """The holder's record in a lock file, read once more after a moment if still empty (the holder writes it right
    after locking)."""
    for _ in range(20):
        text = os.pread(fd, 65536, 0).decode("utf-8", "replace")
        if text.strip():
            return text
        time.sleep(0.01)
    return ""


def _same_file(fd: int, path: Path) -> bool:
    """Whether ``path`` still names the open file ``fd``."""
    try:
        on_disk = os.stat(path)
    except FileNotFoundError:
        return False
    opened = os.fstat(fd)
    return (on_disk.st_dev, on_disk.st_ino) == (opened.st_dev, opened.st_ino)


def check_folder_path(folder: str | os.PathLike[str]) -> None:
    """``folder`` can be a folder: neither it nor a folder above it is a file (or anything else but a folder).

    Args:
        folder: a run or output folder about to be written (it need not exist).

    Raises:
        NotADirectoryError: one line naming ``folder`` and the file in the way, before anything is written (instead
            of an ``[Errno 20]`` once the command's work is done, or a resume hint for a run that cannot exist).
    """
    folder = Path(os.path.abspath(folder))
    for path in (folder, *folder.parents):
        if path.exists() and not path.is_dir():
            what = "is a file" if path == folder else f"lies in {path}, which is a file"
            raise NotADirectoryError(f"{folder}: {what}, not a folder; choose another output folder (nothing was "
                                     "written)")
        if path.is_dir():
            return


def acquire(folder: str | os.PathLike[str], command: str | None = None) -> Path:
    """Take the lock of ``folder`` for this process (again, if it holds it already: counted, see :func:`release`).

    Args:
        folder: the run or output folder about to be written; its parent is made if missing (and removed again by
            :func:`release` if nothing was written there).
        command: the command's name, recorded for the refusal of a second writer (default: the program's).

    Returns:
        The lock file's path (the key :func:`release` takes).

    Raises:
        FolderBusyError: another process holds the lock (one line naming the folder and the holder).
        NotADirectoryError: ``folder`` or a folder above it is a file (:func:`check_folder_path`).
        WriteError: the parent folder or the lock file cannot be made.
    """
    path = lock_path(folder)
    with _HELD_GUARD:
        if path in _HELD:
            _HELD[path].depth += 1
            return path
        check_folder_path(folder)
        made = _make_parents(path, Path(folder))
        try:
            fd = _open_locked(path, Path(folder))
        except BaseException:
            _remove_made(made)
            raise
        record = json.dumps(holder_record(command)).encode()
        os.ftruncate(fd, 0)
        os.pwrite(fd, record, 0)
        _HELD[path] = _Hold(fd, 1, made)
        return path


def release(path: Path) -> None:
    """Give back one hold of the lock :func:`acquire` returned ``path`` for; the last one removes the lock file (while
    still holding it, so that a process waiting on the old file retries on a new one), unlocks it, and removes the
    folders above it that :func:`acquire` made if they are still empty.

    Args:
        path: the lock file's path, as :func:`acquire` returned it.
    """
    with _HELD_GUARD:
        held = _HELD.get(path)
        if held is None:
            return
        held.depth -= 1
        if held.depth > 0:
            return
        del _HELD[path]
        with contextlib.suppress(FileNotFoundError):
            path.unlink()
        os.close(held.fd)  # closing the last descriptor of the open file unlocks it
        _remove_made(held.made)


@contextlib.contextmanager
def hold_folder(folder: str | os.PathLike[str], command: str | None = None) -> Iterator[Path]:
    """The block runs as the only writer of ``folder``: its lock (:func:`acquire`) is taken before the block and given
    back after it, whatever happens; a killed process gives it back too (the OS drops its locks). A second process
    asking for the same folder meanwhile is refused (:class:`FolderBusyError`) before it writes anything.

    Args:
        folder: the run or output folder.
        command: the command's name (``sr-train``), recorded in the lock file (default: the program's).

    Returns:
        A context manager yielding the lock file's path.
    """
    path = acquire(folder, command)
    try:
        yield path
    finally:
        release(path)


def holds(folder: str | os.PathLike[str]) -> bool:
    """Whether this process holds the lock of ``folder``.

    Args:
        folder: the run or output folder.

    Returns:
        True while a :func:`hold_folder` block (or :func:`acquire`) of this process holds it.
    """
    with _HELD_GUARD:
        return lock_path(folder) in _HELD


MKDTEMP_SUFFIX = r"[a-z0-9_]{8}"
"""What ``tempfile.mkdtemp`` appends to its prefix (a regular expression): the staging folders' random part."""


def leftovers(where: str | os.PathLike[str], pattern: str) -> list[Path]:
    """The entries of the folder ``where`` whose names match the regular expression ``pattern`` entirely, never a
    lock file (:func:`is_lock_file`).

    Args:
        where: the folder to look in (missing: none).
        pattern: a regular expression for a whole name (``\\.out\\.[a-z0-9_]{8}``).

    Returns:
        Their paths, sorted.
    """
    where = Path(where)
    if not where.is_dir():
        return []
    regex = re.compile(pattern)
    return sorted(p for p in where.iterdir() if regex.fullmatch(p.name) and not is_lock_file(p))


def remove_leftovers(folder: str | os.PathLike[str], where: str | os.PathLike[str], pattern: str,
                     command: str) -> list[Path]:
    """Remove what a killed earlier ``command`` on ``folder`` left in ``where`` (``pattern``: :func:`leftovers`),
    each in one log line, or one warning line naming what cannot be removed. Only while this process holds
    ``folder``'s lock: a live writer's staging folder is its own (it holds the lock), so one found by the lock's
    holder was left by a process that died; without the lock nothing is touched.

    Args:
        folder: the output folder whose lock this process must hold.
        where: the folder the leftovers lie in (``folder``'s parent for staging folders beside it, or ``folder``).
        pattern: a regular expression for a leftover's whole name.
        command: the command that left them, for the log line (``sr-sleep``).

    Returns:
        The leftovers removed.
    """
    if not holds(folder):
        return []
    removed = []
    for path in leftovers(where, pattern):
        try:
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path)
            else:
                path.unlink()
        except OSError as exc:
            logger.warning("%s: cannot remove what a killed earlier %s left (%s); remove it yourself", path, command,
                           exc.strerror or exc)
            continue
        logger.info("%s: removed, left by a killed earlier %s", path, command)
        removed.append(path)
    return removed


def remove_staging_beside(folder: str | os.PathLike[str], command: str) -> list[Path]:
    """:func:`remove_leftovers` of the staging folders ``.<name>.XXXXXXXX`` that
    :func:`sr_imitation.io.staged_directory` builds ``folder`` in, beside it (never its lock ``.<name>.lock``).

    Args:
        folder: the output folder (its lock held by this process).
        command: the command that builds it (``sr-sleep``).

    Returns:
        The staging folders removed.
    """
    folder = Path(os.path.abspath(folder))
    return remove_leftovers(folder, folder.parent, rf"\.{re.escape(folder.name)}\.{MKDTEMP_SUFFIX}", command)
