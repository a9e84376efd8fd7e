"""One-line errors for the command-line programs.

A user error (a bad flag value, a missing or damaged file, a refused resume, a dataset that does not fit) is
reported as ``<prog>: error: <message>`` on stderr with exit status 2, without a traceback; ``--debug`` (or
``SR_DEBUG=1``) re-raises it with the full traceback. Errors raised while draccus builds the config arrive wrapped
(``ParsingError: Couldn't instantiate class ...``); the message shown is the innermost one, which names the key.
Anything else (a bug) keeps its traceback. A :class:`UsageError` (a flag the command does not know, a choice outside
its list: :mod:`sr_imitation.infra.cli_parsing`) is one line with a pointer to ``--help`` instead of argparse's usage
dump.
"""

from __future__ import annotations

import errno
import logging
import os
import re
import shlex
import sys
from collections.abc import Callable, Sequence
from typing import TypeVar

from sr_imitation.infra.torchcodec_notice import quiet_torchcodec
from sr_imitation.io import CorruptFileError, WriteError

USER_ERRORS: tuple[type[BaseException], ...] = (ValueError, FileExistsError, FileNotFoundError, PermissionError,
                                                IsADirectoryError, NotADirectoryError, CorruptFileError, WriteError)
"""What counts as a user error (``ValueError`` includes settings mismatches, invalid values, dataset mismatches)."""

T = TypeVar("T")

DISK_FULL = (errno.ENOSPC, errno.EDQUOT)
"""Errors of a full disk or an exhausted quota: reported as one line naming the file, whatever wrote it."""
DISK_FULL_ADVICE = ("free space, then continue with --resume=true (a phase is recorded only once all its files are "
                    "written, so the interrupted one is redone)")
"""The advice of a full disk; ``continue with --resume=true`` in it (and in ``WriteError.RESUME_ADVICE``) becomes
what the command that failed can do (:func:`next_step`)."""

RESUME_FLAGS = {"sr-train": "--resume", "sr-rl-train": "--resume", "sr-main": "--train.resume"}
"""The flag that continues an interrupted run, of each command that has one (the others have none)."""

FLAG_NAMES = {"sr-main": {"--resume": "--train.resume", "--overwrite": "--train.overwrite",
                          "--output_dir": "--train.output_dir"}}
"""A command's own names of the flags that messages shared with ``sr-train`` name (``sr-main`` sets them in its
train section)."""

CONTINUE = "continue with --resume=true"
"""The phrase of a shared message that :func:`next_step` replaces."""

_started: list[str] = []
"""The run folders this process started or resumed (:func:`note_run_started`): only then is a resume possible."""


def note_run_started(folder: str | os.PathLike[str]) -> None:
    """Record that ``folder`` now holds a run (its settings fingerprint is written or was checked), so that an
    interruption or a failed write suggests resuming it.

    Args:
        folder: the run folder.
    """
    _started.append(str(folder))


def next_step(prog: str, args: Sequence[str]) -> str | None:
    """What a user can do after ``prog`` stopped on an interruption or a failed write, as a pasteable command with
    every value shell-quoted, or ``None`` where no command would do what it says.

    Args:
        prog: the command's name (``sr-train``).
        args: its command line (without ``--debug``).

    Returns:
        ``continue with: sr-train ... --resume=true`` for a command with a resume flag once its run exists (every
        ``--resume`` / ``--overwrite`` flag given replaced by the resume flag); ``run it again: ...`` for such a
        command before its run exists and for ``sr-grid`` (finished runs are skipped, the others resume); else
        ``None``.
    """
    flag = RESUME_FLAGS.get(prog)
    if flag is not None and _started:
        names = {flag, FLAG_NAMES.get(prog, {}).get("--overwrite", "--overwrite")}
        kept = [a for a in args if a.split("=", 1)[0] not in names]
        return "continue with: " + shlex.join([prog, *kept, f"{flag}=true"])
    if flag is not None or prog == "sr-grid":
        return "run it again: " + shlex.join([prog, *args])
    return None


def own_flag_names(prog: str, message: str) -> str:
    """``message`` with the flags it names as ``sr-train`` does spelled as ``prog`` spells them (:data:`FLAG_NAMES`).

    Args:
        prog: the command that prints it.
        message: a message shared with ``sr-train``.

    Returns:
        The message in ``prog``'s flag names; a message that names a command (``... with sr-record``) is kept as it
        is: its flags are that command's.
    """
    if re.search(r"\bsr-[a-z]", message):
        return message
    for flag, own in FLAG_NAMES.get(prog, {}).items():
        message = re.sub(rf"(?<![\w.-]){re.escape(flag)}(?=[=\s,;)]|$)", own, message)
    return message


def _with_next_step(prog: str, args: Sequence[str], message: str) -> str:
    """``message`` with its ``continue with --resume=true`` (in ``sr-train``'s or ``prog``'s flag names) replaced by
    :func:`next_step`, or dropped where there is none."""
    phrase = next((p for p in (CONTINUE, own_flag_names(prog, CONTINUE)) if p in message), None)
    if phrase is None:
        return message
    step = next_step(prog, args)
    if step is None:
        return message.replace(f" and {phrase}", "").replace(f", then {phrase}", "").replace(phrase, "")
    return message.replace(phrase, step)


class UsageError(ValueError):
    """A command line the parser refuses (unknown flag, choice outside its list, flag without its value): printed as
    one line and a pointer to ``--help``."""


def _next(exc: BaseException) -> BaseException | None:
    """The exception ``exc`` was raised from (``raise ... from None`` ends the chain)."""
    return exc.__cause__ or (None if exc.__suppress_context__ else exc.__context__)


