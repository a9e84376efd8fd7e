"""Frozen skill memories: the interface both substrates implement (Section 3, "Wake phase and frozen skill
memories"; Algorithm 1, line 4).

A memory M_i is everything sleep needs from skill i: an unordered buffer (observations or states, no actions,
rewards or transitions) plus whatever frozen model defines the skill objective L_i(theta) for the *current*
shared policy. Concretely a memory is

* a flat mapping of named tensors (buffer tensors share their leading dimension N = buffer size; frozen model
  weights and normalizer statistics are further tensors), and
* a small JSON-able ``config`` (skill name, architecture, reduction, ...).

Because the state is only tensors plus JSON, every memory saves to one safetensors file with a JSON header
(skill, kind, format version, names, shapes, dtypes, checksum) and loads back bit-exactly. Memories are
immutable: tensors are cloned on creation, exposed through a read-only mapping, and attributes cannot be
reassigned; :meth:`Memory.fingerprint` lets tests prove that sleep leaves them untouched.

Concrete memories: :class:`OutputDistillationMemory` here (frozen teacher outputs on stored inputs, the
generic form of the imitation actor memory L_i^pi); the ACT actor memory (in the ACT-SR plugin,
``lerobot_policy_act_sr.actor_memory``) and the SAC critic memory (``sr_imitation.substrates.sac``) live beside what
writes them and register themselves with :func:`register_memory` when imported.
"""

from __future__ import annotations

import json
import os
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from types import MappingProxyType
from typing import Any, ClassVar

import torch
from torch import Tensor

from sr_imitation.io import (
    CorruptFileError,
    load_checked_safetensors,
    save_checked_safetensors,
    tensors_digest,
)

MEMORY_FORMAT_VERSION = 2
"""2: the header is checksummed too (``header_sha256``); 1: tensors only."""

PolicyFn = Callable[[Mapping[str, Tensor]], Tensor]
"""The current shared policy as a function of a batch of buffered inputs (a dict of tensors)."""

_MEMORY_KINDS: dict[str, type[Memory]] = {}


def register_memory(cls: type[Memory]) -> type[Memory]:
    """Class decorator: make a memory kind loadable by :func:`load_memory`."""
    kind = cls.kind
    if kind in _MEMORY_KINDS and _MEMORY_KINDS[kind] is not cls:
        raise ValueError(f"memory kind {kind!r} is already registered by {_MEMORY_KINDS[kind].__name__}")
    _MEMORY_KINDS[kind] = cls
    return cls


def memory_contents(kind: str) -> str:
    """What a registered memory kind holds, in words (the kind's name when no class of it is imported)."""
    cls = _MEMORY_KINDS.get(kind)
    return cls.contents if cls is not None and cls.contents else kind


