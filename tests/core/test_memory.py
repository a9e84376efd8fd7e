"""Memories: objective, immutability, bit-exact save/load, loud failures on corrupt or mismatched files."""

from __future__ import annotations

import json
import os

import pytest
import torch
from torch import nn

from sr_imitation.core.memory import Memory, OutputDistillationMemory, load_memory
from sr_imitation.io import CorruptFileError, atomic_write_bytes, save_checked_safetensors


def _snapshot() -> nn.Module:
    torch.manual_seed(1)
    return nn.Sequential(nn.Linear(4, 8), nn.ReLU(), nn.Linear(8, 3))


def _memory(skill: str = "reach", n: int = 32) -> tuple[OutputDistillationMemory, nn.Module]:
    net = _snapshot()
    inputs = {"state": torch.randn(n, 4), "image": torch.randint(0, 255, (n, 3, 2, 2), dtype=torch.uint8)}
    mem = OutputDistillationMemory.from_snapshot(skill, lambda obs: net(obs["state"]), inputs, batch_size=10)
    return mem, net


def test_targets_are_the_snapshot_outputs_and_the_objective_is_eq_l_pi():
    mem, net = _memory()
    with torch.no_grad():
        expected = net(mem.tensors["input.state"])
    torch.testing.assert_close(mem.tensors["target"], expected)
    # The snapshot itself has zero loss; another network has the squared-l2 distance, averaged over samples.
    assert mem.objective(lambda obs: net(obs["state"]), 16).item() == pytest.approx(0.0, abs=1e-12)
    other = nn.Linear(4, 3)
    batch = mem.sample(8, torch.Generator().manual_seed(0))
    loss = mem.loss(lambda obs: other(obs["state"]), batch)
    manual = (other(batch["input.state"]) - batch["target"]).pow(2).sum(dim=1).mean()
    torch.testing.assert_close(loss, manual)
    loss.backward()
    assert other.weight.grad is not None and other.weight.grad.abs().sum() > 0


def test_sampling_is_uniform_and_seeded():
    mem, _ = _memory(n=4)
    a = mem.sample(1000, torch.Generator().manual_seed(3))["input.state"]
    b = mem.sample(1000, torch.Generator().manual_seed(3))["input.state"]
    torch.testing.assert_close(a, b)
    counts = torch.stack([(a == row).all(dim=1) for row in mem.tensors["input.state"]]).sum(dim=1)
    assert counts.min() > 180 and counts.max() < 320  # 4 rows, 1000 draws: ~250 each


def test_memory_is_immutable_and_detached_from_its_sources():
    net = _snapshot()
    src = torch.randn(5, 4)
    mem = OutputDistillationMemory.from_snapshot("s", lambda o: net(o["x"]), {"x": src})
    before = mem.fingerprint()
    src.add_(1.0)
    with torch.no_grad():
        net[0].weight.add_(1.0)
    assert mem.fingerprint() == before
    with pytest.raises(AttributeError, match="immutable"):
        mem.skill = "other"
    with pytest.raises(TypeError):
        mem.tensors["target"] = torch.zeros(1)  # read-only mapping
    assert not any(t.requires_grad for t in mem.tensors.values())


def test_nbytes_counts_every_tensor():
    mem, _ = _memory(n=10)
    expected = 10 * 4 * 4 + 10 * 3 * 2 * 2 * 1 + 10 * 3 * 4
    assert mem.nbytes() == expected
    assert "nbytes=" in repr(mem)


def test_save_load_round_trips_bit_exactly(tmp_path):
    mem, _ = _memory()
    path = mem.save(tmp_path / "memories" / "skill_1.safetensors")
    loaded = load_memory(path)
    assert type(loaded) is OutputDistillationMemory
    assert loaded.skill == mem.skill and dict(loaded.config) == dict(mem.config)
    assert sorted(loaded.tensors) == sorted(mem.tensors)
    for name, t in mem.tensors.items():
        assert loaded.tensors[name].dtype == t.dtype
        assert torch.equal(loaded.tensors[name], t)
    assert loaded.fingerprint() == mem.fingerprint()
    assert OutputDistillationMemory.load(path, skill="reach").skill == "reach"
    assert not [p for p in path.parent.iterdir() if p.name.endswith(".tmp")]


