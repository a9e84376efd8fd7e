"""A dataset's identity by content: what a run fingerprints so that a resume over other data is refused.

A stream trains on LeRobot datasets that live outside the run directory; their paths are not their identity (the
same dataset may be moved, given relative or absolute), their bytes are. The identity of a dataset is

    sha256( for every file below its root, in sorted relative-path order:  "<relative path>\\0<sha256 of file>\\n" )

over its meta (``meta/info.json``, ``meta/stats.json``, ``meta/tasks.parquet``, ``meta/episodes/...``), data
(``data/...``) and video (``videos/...``) files; hidden files and folders (``.cache``, ``.something.tmp``) are not
part of a dataset (LeRobot neither writes nor reads them). A run stores each skill's identity in its settings
fingerprint under ``inputs.datasets.<skill>`` (:func:`dataset_inputs`), so a resume, an extension or the archive
check compares them like every other setting, and a changed dataset is refused in one line naming the skill and the
path (:func:`check_inputs`).

Cost. Hashing reads every byte (a 10 GB dataset: about a minute). Per-file digests are cached by
(path, size, mtime in ns, inode) in ``$XDG_CACHE_HOME/sr_imitation/file_digests.json`` (our choice, the stat
check git uses for its index; ``SR_DIGEST_CACHE=<file>`` puts it elsewhere, as the test suite does): a resume
re-hashes only files that were rewritten, replaced or touched. A byte edited in place with size and mtime restored
by hand would escape the cache; ``SR_NO_DIGEST_CACHE=1`` hashes everything. The cache keeps only entries that still
describe a file as it is (each write drops the others: deleted datasets, rewritten files), so it does not grow with
every dataset ever hashed; a process reads it again only when another process rewrote it.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from sr_imitation.io import atomic_write_json, file_digest
from sr_imitation.substrates.act.data import DatasetMismatchError, dataset_info_path

logger = logging.getLogger(__name__)

INPUTS_KEY = "inputs.datasets"
"""The fingerprint's prefix of the dataset identities (``inputs.datasets.<skill>``)."""


class InputsMismatchError(ValueError):
    """A resumed run's dataset differs from the one it started on (one line: skill, path, both digests)."""


def _cache_path() -> Path:
    if os.environ.get("SR_DIGEST_CACHE"):
        return Path(os.environ["SR_DIGEST_CACHE"])
    root = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return root / "sr_imitation" / "file_digests.json"


_read: dict[str, tuple[list[int], dict[str, Any]]] = {}
"""The cache as this process last read or wrote it, by path, with the file's :func:`_stamp` then."""