class Memory(ABC):
    """A frozen skill memory that defines a differentiable skill objective L_i(theta).

    Subclasses set ``kind``, declare ``buffer_keys`` (tensors sampled along their first dimension) and
    implement :meth:`loss`. The constructor validates and freezes the state.

    Args:
        skill: name of the skill this memory stores.
        tensors: the memory's state (buffers, frozen weights, statistics); cloned and frozen here.
        config: JSON-serializable settings needed to evaluate the objective.
    """

    kind: ClassVar[str]
    buffer_keys: ClassVar[tuple[str, ...]] = ()
    contents: ClassVar[str] = ""
    """What the memory holds, in words (the memory-budget tables)."""
    provenance_keys: ClassVar[tuple[str, ...]] = ()
    """Config keys that only record where the memory came from (a snapshot's name) and leave its objective unchanged:
    memories that differ only there are evaluated in one policy call (:func:`per_memory_losses`)."""

    def __init__(self, skill: str, tensors: Mapping[str, Tensor], config: Mapping[str, Any] | None = None):
        if not skill:
            raise ValueError("a memory needs a non-empty skill name")
        frozen = {}
        for name, t in tensors.items():
            if not isinstance(t, Tensor):
                raise TypeError(f"memory tensor {name!r} must be a torch.Tensor, got {type(t).__name__}")
            frozen[name] = t.detach().clone().requires_grad_(False)
        object.__setattr__(self, "skill", str(skill))
        object.__setattr__(self, "_tensors", MappingProxyType(frozen))
        object.__setattr__(self, "config", MappingProxyType(dict(config or {})))
        self._validate()

    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError(f"{type(self).__name__} is immutable; cannot set {name!r}")

    # -- state -----------------------------------------------------------------------------------------
    @property
    def tensors(self) -> Mapping[str, Tensor]:
        """Read-only view of the memory's tensors (do not modify them in place)."""
        return self._tensors

    @property
    def size(self) -> int:
        """Number of buffered samples N."""
        return int(self._tensors[self.buffer_keys[0]].shape[0]) if self.buffer_keys else 0

    def nbytes(self) -> int:
        """Bytes of all stored tensors (buffers, frozen weights, statistics) for the memory-budget table."""
        return sum(t.numel() * t.element_size() for t in self._tensors.values())

    def fingerprint(self) -> str:
        """sha256 of the memory's tensors: equal before and after sleep if the memory stayed frozen."""
        return tensors_digest(self._tensors)

    def _validate(self) -> None:
        missing = [k for k in self.buffer_keys if k not in self._tensors]
        if missing:
            raise ValueError(f"{type(self).__name__}({self.skill!r}) is missing buffer tensors {missing}")
        sizes = {k: int(self._tensors[k].shape[0]) for k in self.buffer_keys}
        if len(set(sizes.values())) > 1:
            raise ValueError(f"{type(self).__name__}({self.skill!r}) buffer sizes differ: {sizes}")
        if self.buffer_keys and self.size == 0:
            raise ValueError(f"{type(self).__name__}({self.skill!r}) has an empty buffer")

    # -- objective -------------------------------------------------------------------------------------
    def sample(self, batch_size: int, generator: torch.Generator | None = None) -> dict[str, Tensor]:
        """Draw ``batch_size`` buffer entries uniformly with replacement (the buffer is unordered)."""
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        idx = torch.randint(self.size, (batch_size,), generator=generator)
        return {k: self._tensors[k][idx] for k in self.buffer_keys}

    @abstractmethod
    def loss(self, policy: Any, batch: Mapping[str, Tensor]) -> Tensor:
        """L_i(theta) on a sampled ``batch`` for the current ``policy``: a differentiable scalar."""

    def scale(self, policy: Any, generator: torch.Generator) -> float:
        """How much L_i can change for this memory, for ``policy`` now (> 0): what a sleep with
        ``early_stop_scale=memory_scale`` measures its plateau rule against. Memory kinds whose loss level is that
        scale need not define it; the others (a frozen critic's value) do."""
        raise ValueError(f"sleep.early_stop_scale=memory_scale: a {self.kind!r} memory has no scale of its own; use "
                         "early_stop_scale=window")

    def segment_losses(self, policy: Any, joint_batch: Mapping[str, Tensor], segments: int) -> Tensor | None:
        """Losses of ``segments`` equal consecutive parts of a concatenated batch from one policy call.

        Memories of one class and config whose objective is a mean over samples can evaluate several memories'
        batches in a single forward pass; return ``None`` (the default) where that is not possible.
        """
        return None

    def objective(self, policy: Any, batch_size: int, generator: torch.Generator | None = None) -> Tensor:
        """L_i(theta) on a fresh uniform batch: ``loss(policy, sample(batch_size))``."""
        return self.loss(policy, self.sample(batch_size, generator))

    # -- persistence -----------------------------------------------------------------------------------
    def header(self) -> dict[str, Any]:
        return {
            "format": "sr_imitation.memory",
            "format_version": MEMORY_FORMAT_VERSION,
            "kind": self.kind,
            "skill": self.skill,
            "config": dict(self.config),
        }

    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write the memory atomically to one safetensors file with a JSON header."""
        return save_checked_safetensors(path, self._tensors, self.header())

    @classmethod
    def load(cls, path: str | os.PathLike[str], skill: str | None = None) -> Memory:
        """Load a memory saved by :meth:`save`, checking kind (and skill, if given)."""
        memory = load_memory(path, skill=skill)
        if cls is not Memory and not isinstance(memory, cls):
            raise CorruptFileError(path, f"memory kind {memory.kind!r} is not a {cls.__name__}")
        return memory

    def __repr__(self) -> str:
        return f"{type(self).__name__}(skill={self.skill!r}, size={self.size}, nbytes={self.nbytes()})"


def summed_objective(
    memories: Sequence[Memory], policy: Any, batch_size: int, generator: torch.Generator | None = None
) -> Tensor:
    """sum_i L_i(theta), each on its own fresh batch of ``batch_size``, with one policy call per memory kind.

    Used by wake-time distillation, where only the sum's gradient is needed (see :func:`per_memory_losses`).
    """
    if not memories:
        raise ValueError("summed_objective needs at least one memory")
    batches = [m.sample(batch_size, generator) for m in memories]
    return torch.stack(per_memory_losses(memories, policy, batches)).sum()


def _group_key(memory: Memory) -> tuple[type, str]:
    """Memories with equal keys share one policy call: same class, same config up to the provenance keys."""
    config = {k: v for k, v in memory.config.items() if k not in memory.provenance_keys}
    return type(memory), json.dumps(config, sort_keys=True)


def per_memory_losses(memories: Sequence[Memory], policy: Any, batches: Sequence[Mapping[str, Tensor]]) -> list[Tensor]:
    """[L_i(theta) on batches[i]], with one policy call per group of same-kind memories when they allow it."""
    losses: list[Tensor | None] = [None] * len(memories)
    groups: dict[tuple[type, str], list[int]] = {}
    for i, memory in enumerate(memories):
        groups.setdefault(_group_key(memory), []).append(i)
    for idx in groups.values():
        sizes = {len(next(iter(batches[i].values()))) for i in idx}
        joint_losses = None
        if len(idx) > 1 and len(sizes) == 1:
            joint = {k: torch.cat([batches[i][k] for i in idx]) for k in batches[idx[0]]}
            joint_losses = memories[idx[0]].segment_losses(policy, joint, len(idx))
        for n, i in enumerate(idx):
            losses[i] = joint_losses[n] if joint_losses is not None else memories[i].loss(policy, batches[i])
    return losses  # type: ignore[return-value]


def load_memory(path: str | os.PathLike[str], skill: str | None = None) -> Memory:
    """Load any registered memory kind from ``path``.

    Raises:
        FileNotFoundError: missing file.
        CorruptFileError: unreadable file, wrong format or version, unknown kind, skill mismatch, or tensors
            inconsistent with the header; the message names the file and the mismatch.
    """
    tensors, header = load_checked_safetensors(path)
    if header.get("format") != "sr_imitation.memory":
        raise CorruptFileError(path, f"not a memory file (format {header.get('format')!r})")
    if header.get("format_version") != MEMORY_FORMAT_VERSION:
        raise CorruptFileError(
            path, f"memory format version {header.get('format_version')} != supported {MEMORY_FORMAT_VERSION}"
        )
    kind = header.get("kind")
    if kind not in _MEMORY_KINDS:
        raise CorruptFileError(path, f"unknown memory kind {kind!r}; known: {sorted(_MEMORY_KINDS)}")
    if skill is not None and header.get("skill") != skill:
        raise CorruptFileError(path, f"memory is for skill {header.get('skill')!r}, expected {skill!r}")
    try:
        return _MEMORY_KINDS[kind](header["skill"], tensors, header.get("config", {}))
    except (ValueError, TypeError, KeyError) as exc:
        raise CorruptFileError(path, f"invalid {kind} memory: {exc}") from exc


REDUCTIONS = ("sum", "mean")


def _check_reduction(reduction: str) -> None:
    if reduction not in REDUCTIONS:
        raise ValueError(f"reduction must be 'sum' or 'mean', got {reduction!r}")


class WeightsMemory(Memory):
    """Weights a method keeps that are not a consolidation objective (counted in the memory budget only)."""

    def loss(self, policy: Any, batch: Any) -> Tensor:
        raise NotImplementedError(f"a {self.kind} memory is counted in the memory budget; it has no objective")


@register_memory
class PolicySnapshot(WeightsMemory):
    """The previous policy's weights, the one rolling teacher of LwF and M2Distill."""

    kind = "policy_snapshot"
    contents = "the policy before this skill's wake (one rolling copy of its weights)"


