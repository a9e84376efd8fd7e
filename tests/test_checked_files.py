"""Every byte of a checked safetensors file (memories, SAC checkpoints, statistics) is covered: a flip anywhere in
the header or the data, or a truncation, is refused naming the file; checkpoint manifests (LeRobot layout) the
same for every file of the directory."""

from __future__ import annotations

import json

import pytest
import torch

from sr_imitation.core.memory import OutputDistillationMemory, load_memory
from sr_imitation.io import (
    CorruptFileError,
    load_checked_safetensors,
    read_checked_json,
    save_checked_safetensors,
    verify_manifest,
    write_checked_json,
    write_manifest,
)


def _memory() -> OutputDistillationMemory:
    g = torch.Generator().manual_seed(0)
    return OutputDistillationMemory("reach", {"input.x": torch.randn(6, 3, generator=g),
                                             "target": torch.randn(6, 2, generator=g)}, {"reduction": "mean"})


def test_every_single_byte_flip_of_a_memory_file_is_refused_naming_it(tmp_path):
    path = _memory().save(tmp_path / "m.safetensors")
    data = path.read_bytes()
    assert load_memory(path).config["reduction"] == "mean"
    for position in range(len(data)):
        for bit in (0x01, 0x20):  # a low bit and the ASCII case/space bit
            flipped = bytearray(data)
            flipped[position] ^= bit
            path.write_bytes(bytes(flipped))
            with pytest.raises(CorruptFileError) as info:
                load_memory(path)
            assert str(path) in str(info.value), position
    for cut in (1, 8, len(data) // 2, len(data) - 1):
        path.write_bytes(data[:cut])
        with pytest.raises(CorruptFileError, match="m.safetensors"):
            load_memory(path)


def test_the_issue_s_header_edit_is_refused(tmp_path):
    """'reduction' -> 'reducthon' in the JSON header loaded with the default reduction before header checksums."""
    path = _memory().save(tmp_path / "m.safetensors")
    data = path.read_bytes()
    assert data.count(b"reduction") == 1
    path.write_bytes(data.replace(b"reduction", b"reducthon"))
    with pytest.raises(CorruptFileError, match="header does not match its header_sha256"):
        load_memory(path)


def test_files_without_a_header_checksum_are_refused(tmp_path):
    from safetensors.torch import save_file

    tensors = {"w": torch.ones(3)}
    header = {"format": "x", "tensors": {"w": {"dtype": "float32", "shape": [3]}}}
    from sr_imitation.io import tensors_digest

    header["sha256"] = tensors_digest(tensors)
    save_file(tensors, str(tmp_path / "old.safetensors"), metadata={"sr_header": json.dumps(header)})
    with pytest.raises(CorruptFileError, match="old.safetensors: header has no header_sha256"):
        load_checked_safetensors(tmp_path / "old.safetensors")
    save_checked_safetensors(tmp_path / "new.safetensors", tensors, {"format": "x"})
    assert torch.equal(load_checked_safetensors(tmp_path / "new.safetensors")[0]["w"], tensors["w"])


def test_checkpoint_manifest_names_the_changed_file(tmp_path):
    ckpt = tmp_path / "wake"
    (ckpt / "pretrained_model").mkdir(parents=True)
    (ckpt / "pretrained_model" / "model.safetensors").write_bytes(bytes(range(200)))
    (ckpt / "pretrained_model" / "config.json").write_text('{"dim_model": 128}')
    (ckpt / "wake_history.json").write_text("{}")
    write_manifest(ckpt)
    verify_manifest(ckpt)
    model = ckpt / "pretrained_model" / "model.safetensors"
    original = model.read_bytes()
    for change, match in [
        (lambda: model.write_bytes(original[:-1] + b"\x00"), r"model.safetensors: contents differ"),
        (lambda: model.write_bytes(original[:100]), r"model.safetensors: contents differ"),
        (lambda: model.unlink(), r"model.safetensors: missing"),
    ]:
        change()
        with pytest.raises(CorruptFileError, match=match):
            verify_manifest(ckpt)
        model.write_bytes(original)
    (ckpt / "eval.json").write_text("{}")  # written next to the checkpoint later: not part of it
    verify_manifest(ckpt)
    manifest = ckpt / "checksums.json"
    manifest.write_text(manifest.read_text().replace('"format"', '"formaat"'))
    with pytest.raises(CorruptFileError, match="checksums.json: checksum manifest is corrupted"):
        verify_manifest(ckpt)
    manifest.unlink()
    with pytest.raises(CorruptFileError, match="checksums.json"):
        verify_manifest(ckpt)


def test_no_byte_flip_or_truncation_of_a_checked_json_file_changes_what_is_read(tmp_path):
    """progress.json, eval.json, results.json, ...: a flip is refused naming the file, or (a flip that leaves the
    same JSON values, e.g. 1e-05 -> 1E-05) reads back exactly the original."""
    obj = {"completed": {"1.wake": {"loss": 0.25, "lr": 1e-05, "ok": True, "skill": "reach", "none": None}},
           "version": 2}
    path = write_checked_json(tmp_path / "progress.json", obj)
    assert read_checked_json(path) == obj
    data = path.read_bytes()
    refused = 0
    for position in range(len(data)):
        for bit in (0x01, 0x20):
            flipped = bytearray(data)
            flipped[position] ^= bit
            path.write_bytes(bytes(flipped))
            try:
                assert read_checked_json(path) == obj, position
            except CorruptFileError as exc:
                assert str(path) in str(exc)
                refused += 1
    assert refused >= 2 * len(data) - 4  # only the exponent letters' case flips read back unchanged
    for cut in (1, len(data) // 2, len(data) - 2):
        path.write_bytes(data[:cut])
        with pytest.raises(CorruptFileError, match="progress.json"):
            read_checked_json(path)


def test_a_checked_json_file_always_needs_its_checksum(tmp_path):
    path = tmp_path / "results.json"
    path.write_text(json.dumps({"a": 1}))
    with pytest.raises(CorruptFileError, match=r"results.json: has no sha256"):
        read_checked_json(path)  # older files are read by their schema version (stream.results.load_results)
    path.write_text(json.dumps({"a": 1, "sha256": "0" * 64}))
    with pytest.raises(CorruptFileError, match="do not match"):
        read_checked_json(path)
    path.write_text("[1, 2]")
    with pytest.raises(CorruptFileError, match="not a JSON object"):
        read_checked_json(path)
    with pytest.raises(ValueError, match="own 'sha256'"):
        write_checked_json(path, {"sha256": "x"})


def test_a_failed_write_names_the_file_and_leaves_the_old_one(tmp_path, monkeypatch):
    """A full disk (any OSError) while writing: one line naming the file and saying the run can resume; the old
    file is untouched and no temporary file is left."""
    import errno
    import os as _os

    from sr_imitation.infra.cli_errors import run_cli
    from sr_imitation.io import WriteError, atomic_write_bytes

    path = tmp_path / "progress.json"
    path.write_bytes(b"old")

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(_os, "fsync", full)
    with pytest.raises(WriteError, match=r"progress.json: cannot write \(No space left on device\).*--resume=true"):
        atomic_write_bytes(path, b"new")
    assert path.read_bytes() == b"old" and sorted(p.name for p in tmp_path.iterdir()) == ["progress.json"]
    with pytest.raises(SystemExit, match="2"):
        run_cli("sr-train", lambda args: atomic_write_bytes(path, b"new"), [])


def test_a_full_disk_anywhere_is_one_line_naming_the_file_and_saying_the_run_can_resume(tmp_path, capsys):
    """Before: a 68-line traceback ending "No space left on device" for a write outside the atomic helpers."""
    import errno

    from sr_imitation.infra.cli_errors import note_run_started, run_cli

    log = tmp_path / "run" / "log.jsonl"

    def full(args):
        note_run_started(log.parent)  # the run exists (its log is written): the hint is the command that resumes it
        try:
            raise OSError(errno.ENOSPC, "No space left on device", str(log))
        except OSError as exc:
            raise RuntimeError("a library's wrapper") from exc

    with pytest.raises(SystemExit, match="2"):
        run_cli("sr-train", full, [])
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{log}: cannot write (No space left on device)" in err and "--resume=true" in err


def test_a_flipped_byte_in_a_checkpoint_manifest_names_it(tmp_path):
    """Before: a byte flipped to invalid UTF-8 in checksums.json gave a decoding error without the file's name."""
    ckpt = tmp_path / "wake"
    ckpt.mkdir()
    (ckpt / "model.safetensors").write_bytes(b"weights")
    write_manifest(ckpt)
    manifest = ckpt / "checksums.json"
    good = manifest.read_bytes()
    for at in range(0, len(good), max(1, len(good) // 40)):
        data = bytearray(good)
        data[at] ^= 0x80
        manifest.write_bytes(bytes(data))
        with pytest.raises(CorruptFileError, match="checksums.json: "):
            verify_manifest(ckpt)
