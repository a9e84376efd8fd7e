"""Atomic file writes and checked safetensors files.

Every file this project writes that a later run reads back (memories, checkpoints, results) goes through
:func:`atomic_write_bytes`: write to a temporary file in the same directory, flush and fsync, then
``os.replace``. A run killed at any point leaves either the old file or the new one, never a torn file.

And every such file is checksummed over header and data: safetensors files carry a sha256 of their tensors and
of their header (:func:`save_checked_safetensors`), JSON records a sha256 entry over all their other entries
(:func:`write_checked_json`), third-party checkpoint directories a sealed ``checksums.json``
(:func:`write_manifest`). The exceptions are files written for people or other programs to read and never read
back as state: reports, plots, videos and logs. A run's ``train_config.json`` is sealed too (read with the seal
left out: :func:`read_config_json`, :func:`unsealed`); configs a person writes are not.

The lowest layer of the package (``tests/test_architecture.py``): it imports nothing of ``sr_imitation``, and the
core's memories, the run infrastructure (:mod:`sr_imitation.infra`) and everything above are saved through it.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import shutil
import tempfile
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError
from safetensors.torch import load as st_load
from safetensors.torch import save as st_save


class CorruptFileError(RuntimeError):
    """A file is unreadable, truncated, or does not match what it declares or what the caller expects."""

    def __init__(self, path: str | os.PathLike[str], problem: str) -> None:
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


class WriteError(OSError):
    """Writing a file failed (a full disk, a read-only or vanished directory): one line naming the file, saying that
    nothing half-written was left and that a run can resume once the cause is fixed."""

    RESUME_ADVICE = "nothing half-written was left - fix the cause and continue with --resume=true"
    """What to do next, for a resumable run (the default)."""

    def __init__(self, path: str | os.PathLike[str], exc: OSError, advice: str = RESUME_ADVICE) -> None:
        self.path = Path(path)
        self.reason = getattr(exc, "reason", None) or exc.strerror or str(exc)
        super().__init__(exc.errno, f"{self.path}: cannot write ({self.reason}); {advice}")

    def __str__(self) -> str:
        return str(self.strerror)


def fsync_directory(directory: str | os.PathLike[str]) -> None:
    """Make a rename inside ``directory`` durable (the directory entry itself is flushed; POSIX only)."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return  # platforms without directory descriptors
    try:
        os.fsync(fd)
    except OSError:
        pass  # file systems that cannot fsync a directory
    finally:
        os.close(fd)


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (temp file + fsync + rename + fsync of the directory); returns the path.
    An ``OSError`` becomes a :class:`WriteError` naming ``path`` (the old file, if any, is untouched)."""
    path = Path(path)
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        fsync_directory(path.parent)
    except BaseException as exc:
        if tmp is not None and os.path.exists(tmp):
            os.unlink(tmp)
        if isinstance(exc, OSError) and not isinstance(exc, WriteError):
            raise WriteError(path, exc) from exc
        raise
    return path


def atomic_write_json(path: str | os.PathLike[str], obj: Any) -> Path:
    """JSON-serialize ``obj`` (indent 2, sorted keys) and write it atomically."""
    return atomic_write_bytes(path, (json.dumps(obj, indent=2, sort_keys=True) + "\n").encode())


JSON_CHECKSUM = "sha256"
"""The entry of a checked JSON file (:func:`write_checked_json`) that seals every other entry."""


def write_checked_json(path: str | os.PathLike[str], obj: Mapping[str, Any]) -> Path:
    """Write the JSON object ``obj`` atomically with a ``sha256`` entry over every other entry (the canonical JSON
    of :func:`header_digest`), so :func:`read_checked_json` notices a flipped byte, an edit or a truncation.

    Raises:
        ValueError: ``obj`` already has a ``sha256`` entry of its own.
    """
    if JSON_CHECKSUM in obj:
        raise ValueError(f"{path}: a checked JSON object cannot have its own {JSON_CHECKSUM!r} entry")
    body = dict(obj)
    return atomic_write_json(path, {**body, JSON_CHECKSUM: header_digest(body)})


def read_checked_json(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The object written by :func:`write_checked_json` (without its ``sha256`` entry).

    ``CorruptFileError`` naming the file if it is not valid JSON, not an object, has no sha256 or does not match
    it. A missing file raises ``FileNotFoundError``. (Readers of files from versions that wrote no seal decide by
    the file's recorded schema version, e.g. :func:`sr_imitation.reporting.results.load_results`.)
    """
    data = read_json(path)
    if not isinstance(data, dict):
        raise CorruptFileError(path, "not a JSON object")
    if JSON_CHECKSUM not in data:
        raise CorruptFileError(path, f"has no {JSON_CHECKSUM} entry (written by a version before checksums, or "
                                     "edited by hand)")
    return unsealed(path, data)[0]


def read_config_json(path: str | os.PathLike[str]) -> tuple[dict[str, Any], bool]:
    """A config file's JSON object and whether it was sealed: a run's ``train_config.json`` carries a ``sha256``
    entry (:func:`write_checked_json`), checked here and left out of the object returned; a config a person wrote
    has none. ``CorruptFileError`` naming the file if it is not a JSON object or does not match its seal."""
    return unsealed(path, read_json(path))