def _stamp(path: Path | str) -> list[int] | None:
    """A file's (size, mtime in ns, inode), the cache's test of "unchanged"; ``None`` if it cannot be read."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return [st.st_size, st.st_mtime_ns, st.st_ino]


def _load_cache(path: Path) -> dict[str, Any]:
    stamp = _stamp(path)
    seen = _read.get(str(path))
    if stamp is not None and seen is not None and seen[0] == stamp:
        return dict(seen[1])  # unchanged since this process read or wrote it (entries are replaced, never changed)
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}  # no cache, or an unreadable one: it is only a cache, everything is re-hashed
    if not isinstance(data, dict):
        return {}
    if stamp is not None:
        _read[str(path)] = (stamp, dict(data))
    return data


def _still_valid(key: str, entry: Any) -> bool:
    """Whether a cache entry still describes its file as it is now (a deleted or rewritten file's entry is dead)."""
    stamp = _stamp(key)
    return stamp is not None and isinstance(entry, dict) and entry.get("stat") == stamp


def _save_cache(path: Path, cache: dict[str, Any]) -> None:
    kept = {key: entry for key, entry in cache.items() if _still_valid(key, entry)}
    atomic_write_json(path, kept)
    stamp = _stamp(path)
    if stamp is not None:
        _read[str(path)] = (stamp, kept)


def dataset_files(root: Path) -> list[Path]:
    """Every file of a dataset (hidden files and folders excluded), sorted by relative path."""
    root = Path(root)
    files = []
    for path in root.rglob("*"):
        rel = path.relative_to(root)
        if path.is_file() and not any(part.startswith(".") for part in rel.parts):
            files.append(path)
    return sorted(files, key=lambda p: p.relative_to(root).as_posix())


def dataset_digest(root: Path, cache: dict[str, Any] | None = None) -> str:
    """The content identity of the dataset at ``root`` (see the module docstring). ``cache``: per-file digests by
    stat (updated in place)."""
    root = Path(root)
    if not dataset_info_path(root).is_file():  # the same one line as the dataset checks (substrates.act.data)
        raise DatasetMismatchError(f"{root}: not a LeRobot dataset (missing {dataset_info_path(root)})")
    h = hashlib.sha256()
    files = dataset_files(root)
    for path in files:
        key = str(path.resolve())
        stamp = _stamp(path)
        entry = None if cache is None else cache.get(key)
        if isinstance(entry, dict) and entry.get("stat") == stamp and isinstance(entry.get("sha256"), str):
            digest = entry["sha256"]
        else:
            digest = file_digest(path)
            if cache is not None:
                cache[key] = {"stat": stamp, "sha256": digest}
        h.update(f"{path.relative_to(root).as_posix()}\0{digest}\n".encode())
    return h.hexdigest()


def dataset_inputs(skills: Sequence[str], paths: Sequence[Path]) -> dict[str, str]:
    """``{skill: content digest}`` of the stream's datasets (cached per file, see the module docstring)."""
    use_cache = os.environ.get("SR_NO_DIGEST_CACHE", "") in ("", "0")
    cache_path = _cache_path()
    cache = _load_cache(cache_path) if use_cache else None
    entries = None if cache is None else dict(cache)
    out = {skill: dataset_digest(Path(path), cache) for skill, path in zip(skills, paths, strict=True)}
    if cache is not None and cache != entries:  # a file was hashed anew
        try:
            _save_cache(cache_path, cache)
        except OSError as exc:  # a read-only home: only the cache is lost
            logger.warning("cannot write the digest cache %s (%s); datasets are re-hashed next time", cache_path, exc)
    return out


def stored_inputs(settings: Mapping[str, Any]) -> dict[str, str]:
    """The dataset identities a stored fingerprint holds (``{}`` for runs started before inputs were recorded)."""
    prefix = INPUTS_KEY + "."
    return {k[len(prefix):]: v for k, v in settings.items() if k.startswith(prefix)}


def check_inputs(fingerprint_file: Path, stored: Mapping[str, Any], current: Mapping[str, str],
                 paths: Mapping[str, Path], allow_unhashed: bool) -> None:
    """Refuse a resume whose datasets differ from the run's: :class:`InputsMismatchError` naming the skill, its
    path and both digests. A run without stored identities (started before they were recorded) is refused unless
    ``allow_unhashed`` (``--allow_unhashed_inputs=true``: the user vouches that the data is unchanged)."""
    old = stored_inputs(stored)
    if not old:
        if allow_unhashed:
            logger.warning("%s records no dataset identities (a run started before they were); resuming without "
                           "checking its data because --allow_unhashed_inputs=true", fingerprint_file)
            return
        raise InputsMismatchError(
            f"{fingerprint_file}: this run started before datasets were fingerprinted, so its data cannot be "
            "checked; pass --allow_unhashed_inputs=true to resume it anyway (you vouch the datasets are unchanged)")
    for skill, digest in current.items():
        if skill in old and old[skill] != digest:
            raise InputsMismatchError(
                f"{paths[skill]}: the dataset of skill {skill!r} differs from the one this run trained on "
                f"(content sha256 {old[skill][:12]}... stored in {fingerprint_file.name}, {digest[:12]}... now); "
                "resume with the original data or start a new run in another output_dir")
