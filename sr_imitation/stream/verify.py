"""Every sealed file of a run directory, verified before a resume writes anything.

A file is read back only when the phase that needs it runs, so a corrupted stage-1 checkpoint would otherwise be
noticed after later phases were redone and rewritten. :func:`verify_run_files` checks them all first and raises
:class:`~sr_imitation.io.CorruptFileError` naming the first bad file:

- a folder with ``checksums.json`` (a checkpoint in LeRobot's layout): every file it lists
  (:func:`~sr_imitation.io.verify_manifest`);
- ``*.safetensors`` outside such folders (memories, SAC checkpoints, trajectories, statistics): header and tensor
  checksums (:func:`~sr_imitation.io.load_checked_safetensors`);
- ``*.json`` outside such folders (progress, fingerprint, evaluations, diagnostics): their ``sha256`` seal
  (:func:`~sr_imitation.io.read_checked_json`), except ``unsealed`` names (the run's config copy, which the
  settings fingerprint checks, and the files a run rewrites at its end);
- ``*.npz`` (ACT evaluation trajectories of runs written before they were sealed safetensors): the zip's CRC of
  every member.

Not verified, because nothing reads them back: videos, plots, markdown reports, ``log.jsonl``, wandb's own files
(``wandb/``); nor hidden files (what an interrupted atomic write leaves; the resume removes them).
"""

from __future__ import annotations

import zipfile
import zlib
from collections.abc import Iterable
from pathlib import Path

from sr_imitation.io import (
    MANIFEST,
    CorruptFileError,
    load_checked_safetensors,
    read_checked_json,
    read_json,
    verify_manifest,
)

THIRD_PARTY = ("wandb", "videos")
"""Top-level folders other programs write into a run (wandb's offline run, rollout videos): never read back."""


def _visible(root: Path, path: Path) -> bool:
    parts = path.relative_to(root).parts
    return not any(part.startswith(".") for part in parts) and not (parts and parts[0] in THIRD_PARTY)


def verify_run_files(root: Path, unsealed: Iterable[str] = ()) -> int:
    """Verify every sealed file below ``root`` (see the module docstring); ``unsealed``: top-level file names that
    carry no seal by design. Returns the number of files checked."""
    root = Path(root)
    unsealed = set(unsealed)
    covered: set[Path] = set()
    checked = 0
    for manifest in sorted(root.rglob(MANIFEST)):
        if not _visible(root, manifest):
            continue
        verify_manifest(manifest.parent)
        listed = read_json(manifest).get("files", {})
        covered |= {manifest.parent / name for name in listed} | {manifest}
        checked += len(listed) + 1
    for path in sorted(root.rglob("*")):
        if path in covered or not path.is_file() or not _visible(root, path):
            continue
        if path.parent == root and path.name in unsealed:
            continue
        if path.suffix == ".safetensors":
            load_checked_safetensors(path)
        elif path.suffix == ".json":
            read_checked_json(path)
        elif path.suffix == ".npz":
            _verify_zip(path)
        else:
            continue
        checked += 1
    return checked


def _verify_zip(path: Path) -> None:
    try:
        with zipfile.ZipFile(path) as archive:
            bad = archive.testzip()
    except (zipfile.BadZipFile, zlib.error, OSError, EOFError, ValueError) as exc:
        raise CorruptFileError(path, f"unreadable archive ({exc})") from exc
    if bad is not None:
        raise CorruptFileError(path, f"member {bad!r} fails its CRC (corrupted)")