def unsealed(path: str | os.PathLike[str], data: Any) -> tuple[dict[str, Any], bool]:
    """A config file's parsed JSON without its ``sha256`` entry, and whether it had one (a run's sealed
    ``train_config.json``); ``CorruptFileError`` naming ``path`` if ``data`` is not a JSON object or does not match
    its seal."""
    if not isinstance(data, dict):
        raise CorruptFileError(path, "not a JSON object")
    if JSON_CHECKSUM not in data:
        return data, False
    body = {k: v for k, v in data.items() if k != JSON_CHECKSUM}
    if header_digest(body) != data[JSON_CHECKSUM]:
        raise CorruptFileError(path, f"contents do not match its {JSON_CHECKSUM} (corrupted or edited)")
    return body, True


def read_json(path: str | os.PathLike[str]) -> Any:
    """Parse a JSON file; ``CorruptFileError`` naming the file if it is not valid JSON or not UTF-8 text (a missing
    file raises ``FileNotFoundError``)."""
    path = Path(path)
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise CorruptFileError(path, f"not valid JSON ({exc})") from exc
    except UnicodeDecodeError as exc:  # a flipped byte outside ASCII
        raise CorruptFileError(path, f"not valid JSON (not UTF-8 text: {exc.reason} at byte {exc.start})") from exc


def tensors_digest(tensors: Mapping[str, torch.Tensor]) -> str:
    """sha256 over names, dtypes, shapes and raw bytes of ``tensors`` in sorted name order."""
    h = hashlib.sha256()
    for name in sorted(tensors):
        t = tensors[name].detach().cpu().contiguous()
        h.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b"")  # 0-dim safe
    return h.hexdigest()


def save_checked_safetensors(
    path: str | os.PathLike[str], tensors: Mapping[str, torch.Tensor], header: Mapping[str, Any]
) -> Path:
    """Save tensors with a JSON header in the safetensors metadata, atomically.

    The header gets ``tensors`` (name -> dtype and shape), ``sha256`` (of the tensor bytes) and
    ``header_sha256`` (of the header itself, every other key included) added, so :func:`load_checked_safetensors`
    detects truncation, bit corruption of the data *or* the header, and mismatches.
    """
    tensors = {k: v.detach().cpu().contiguous() for k, v in tensors.items()}
    full = dict(header)
    full["tensors"] = {k: {"dtype": str(v.dtype).removeprefix("torch."), "shape": list(v.shape)}
                       for k, v in sorted(tensors.items())}
    full["sha256"] = tensors_digest(tensors)
    full["header_sha256"] = header_digest(full)
    data = st_save(tensors, metadata={"sr_header": json.dumps(full, sort_keys=True)})
    return atomic_write_bytes(path, data)


