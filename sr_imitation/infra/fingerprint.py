"""Settings fingerprints: a run directory that cannot change its settings silently.

A run stores, at its start, every setting of its configuration as a flat mapping of dotted keys
(``sleep.batch_size``, ``wake.budgets.reach.max_episodes``) minus an explicit allow-list of settings that
cannot change results (where the run is, progress bars, video count, ...), together with the sha256 of that
mapping. A resume computes the same mapping from the requested configuration and refuses, before writing anything,
if any key differs, was added or was removed; the error is one line naming the file and every differing key with
its stored and requested values.

Flattening: dataclasses and mappings are walked (their fields/keys joined with ``.``); every other value is a leaf
converted to JSON (enums to their value, paths to POSIX strings, tuples and sets to lists, dataclasses inside lists
to objects). Empty dataclasses and mappings are leaves (``{}``) so that adding the first entry shows as a change.
Values are compared by their canonical JSON text, where numbers are compared as Python compares them: integral
floats are written as integers and booleans as 0/1 (``1.0`` equals ``1``: draccus turns ``--x=1`` into ``1.0`` for
a float field while a config built in Python may hold ``1``; ``False`` equals ``0``: LeRobot declares
``replace_final_stride_with_dilation: int = False``, which draccus reads back as ``0``), and NaN equals NaN.

Allow-list patterns are :func:`fnmatch.fnmatchcase` patterns (``eval.videos_per_skill``, ``wandb.*``); a pattern
also covers everything below the key it names (``policy.input_features`` covers
``policy.input_features.observation.state.shape``).

Substrate-free: only the standard library and :mod:`sr_imitation.io`.
"""

from __future__ import annotations

import dataclasses
import enum
import fnmatch
import hashlib
import json
import math
import os
from collections.abc import Iterable, Mapping
from pathlib import Path, PurePath
from typing import Any

from sr_imitation.io import CorruptFileError, atomic_write_json, read_json

FINGERPRINT_FILE = "settings_fingerprint.json"
"""Name of the fingerprint file in a run directory (next to the program's own config file)."""
FINGERPRINT_FORMAT = "sr_imitation.settings_fingerprint"
FINGERPRINT_VERSION = 1
STACK_KEY = "stack"
"""A derived top-level key (:attr:`SettingsFingerprint.derived`): the versions of the libraries that compute a run's
numbers (``stack.lerobot``). A resume under other versions is refused first, by :func:`check_stack`."""
RUN_DIRECTORY = "."
"""``output_dir`` as a run's own config file stores it: the directory holding the file (see :func:`output_dir_for`)."""


class _Absent:
    """A key one side does not have (``<absent>`` in messages)."""

    def __repr__(self) -> str:
        return "<absent>"


ABSENT: Any = _Absent()