def test_missing_file_names_the_path(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.safetensors"):
        load_memory(tmp_path / "nope.safetensors")


def test_flipped_byte_is_detected(tmp_path):
    mem, _ = _memory()
    path = mem.save(tmp_path / "m.safetensors")
    data = bytearray(path.read_bytes())
    data[-5] ^= 0xFF  # inside the tensor data
    path.write_bytes(bytes(data))
    with pytest.raises(CorruptFileError, match=r"m\.safetensors.*sha256"):
        load_memory(path)


def test_truncated_file_is_detected(tmp_path):
    mem, _ = _memory()
    path = mem.save(tmp_path / "m.safetensors")
    path.write_bytes(path.read_bytes()[:100])
    with pytest.raises(CorruptFileError, match=r"m\.safetensors.*not a readable safetensors"):
        load_memory(path)


def test_skill_and_kind_mismatches_are_named(tmp_path):
    mem, _ = _memory("door-open")
    path = mem.save(tmp_path / "m.safetensors")
    with pytest.raises(CorruptFileError, match=r"skill 'door-open', expected 'reach'"):
        load_memory(path, skill="reach")
    header = mem.header() | {"kind": "mystery"}
    save_checked_safetensors(tmp_path / "k.safetensors", mem.tensors, header)
    with pytest.raises(CorruptFileError, match="unknown memory kind 'mystery'"):
        load_memory(tmp_path / "k.safetensors")
    save_checked_safetensors(tmp_path / "v.safetensors", mem.tensors, mem.header() | {"format_version": 99})
    with pytest.raises(CorruptFileError, match="format version 99"):
        load_memory(tmp_path / "v.safetensors")


def test_header_that_disagrees_with_the_tensors_is_named(tmp_path):
    mem, _ = _memory()
    path = mem.save(tmp_path / "m.safetensors")
    raw = path.read_bytes()
    n = int.from_bytes(raw[:8], "little")
    meta = json.loads(raw[8 : 8 + n])
    header = json.loads(meta["__metadata__"]["sr_header"])
    header["tensors"]["target"]["shape"] = [32, 4]
    meta["__metadata__"]["sr_header"] = json.dumps(header)
    blob = json.dumps(meta).encode()
    blob += b" " * (-len(blob) % 8)
    path.write_bytes(len(blob).to_bytes(8, "little") + blob + raw[8 + n :])
    with pytest.raises(CorruptFileError, match=r"tensor 'target' is .*\[32, 3\].*header declares .*\[32, 4\]"):
        load_memory(path)


def test_invalid_memories_are_rejected():
    with pytest.raises(ValueError, match="skill"):
        OutputDistillationMemory("", {"input.x": torch.zeros(2, 1), "target": torch.zeros(2, 1)})
    with pytest.raises(ValueError, match="buffer sizes differ"):
        OutputDistillationMemory("a", {"input.x": torch.zeros(2, 1), "target": torch.zeros(3, 1)})
    with pytest.raises(ValueError, match="empty buffer"):
        OutputDistillationMemory("a", {"input.x": torch.zeros(0, 1), "target": torch.zeros(0, 1)})
    with pytest.raises(ValueError, match="no 'input"):
        OutputDistillationMemory("a", {"target": torch.zeros(2, 1)})
    mem = OutputDistillationMemory("a", {"input.x": torch.zeros(2, 1), "target": torch.zeros(2, 3)})
    with pytest.raises(ValueError, match=r"policy output shape \(2, 2\) != stored target shape \(2, 3\)"):
        mem.loss(lambda obs: torch.zeros(2, 2), mem.sample(2))


def test_abstract_memory_cannot_be_instantiated():
    with pytest.raises(TypeError):
        Memory("a", {})  # type: ignore[abstract]


def test_atomic_write_keeps_the_old_file_when_the_rename_fails(tmp_path, monkeypatch):
    target = tmp_path / "ckpt.bin"
    atomic_write_bytes(target, b"old")

    def boom(*_args, **_kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError, match="disk full"):
        atomic_write_bytes(target, b"new")
    assert target.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["ckpt.bin"]


def test_summed_objective_equals_the_sum_of_per_memory_objectives():
    from sr_imitation.core.memory import summed_objective

    net = nn.Linear(4, 3)
    mems = [OutputDistillationMemory(f"s{i}", {"input.state": torch.randn(20, 4), "target": torch.randn(20, 3)})
            for i in range(3)]
    policy = lambda obs: net(obs["state"])  # noqa: E731
    joint = summed_objective(mems, policy, 5, torch.Generator().manual_seed(0))
    gen = torch.Generator().manual_seed(0)
    separate = sum(m.objective(policy, 5, gen) for m in mems)
    torch.testing.assert_close(joint, separate)
    with pytest.raises(ValueError, match="at least one"):
        summed_objective([], policy, 5)


def test_scalar_tensors_save_and_load(tmp_path):
    from sr_imitation.io import load_checked_safetensors

    save_checked_safetensors(tmp_path / "s.safetensors", {"log_alpha": torch.tensor(-1.5)}, {"format": "x"})
    tensors, _ = load_checked_safetensors(tmp_path / "s.safetensors")
    assert tensors["log_alpha"].shape == () and tensors["log_alpha"].item() == -1.5