def header_digest(header: Mapping[str, Any]) -> str:
    """sha256 of a header's canonical JSON (sorted keys), without its own ``header_sha256`` entry."""
    body = {k: v for k, v in header.items() if k != "header_sha256"}
    return hashlib.sha256(json.dumps(body, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def file_digest(path: str | os.PathLike[str]) -> str:
    """sha256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


MANIFEST = "checksums.json"
MANIFEST_FORMAT = "sr_imitation.checksums"


def write_manifest(directory: str | os.PathLike[str]) -> Path:
    """Write ``checksums.json`` in ``directory``: the sha256 of every other file below it (for checkpoints in a
    third-party layout, e.g. LeRobot's ``pretrained_model/``), itself sealed by a sha256 over its entries."""
    directory = Path(directory)
    files = {p.relative_to(directory).as_posix(): file_digest(p) for p in sorted(directory.rglob("*"))
             if p.is_file() and p.name != MANIFEST}
    body = {"format": MANIFEST_FORMAT, "files": files}
    return atomic_write_json(directory / MANIFEST, {**body, "sha256": header_digest(body)})


@contextlib.contextmanager
def staged_directory(final: str | os.PathLike[str]) -> Iterator[Path]:
    """Build a directory of files (a checkpoint) in a staging directory beside ``final``, then seal and publish it.

    Yields the staging directory; when the block ends without an error, ``checksums.json`` is written over its files
    (:func:`write_manifest`), an existing ``final`` (e.g. left by a run killed after the rename but before its
    progress was recorded, or a directory the caller decided to replace) is removed, and the staging directory is
    renamed to ``final``. On any error the staging directory is removed and ``final`` is untouched; an ``OSError``
    becomes a :class:`WriteError` naming ``final``.
    """
    final = Path(final)
    try:
        final.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.", dir=final.parent))
    except OSError as exc:
        raise WriteError(final, exc) from exc
    try:
        yield tmp
        write_manifest(tmp)  # sha256 of every file: LeRobot's safetensors carry no checksum of their own
        if final.exists():
            shutil.rmtree(final)
        os.replace(tmp, final)
        fsync_directory(final.parent)
    except BaseException as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        if isinstance(exc, OSError) and not isinstance(exc, WriteError):
            raise WriteError(final, exc) from exc
        raise


def verify_checkpoint(pretrained: str | os.PathLike[str], what: str = "the checkpoint") -> bool:
    """Check a ``pretrained_model`` directory against the ``checksums.json`` one level up (how ``sr-train`` stages
    and ``sr-sleep`` outputs are sealed: :func:`verify_manifest`); without one (a ``pretrained_model/`` copied on
    its own, or written by stock ``lerobot-train``) one warning line says that it is used unverified.

    Args:
        pretrained: the ``pretrained_model`` directory.
        what: what it is, for the warning (``policy.path``).

    Returns:
        Whether it was verified.

    Raises:
        CorruptFileError: a file differs from its checksum, or is missing.
    """
    folder = Path(pretrained).parent
    if (folder / MANIFEST).is_file():
        verify_manifest(folder)
        return True
    logging.getLogger(__name__).warning(
        "%s: %s is not verified: no %s one level up (it is written beside pretrained_model/ by sr-train and sr-sleep; "
        "copy the folder holding both to keep the check)", pretrained, what, folder / MANIFEST)
    return False


def verify_manifest(directory: str | os.PathLike[str]) -> None:
    """Check every file listed in ``directory/checksums.json`` (none missing, none changed); ``CorruptFileError``
    naming the first file that differs. Files added later (evaluation outputs next to a checkpoint) are not part of
    the checkpoint and are not checked."""
    directory = Path(directory)
    path = directory / MANIFEST
    if not path.is_file():
        raise CorruptFileError(path, "checkpoint has no checksums.json (written before checksums, or incomplete)")
    manifest = read_json(path)
    body = {k: v for k, v in manifest.items() if k != "sha256"} if isinstance(manifest, dict) else {}
    if body.get("format") != MANIFEST_FORMAT or header_digest(body) != manifest.get("sha256"):
        raise CorruptFileError(path, "checksum manifest is corrupted (its sha256 does not match its entries)")
    for name, digest in sorted(body["files"].items()):
        if not (directory / name).is_file():
            raise CorruptFileError(directory / name, "missing (listed in checksums.json)")
        if file_digest(directory / name) != digest:
            raise CorruptFileError(directory / name, "contents differ from checksums.json (corrupted or edited)")


def load_checkpoint_weights(directory: str | os.PathLike[str],
                            weights: str = "pretrained_model/model.safetensors") -> dict[str, torch.Tensor]:
    """The weights of a sealed checkpoint ``directory`` (LeRobot's layout: ``weights`` inside it), after checking
    every file of it against its ``checksums.json`` (:func:`verify_manifest`); ``CorruptFileError`` naming the file
    when that fails or the weights do not load (the caller checks the file exists, with its own message)."""
    from safetensors.torch import load_file  # noqa: PLC0415  (only here: the other readers take bytes)

    verify_manifest(directory)
    path = Path(directory) / weights
    try:
        return load_file(str(path))
    except Exception as exc:  # safetensors raises its own error types without the file name
        raise CorruptFileError(path, f"unreadable weights ({exc})") from exc


def load_checked_safetensors(path: str | os.PathLike[str]) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """Load a file written by :func:`save_checked_safetensors`; verify its header and checksum.

    Raises:
        FileNotFoundError: the file does not exist (message names it).
        CorruptFileError: unreadable or truncated file, missing header, or tensors that differ from the header
            (names, dtypes, shapes or checksum); the message names the file and the mismatch.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    data = path.read_bytes()
    try:
        tensors = st_load(data)
        meta_len = int.from_bytes(data[:8], "little")
        raw_meta = json.loads(data[8 : 8 + meta_len]).get("__metadata__", {})
    except (SafetensorError, ValueError, json.JSONDecodeError, OverflowError) as exc:
        raise CorruptFileError(path, f"not a readable safetensors file ({exc})") from exc
    if "sr_header" not in raw_meta:
        raise CorruptFileError(path, "safetensors file has no sr_header metadata (not written by sr_imitation)")
    try:
        header = json.loads(raw_meta["sr_header"])
    except json.JSONDecodeError as exc:
        raise CorruptFileError(path, f"sr_header is not valid JSON ({exc})") from exc
    declared = header.get("tensors", {})
    if sorted(declared) != sorted(tensors):
        raise CorruptFileError(
            path, f"tensor names {sorted(tensors)} differ from the header's {sorted(declared)}"
        )
    for name, spec in declared.items():
        t = tensors[name]
        actual = {"dtype": str(t.dtype).removeprefix("torch."), "shape": list(t.shape)}
        if actual != spec:
            raise CorruptFileError(path, f"tensor {name!r} is {actual}, header declares {spec}")
    if "header_sha256" not in header:
        raise CorruptFileError(path, "header has no header_sha256 (written before header checksums; re-create it)")
    if header_digest(header) != header["header_sha256"]:
        raise CorruptFileError(path, "header does not match its header_sha256 (corrupted or edited header)")
    if tensors_digest(tensors) != header.get("sha256"):
        raise CorruptFileError(path, "tensor data does not match the header's sha256 (corrupted file)")
    return tensors, header