def to_jsonable(value: Any, key: str = "") -> Any:
    """``value`` as plain JSON data (dict/list/str/int/float/bool/None); ``TypeError`` naming ``key`` otherwise."""
    if isinstance(value, enum.Enum):  # first: str-valued enums are also str
        return to_jsonable(value.value, key)
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, PurePath):
        return value.as_posix()
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_jsonable(getattr(value, f.name), _join(key, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, Mapping):
        return {_key_text(k): to_jsonable(v, _join(key, _key_text(k))) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_jsonable(v, f"{key}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, (set, frozenset)):
        return sorted((to_jsonable(v, key) for v in value), key=canonical_json)
    if hasattr(value, "item") and hasattr(value, "dtype") and getattr(value, "ndim", None) == 0:
        return to_jsonable(value.item(), key)  # numpy/torch scalars
    if hasattr(value, "tolist") and hasattr(value, "dtype"):
        return to_jsonable(value.tolist(), key)  # numpy arrays
    raise TypeError(f"setting {key or '<root>'!r}: cannot fingerprint a value of type {type(value).__name__}")


def flatten_settings(cfg: Any) -> dict[str, Any]:
    """Every leaf setting of ``cfg`` (a dataclass or mapping, nested freely) under its dotted key, JSON values."""
    if not (isinstance(cfg, Mapping) or (dataclasses.is_dataclass(cfg) and not isinstance(cfg, type))):
        raise TypeError(f"flatten_settings needs a dataclass or a mapping, got {type(cfg).__name__}")
    out: dict[str, Any] = {}
    _walk(cfg, "", out)
    return out


def _walk(value: Any, prefix: str, out: dict[str, Any]) -> None:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        items: Iterable[tuple[str, Any]] = [(f.name, getattr(value, f.name)) for f in dataclasses.fields(value)]
    elif isinstance(value, Mapping):
        items = [(_key_text(k), v) for k, v in value.items()]
    else:
        if prefix in out:
            raise ValueError(f"setting {prefix!r} appears twice after flattening (a key containing '.')")
        out[prefix] = to_jsonable(value, prefix)
        return
    items = list(items)
    if not items and prefix:
        out[prefix] = {}
    for name, child in items:
        _walk(child, _join(prefix, name), out)


def _join(prefix: str, name: str) -> str:
    return f"{prefix}.{name}" if prefix else name


def _key_text(key: Any) -> str:
    if isinstance(key, enum.Enum):
        key = key.value
    return key if isinstance(key, str) else str(key)


def check_finite(cfg: Any) -> None:
    """Refuse any non-finite float setting of ``cfg`` (NaN, +-inf), naming its dotted key, at parse time: a NaN
    learning rate or budget otherwise surfaces only after something was written (or trains silently on NaN).
    Settings that are absent use ``None``, never ``inf``."""
    for key, value in flatten_settings(cfg).items():
        if isinstance(value, float) and not math.isfinite(value):
            raise ValueError(f"{key}: must be a finite number, got {value}")


def is_allowed(key: str, allow: Iterable[str]) -> bool:
    """Whether ``key`` or one of its dotted prefixes matches an allow-list pattern."""
    parts = key.split(".")
    prefixes = [".".join(parts[: i + 1]) for i in range(len(parts))]
    return any(fnmatch.fnmatchcase(p, pattern) for pattern in allow for p in prefixes)


def _canonical(value: Any) -> Any:
    if isinstance(value, bool):
        return int(value)
    if isinstance(value, float) and math.isfinite(value) and value.is_integer() and abs(value) < 2**53:
        return int(value)
    if isinstance(value, list):
        return [_canonical(v) for v in value]
    if isinstance(value, dict):
        return {k: _canonical(v) for k, v in value.items()}
    return value


def canonical_json(value: Any) -> str:
    """The one JSON text that two equal settings share (sorted keys, no spaces, integral floats as integers,
    booleans as 0/1)."""
    return json.dumps(_canonical(value), sort_keys=True, separators=(",", ":"), allow_nan=True)


def settings_digest(settings: Mapping[str, Any]) -> str:
    """sha256 of the canonical JSON of a flat settings mapping."""
    return hashlib.sha256(canonical_json(dict(settings)).encode()).hexdigest()


@dataclasses.dataclass(frozen=True)
class SettingsFingerprint:
    """The settings that must be equal for a resume (flat, allow-listed keys removed) and their sha256."""

    settings: dict[str, Any]
    sha256: str
    allow: tuple[str, ...] = ()
    derived: tuple[str, ...] = ()
    """Top-level keys computed from the configuration by the code rather than set in it (``method_config``: the
    method's settings with their defaults). A stored fingerprint without such a key predates it and counts as equal
    there (:func:`check_settings`); one that has it must match."""
    stack_hint: str = ""
    """What to do when a run was made with other versions of the libraries under :data:`STACK_KEY` (the command
    that continues it, or where), said by :class:`StackMismatchError`. Not written to the file."""
    added: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    """Settings added to the code after runs were first fingerprinted, with the value (JSON) every run that predates
    them had: a stored fingerprint without such a key counts as holding that value (:func:`check_settings`), so an
    older run resumes with it and is refused with another. Not written to the file."""

    def to_json(self) -> dict[str, Any]:
        return {"format": FINGERPRINT_FORMAT, "version": FINGERPRINT_VERSION, "sha256": self.sha256,
                "allow_list": list(self.allow), "derived": list(self.derived), "settings": self.settings}


def settings_fingerprint(cfg: Any, allow: Iterable[str] = (), derived: Mapping[str, Any] | None = None,
                         added: Mapping[str, Any] | None = None, stack_hint: str = "") -> SettingsFingerprint:
    """Flatten ``cfg`` (:func:`flatten_settings`) and ``derived`` (see :attr:`SettingsFingerprint.derived`; a key
    of both is refused), drop the keys ``allow`` covers, hash the rest. ``added``, ``stack_hint``: see
    :class:`SettingsFingerprint`."""
    allow, derived = tuple(allow), dict(derived or {})
    flat = flatten_settings(cfg)
    clash = sorted(set(derived) & {k.split(".")[0] for k in flat})
    if clash:
        raise ValueError(f"derived settings {clash} are also settings of the configuration")
    flat.update(flatten_settings(derived))
    flat = {k: v for k, v in sorted(flat.items()) if not is_allowed(k, allow)}
    return SettingsFingerprint(flat, settings_digest(flat), allow, tuple(derived), stack_hint, dict(added or {}))


def diff_settings(stored: Mapping[str, Any], current: Mapping[str, Any]) -> dict[str, tuple[Any, Any]]:
    """Keys whose values differ, with (stored, current); a key on one side only has :data:`ABSENT` on the other.

    An empty mapping and an absent key are the same: both mean "no values" (our choice). A mapping setting added
    later with an empty default (``method_options``) so does not block resuming a run that started before it."""
    out = {}
    for key in sorted(set(stored) | set(current)):
        a, b = stored.get(key, ABSENT), current.get(key, ABSENT)
        if _no_values(a) and _no_values(b):
            continue
        if a is ABSENT or b is ABSENT or canonical_json(a) != canonical_json(b):
            out[key] = (a, b)
    return out


def _no_values(value: Any) -> bool:
    return value is ABSENT or (isinstance(value, Mapping) and not value)


def _show(value: Any) -> str:
    return "<absent>" if value is ABSENT else json.dumps(value, allow_nan=True)


class SettingsMismatchError(ValueError):
    """A resume asked for settings other than the run's stored ones. The message is one line: the file, then
    every differing key as ``key: stored -> requested``."""

    def __init__(self, path: str | os.PathLike[str], diffs: Mapping[str, tuple[Any, Any]]) -> None:
        self.path = Path(path)
        self.diffs = dict(diffs)
        changes = "; ".join(f"{k}: {_show(a)} -> {_show(b)}" for k, (a, b) in sorted(self.diffs.items()))
        super().__init__(
            f"{self.path}: cannot resume with different settings (stored -> requested): {changes} "
            "(resume with the stored values, or start a new run in another output_dir)"
        )


class StackMismatchError(SettingsMismatchError):
    """A resume under other library versions than the run was made with (keys under :data:`STACK_KEY`). One line:
    the file, each library with its stored and installed version, and the fingerprint's ``stack_hint``."""

    def __init__(self, path: str | os.PathLike[str], diffs: Mapping[str, tuple[Any, Any]], hint: str = "") -> None:
        self.path = Path(path)
        self.diffs = dict(diffs)
        made = ", ".join(f"{k.removeprefix(STACK_KEY + '.')} {_version(a)}" for k, (a, _) in sorted(self.diffs.items()))
        here = ", ".join(f"{k.removeprefix(STACK_KEY + '.')} {_version(b)}" for k, (_, b) in sorted(self.diffs.items()))
        ValueError.__init__(self, f"{self.path}: this run was made with {made} and cannot resume under {here} "
                                  f"(another release computes other numbers){': ' + hint if hint else ''}")


def _version(value: Any) -> str:
    return "<unrecorded>" if value is ABSENT or value is None else str(value)


def check_stack(path: str | os.PathLike[str], stored: Mapping[str, Any], current: SettingsFingerprint) -> None:
    """Raise :class:`StackMismatchError` if the run's library versions (:data:`STACK_KEY`) differ from ``current``'s;
    checked before the inputs and the other settings, so it is the one line a user sees."""
    diffs = {k: v for k, v in resume_differences(stored, current).items() if is_allowed(k, [STACK_KEY])}
    if diffs:
        raise StackMismatchError(path, diffs, current.stack_hint)


def check_settings(path: str | os.PathLike[str], stored: Mapping[str, Any], current: SettingsFingerprint) -> None:
    """Raise :class:`SettingsMismatchError` naming ``path`` unless ``stored`` equals ``current.settings``.

    ``stored`` is filtered with ``current.allow`` first, so a key allow-listed since the run started (or an older
    run's stored config, see :func:`settings_from_config`) is not counted; a key under one of ``current.derived``
    that ``stored`` lacks is taken as equal (the run predates it: its code did not record it), and a key of
    ``current.added`` that ``stored`` lacks as holding its value there."""
    diffs = resume_differences(stored, current)
    if diffs:
        raise SettingsMismatchError(path, diffs)


def resume_differences(stored: Mapping[str, Any], current: SettingsFingerprint) -> dict[str, tuple[Any, Any]]:
    """What :func:`check_settings` refuses: the keys whose values differ between ``stored`` and ``current`` after its
    allow-list, derived and added settings are accounted for (see there)."""
    stored = {k: v for k, v in stored.items() if not is_allowed(k, current.allow)}
    predates = {k: v for k, v in current.settings.items() if k not in stored and is_allowed(k, current.derived)}
    older = {k: v for k, v in current.added.items() if k not in stored and not is_allowed(k, current.allow)}
    return diff_settings({**stored, **predates, **older}, current.settings)


def write_fingerprint(path: str | os.PathLike[str], fingerprint: SettingsFingerprint) -> Path:
    """Write ``fingerprint`` atomically as JSON."""
    return atomic_write_json(path, fingerprint.to_json())


def read_fingerprint(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The stored flat settings of a fingerprint file; ``CorruptFileError`` naming the file if it is unreadable,
    of another format, or its settings do not match its sha256 (edited by hand or corrupted)."""
    path = Path(path)
    data = read_json(path)
    if not isinstance(data, dict) or data.get("format") != FINGERPRINT_FORMAT:
        raise CorruptFileError(path, f"not a settings fingerprint (format {FINGERPRINT_FORMAT!r} expected)")
    if data.get("version") != FINGERPRINT_VERSION:
        raise CorruptFileError(path, f"fingerprint version {data.get('version')!r}, this code reads "
                                     f"{FINGERPRINT_VERSION}")
    settings = data.get("settings")
    if not isinstance(settings, dict) or settings_digest(settings) != data.get("sha256"):
        raise CorruptFileError(path, "the stored settings do not match their sha256 (edited or corrupted)")
    return settings


def settings_from_config(config: Mapping[str, Any]) -> dict[str, Any]:
    """Flat settings of a stored (nested JSON) config: the comparison base for runs written before fingerprints."""
    return flatten_settings(config)


def output_dir_for(config_path: str | os.PathLike[str] | None, args: Iterable[str], output_dir: Path) -> Path:
    """The output directory a command line means.

    A run's own config file stores ``output_dir`` as ``"."`` (:data:`RUN_DIRECTORY`): the run directory the file
    belongs to, so ``--config_path=<run>/train_config.json --resume=true`` resumes ``<run>`` wherever it was copied,
    and nothing in a run directory names its absolute location. The copy beside each checkpoint (LeRobot's
    ``<run>/last/pretrained_model/train_config.json``) means the same run: the nearest folder above the file that
    holds the run's :data:`FINGERPRINT_FILE` (:func:`run_directory_of`). An explicit ``--output_dir`` wins.
    """
    given = any(a == "--output_dir" or a.startswith("--output_dir=") for a in args)
    if config_path is not None and not given and Path(output_dir) == Path(RUN_DIRECTORY):
        return run_directory_of(Path(config_path))
    return Path(output_dir)


def run_directory_of(config_path: Path, levels: int = 4) -> Path:
    """The run directory of a run's config file: its own folder, or the nearest of the ``levels`` folders above it
    (lexically, so ``<run>/last/...`` stays in ``<run>``) that holds :data:`FINGERPRINT_FILE`; its own folder when
    none does (a fresh run started from a copied config)."""
    folder = Path(config_path).parent
    for candidate in [folder, *list(folder.parents)[:levels]]:
        if (candidate / FINGERPRINT_FILE).is_file():
            return candidate
    return folder
