"""The weight store of an archive of runs: what a later question about a run needs and git should not carry.

A driver's ``--archive=<folder>`` (:mod:`sr_imitation.experiments.archive`) keeps a finished run's report files in
the tracked ``<folder>/<run>/``; with ``--keep_weights=true`` it also copies every checkpoint, memory and evaluation
file of the run (the run directory without :data:`NOT_STORED`) into the git-ignored ``<folder>.weights/<run>/``
(:func:`weight_store`), and writes the list of those files with their sizes and sha256 into the tracked
``<folder>/<run>/weights.json`` (:data:`WEIGHTS_FILE`), so that the store of any machine can be checked against the
archive (:func:`verify_weights`) before a re-sleep (:mod:`sr_imitation.substrates.sac.resleep`) reads it. Standard
library and ``sr_imitation.io`` only.
"""

from __future__ import annotations

import contextlib
import fnmatch
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from sr_imitation.io import CorruptFileError, file_digest, read_checked_json

WEIGHTS_FILE = "weights.json"
"""In an archived run: the weight store's file list (relative path -> bytes and sha256), sealed."""
WEIGHTS_FORMAT = "sr_imitation.weights"
NOT_STORED = ("videos", "wandb", "log.jsonl", "*.png", "*.md", "*.mp4", ".*", "wake_snapshot.safetensors")
"""What the weight store leaves out of a run (fnmatch on each path part): nothing a resume or a re-sleep reads."""


def weight_store(archive: Path) -> Path:
    """The git-ignored folder beside ``archive`` that keeps its runs' weights: ``<archive>.weights``."""
    archive = Path(archive)
    return archive.with_name(f"{archive.name}.weights")


def _stored(relative: Path) -> bool:
    return not any(fnmatch.fnmatchcase(part, pattern) for part in relative.parts for pattern in NOT_STORED)


def store_weights(run: Path, store: Path) -> dict[str, Any]:
    """Copy what a resume or a re-sleep of ``run`` reads (everything but :data:`NOT_STORED`; links are not followed)
    into ``store`` (replaced atomically) and return its file list: ``{"format", "store", "files": {path: {"bytes",
    "sha256"}}}``, ``store`` relative to the archive's parent."""
    run, store = Path(run), Path(store)
    files = sorted(p for p in run.rglob("*") if p.is_file() and not p.is_symlink() and _stored(p.relative_to(run)))
    listing: dict[str, dict[str, Any]] = {}
    with staged_replacement(store) as tmp:
        for path in files:
            rel = path.relative_to(run)
            (tmp / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(path, tmp / rel)
            listing[rel.as_posix()] = {"bytes": (tmp / rel).stat().st_size, "sha256": file_digest(tmp / rel)}
    return {"format": WEIGHTS_FORMAT, "store": f"{store.parent.name}/{store.name}", "files": listing}


def verify_weights(archived: Path, store: Path | None = None) -> Path:
    """Check an archived run's weight store against its ``weights.json``: every listed file present with its size and
    sha256 (:class:`CorruptFileError` naming the first that is not). ``store``: where the files are (default: the
    archive's ``.weights`` sibling). Returns the store."""
    archived = Path(archived)
    listing = read_checked_json(archived / WEIGHTS_FILE)
    if store is None:
        store = weight_store(archived.parent) / archived.name
    for rel, want in listing["files"].items():
        path = Path(store) / rel
        if not path.is_file():
            raise CorruptFileError(path, f"missing from the weight store (listed in {archived / WEIGHTS_FILE})")
        if path.stat().st_size != want["bytes"] or file_digest(path) != want["sha256"]:
            raise CorruptFileError(path, f"differs from its checksum in {archived / WEIGHTS_FILE}")
    return Path(store)


@contextlib.contextmanager
def staged_replacement(target: Path) -> Iterator[Path]:
    """A temporary folder beside ``target`` to fill; when the block ends without an error it replaces ``target``
    (:func:`replace_dir`), on any error it is removed and ``target`` is untouched."""
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent))
    try:
        yield tmp
        replace_dir(tmp, target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def replace_dir(tmp: Path, target: Path) -> None:
    """Rename ``tmp`` to ``target``, the old ``target`` (if any) set aside first and removed after."""
    old = None
    if target.exists():
        old = target.with_name(f".{target.name}.old")
        shutil.rmtree(old, ignore_errors=True)
        os.replace(target, old)
    os.replace(tmp, target)
    if old is not None:
        shutil.rmtree(old)
