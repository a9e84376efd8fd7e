"""The ``--config_path`` file of a command line, read and checked in one place and handed on parsed.

:func:`read_config_file` is the only reader of the file: every user error in it is one line naming the file (it
cannot be read, is not JSON, not a JSON object, or a run's ``train_config.json`` does not match its seal). What it
returns, a :class:`ConfigFile`, goes to the command's own checks, its substrate's parser and draccus (which is given
the settings, never the path: :func:`sr_imitation.infra.cli_parsing.parse_command`). ``sr-train`` reads the file
before it knows the substrate; :func:`config_scope` hands that reading to the substrate's parser, which asks for the
path it was given (:func:`config_file`).
"""

from __future__ import annotations

import contextlib
import contextvars
import json
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sr_imitation.infra.cli_errors import split_config_path
from sr_imitation.io import unsealed


@dataclass(frozen=True)
class ConfigFile:
    """A ``--config_path`` file as :func:`read_config_file` read it."""

    path: Path
    """Where it is (errors name it; a run's own file locates the run:
    :func:`~sr_imitation.infra.fingerprint.output_dir_for`)."""
    settings: dict[str, Any]
    """Its JSON object (a run's seal left out): the keys the file sets."""
    sealed: bool = False
    """Whether it is a run's own ``train_config.json`` (sealed by the run, with every setting the run had), not a
    file a person wrote."""

    @property
    def is_main_job_preset(self) -> bool:
        """Whether it is an ``sr-main`` preset (``record`` and ``train`` sections)."""
        return "train" in self.settings and "record" in self.settings

    @property
    def run_settings(self) -> dict[str, Any]:
        """The run's settings: an ``sr-main`` preset's ``train`` section, else the whole file."""
        train = self.settings.get("train")
        return train if self.is_main_job_preset and isinstance(train, dict) else self.settings


def read_config_file(path: str | os.PathLike[str]) -> ConfigFile:
    """The only reader of a ``--config_path`` file: its JSON object, checked.

    Args:
        path: the file.

    Returns:
        The file's settings (a run's ``train_config.json`` checked against its seal, the seal left out).

    Raises:
        FileNotFoundError: one line naming the file when it cannot be read.
        ValueError: one line naming the file when it is not JSON.
        CorruptFileError: one line naming the file when it is not a JSON object or does not match its seal.
    """
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        raise FileNotFoundError(f"{path}: cannot read the config file ({exc.strerror or exc})") from None
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON (not UTF-8 text: {exc.reason} at byte {exc.start})") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from None
    settings, sealed = unsealed(path, data)
    return ConfigFile(Path(path), settings, sealed)


_CURRENT: contextvars.ContextVar[ConfigFile | None] = contextvars.ContextVar("sr_config_file", default=None)
"""The file the running command read (:func:`config_scope`)."""


@contextlib.contextmanager
def config_scope(config: ConfigFile | None) -> Iterator[None]:
    """Within the block, :func:`config_file` answers ``config``'s path with ``config`` itself: the parser a command
    hands its command line to gets the file the command read, not a second reading."""
    token = _CURRENT.set(config)
    try:
        yield
    finally:
        _CURRENT.reset(token)


def config_file(config: str | os.PathLike[str] | ConfigFile | None) -> ConfigFile | None:
    """``config`` as a :class:`ConfigFile`: ``None`` and a :class:`ConfigFile` as they are, the path of the file the
    running command read (:func:`config_scope`) as that reading, any other path read (:func:`read_config_file`)."""
    if config is None or isinstance(config, ConfigFile):
        return config
    current = _CURRENT.get()
    if current is not None and Path(config) == current.path:
        return current
    return read_config_file(config)


def split_config(args: Sequence[str]) -> tuple[ConfigFile | None, list[str]]:
    """``--config_path=<file>`` apart from the other flags of ``args``, the file read (:func:`config_file`);
    returns (the file or None, the other flags)."""
    path, rest = split_config_path(args)
    return config_file(path), rest