def _user_error(exc: BaseException) -> BaseException | None:
    """The innermost user error in ``exc``'s cause chain (draccus wraps __post_init__ errors), or None; an error that
    names its file (:class:`~sr_imitation.io.CorruptFileError`, :class:`~sr_imitation.io.WriteError`) is taken as it
    is, not the parser's or the system's error it was raised from (``JSONDecodeError`` names no file)."""
    found = None
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, (CorruptFileError, WriteError)):
            return exc
        if isinstance(exc, OSError) and exc.errno in DISK_FULL:  # a write outside the atomic helpers (a log, a
            return WriteError(exc.filename or "a file of the run", exc, DISK_FULL_ADVICE)  # third-party save)
        if isinstance(exc, USER_ERRORS) or type(exc).__module__.startswith(("draccus", "yaml")):
            found = exc
        exc = _next(exc)
    return found


def _yaml_message(exc: BaseException) -> str | None:
    """A flag value draccus could not read as YAML (``--tests=[sr`` after the shell took ``>wake_only]`` as a
    redirection): the value and what the YAML parser expected, instead of its multi-line report."""
    if not type(exc).__module__.startswith("yaml"):
        return None
    mark = getattr(exc, "problem_mark", None)
    value = str(getattr(mark, "buffer", "") or "").rstrip("\0")
    return (f"a flag value is not valid YAML: {value!r} ({getattr(exc, 'problem', None) or exc}); quote a value "
            "that holds shell characters (> < ! | & ; or spaces), e.g. '--tests=[sr>wake_only]'")


def _decoding_key(exc: BaseException | None) -> str | None:
    """The dotted key of the deepest draccus ``DecodingError`` in ``exc``'s chain (the setting being decoded)."""
    key, seen = None, set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        path = getattr(exc, "key_path", None)
        if type(exc).__module__.startswith("draccus") and path:
            key = ".".join(str(p) for p in path)
        exc = _next(exc)
    return key


def split_config_path(args: Sequence[str]) -> tuple[str | None, list[str]]:
    """Remove ``--config_path=<file>`` (or ``--config_path <file>``) from ``args``; returns (path or None, rest)."""
    path, rest = None, []
    args = list(args)
    i = 0
    while i < len(args):
        arg = args[i]
        if arg.startswith("--config_path="):
            path = arg.split("=", 1)[1]
        elif arg == "--config_path" and i + 1 < len(args):
            path = args[i + 1]
            i += 1
        else:
            rest.append(arg)
        i += 1
    return path, rest


def split_debug(args: Sequence[str]) -> tuple[bool, list[str]]:
    """Remove ``--debug`` / ``--debug=true|false`` from ``args``; returns (debug, rest)."""
    debug, rest = os.environ.get("SR_DEBUG", "") not in ("", "0"), []
    for arg in args:
        if arg in ("--debug", "--debug=true", "--debug=True"):
            debug = True
        elif arg in ("--debug=false", "--debug=False"):
            debug = False
        else:
            rest.append(arg)
    return debug, rest


LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
"""The one format of every command's log lines."""


def setup_logging(level: int = logging.INFO) -> None:
    """The one logging set-up of every command (``main()`` of each console script and ``python -m`` module).

    Importing LeRobot calls ``logging.debug`` at module level (``lerobot.utils.import_utils``), and a module-level
    logging call with no handler installed runs ``logging.basicConfig()``: a WARNING-level root logger with the
    default format, before any command starts. ``basicConfig(level=INFO)`` alone then does nothing, and until
    2026-11-26 every INFO line of every command was lost (a two-hour run logged nothing but its bars). So the
    handler that implicit call installed is replaced and the root level is set; handlers anyone else installed
    (pytest's, an application's) are kept.
    """
    root = logging.getLogger()
    for handler in list(root.handlers):
        implicit = (type(handler) is logging.StreamHandler and handler.formatter is not None
                    and handler.formatter._fmt == logging.BASIC_FORMAT)
        if implicit:
            root.removeHandler(handler)
    logging.basicConfig(level=level, format=LOG_FORMAT)  # does nothing while other handlers remain
    root.setLevel(level)
    logging.getLogger("OpenGL.acceleratesupport").setLevel(logging.WARNING)  # "No OpenGL_accelerate module" each run
    quiet_torchcodec()  # a missing FFmpeg: one line, not LeRobot's ~100 lines of loader errors


def run_cli[T](prog: str, main: Callable[[list[str]], T], args: Sequence[str] | None = None) -> T:
    """Run ``main(args)`` (``sys.argv[1:]`` by default), turning user errors into one line and exit status 2."""
    debug, rest = split_debug(list(sys.argv[1:] if args is None else args))
    _started.clear()
    try:
        return main(rest)
    except KeyboardInterrupt:
        step = next_step(prog, rest)
        sys.stderr.write(f"{prog}: interrupted{'' if step is None else f'; {step}'}\n")
        raise SystemExit(130) from None
    except Exception as exc:
        user = _user_error(exc)
        if user is None or debug:
            raise
        message = " ".join((_yaml_message(user) or str(user)).split())  # one line
        message = _with_next_step(prog, rest, own_flag_names(prog, message))
        key = _decoding_key(exc)
        if key and not message.startswith(("`", key)):
            message = f"{key}: {message}"  # draccus knew which setting it was decoding
        if isinstance(user, UsageError):
            sys.stderr.write(f"{prog}: error: {message} ({prog} --help lists every flag)\n")
        else:
            sys.stderr.write(f"{prog}: error: {message} (--debug shows the traceback)\n")
        raise SystemExit(2) from None