@register_memory
class OutputDistillationMemory(Memory):
    """Frozen-snapshot distillation memory: L_i = E_{o ~ B_i} ||pi_theta(o) - pi_{theta_i}(o)||^2.

    The snapshot's outputs on the buffer never change, so they are computed once at creation
    (:meth:`from_snapshot`) and stored as ``target``; the snapshot itself is not needed during sleep. Inputs
    are stored under ``input.<name>`` and passed to the policy as a dict ``{name: tensor}``.

    ``config["reduction"]``: ``"sum"`` (default; squared l2 norm per sample, averaged over the batch, exactly
    the paper's expectation) or ``"mean"`` (also averaged over output elements: Eq. divided by the output size,
    the same gradient direction).
    """

    kind = "output_distillation"
    contents = "inputs (states or observations) + the policy's outputs on them"

    def __init__(self, skill: str, tensors: Mapping[str, Tensor], config: Mapping[str, Any] | None = None):
        config = {"reduction": "sum", **dict(config or {})}
        _check_reduction(config["reduction"])
        super().__init__(skill, tensors, config)

    @property
    def buffer_keys(self) -> tuple[str, ...]:  # type: ignore[override]
        return self._buffer_keys

    def _validate(self) -> None:
        inputs = sorted(k for k in self._tensors if k.startswith("input."))
        object.__setattr__(self, "_buffer_keys", ("target", *inputs))
        if not inputs:
            raise ValueError(f"OutputDistillationMemory({self.skill!r}) stores no 'input.*' tensors")
        super()._validate()

    @classmethod
    def from_snapshot(
        cls,
        skill: str,
        snapshot: PolicyFn,
        inputs: Mapping[str, Tensor],
        batch_size: int = 256,
        reduction: str = "sum",
    ) -> OutputDistillationMemory:
        """Evaluate the frozen ``snapshot`` once on ``inputs`` (in batches, no grad) and store the targets."""
        _check_reduction(reduction)  # before the snapshot's forward passes, not after
        n = int(next(iter(inputs.values())).shape[0])
        outs = []
        with torch.no_grad():
            for start in range(0, n, batch_size):
                outs.append(snapshot({k: v[start : start + batch_size] for k, v in inputs.items()}).detach())
        tensors = {f"input.{k}": v for k, v in inputs.items()}
        tensors["target"] = torch.cat(outs).cpu()
        return cls(skill, tensors, {"reduction": reduction})

    def _per_sample(self, policy: PolicyFn, batch: Mapping[str, Tensor]) -> Tensor:
        """Squared error per sample: summed (``sum``) or averaged (``mean``) over the output elements."""
        obs = {k.removeprefix("input."): v for k, v in batch.items() if k.startswith("input.")}
        pred = policy(obs)
        target = batch["target"].to(pred.device, pred.dtype)
        if pred.shape != target.shape:
            raise ValueError(
                f"memory {self.skill!r}: policy output shape {tuple(pred.shape)} != stored target shape "
                f"{tuple(target.shape)}"
            )
        err = (pred - target).pow(2).flatten(1)
        return err.mean(dim=1) if self.config["reduction"] == "mean" else err.sum(dim=1)

    def loss(self, policy: PolicyFn, batch: Mapping[str, Tensor]) -> Tensor:
        return self._per_sample(policy, batch).mean()

    def segment_losses(self, policy: PolicyFn, joint_batch: Mapping[str, Tensor], segments: int) -> Tensor:
        return self._per_sample(policy, joint_batch).view(segments, -1).mean(dim=1)
