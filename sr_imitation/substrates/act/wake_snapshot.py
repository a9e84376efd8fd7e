"""Mid-wake snapshots for ACT-SR: a wake killed at any point resumes from its last epoch boundary with identical
results.

A wake is one phase of the stream engine (and the MT-Joint oracle's one training phase), and a phase killed inside
used to be redone from its start: same numbers, all its time again (5-30 min on a CPU preset, hours at the paper's
budgets on a GPU). So :func:`~sr_imitation.substrates.act.wake.wake_train` writes, at the end of an epoch every
``--wake.snapshot_every_s`` seconds of wall time (default 300, our choice), everything the rest of the wake depends
on to one checked safetensors file, and a wake that finds that file continues from it with the next epoch:

- the policy's whole state (the training-only VAE encoder included) and the optimizer's state;
- the weights of the best epoch so far, when the wake restores them at its end (``--wake.restore=best``);
- the wake's own generators (the training and validation loaders', the distillation's memory sampler) and the
  process's global ones (torch's, CUDA's on a GPU, numpy's, Python's): dropout, ACT's VAE sampling and the loaders'
  worker seeds draw from them;
- the loop's record: epochs done, steps, the per-epoch history, the best epoch and its validation l1, and the wall
  time run so far (so that the phase's reported compute time counts the time before the kill, as the SAC wake's
  does; it changes no number the wake computes);
- a continual method's wake hooks: their generator and counters and the method's own wake state
  (``ContinualMethod.wake_state``; every method with wake hooks declares ``resumable_wake_hooks``).

When and whether a snapshot is written depends on wall time only; writing one reads the state and draws nothing, so
the numbers of a run never depend on it (``tests/substrates/act/test_wake_snapshot.py`` kills wakes inside an epoch and
checks the resumed ones bit for bit against wakes that were never stopped). The file is removed when the wake ends.
Only the main process writes (the processes of a launched run hold the same state); every process reads it. A wake
shaped by hooks that do not declare their state (``resumable_wake_hooks`` False, a new method's default) is not
snapshotted: such a wake, killed, starts again from its start. The SAC wake's counterpart is
:mod:`sr_imitation.substrates.sac.wake_snapshot`.

Size, measured on the state-only Meta-World preset (AMD EPYC, one core): 8 MB written in 0.05 s at its default width
(0.68 M parameters: weights and AdamW's two moments), 32 MB in 0.2 s at the test preset's ``--policy.dim_model=256``
(2.7 M); ``--wake.restore=best`` adds the best weights (a third more).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from sr_imitation.infra.snapshot import (
    load_weights,
    optimizer_tensors,
    prefixed,
    read_snapshot,
    restore_optimizer,
    write_snapshot,
)

FORMAT = "sr_imitation.imitation.wake_snapshot"
"""The format name written in the file (the module's name before the substrates/ move: files keep their format)."""
VERSION = 1


@dataclass
class WakeGenerators:
    """The generators a wake owns (the process's global ones are saved beside them)."""

    train: torch.Generator
    validation: torch.Generator
    memory: torch.Generator | None
    """The distillation's memory sampler (``policy.memory_generator``); None for a policy without one."""

    def named(self) -> dict[str, torch.Generator]:
        out = {"train": self.train, "validation": self.validation}
        return out if self.memory is None else out | {"memory": self.memory}


@dataclass
class WakeRecord:
    """The loop's record at an epoch boundary (what :class:`~sr_imitation.substrates.act.wake.WakeResult` holds)."""

    epochs: int
    best_epoch: int
    best_val_l1: float
    steps: int
    history: list[dict[str, float]]
    seconds: float = 0.0
    """Wall time the wake had run when the snapshot was written (its time before earlier resumes included): reported
    as compute time only, never read by the loop. A snapshot written before this field existed reads as 0."""


def save(path: Path, identity: dict[str, Any], record: WakeRecord, policy: torch.nn.Module,
         optimizer: torch.optim.Optimizer, best_state: dict[str, torch.Tensor] | None,
         generators: WakeGenerators, hooks: Any = None) -> None:
    """Write the snapshot of a wake at the end of an epoch (atomically; checked on load); ``hooks``: the method's
    resumable wake hooks, if any."""
    tensors = {f"policy.{n}": t for n, t in policy.state_dict().items()}
    tensors.update(optimizer_tensors("optimizer", optimizer))
    if best_state is not None:
        tensors.update({f"best.{n}": t for n, t in best_state.items()})
    tensors.update({f"rng.{name}": g.get_state() for name, g in generators.named().items()})
    tensors["loop.best_val_l1"] = torch.tensor(record.best_val_l1, dtype=torch.float64)  # inf before a best
    header = {"epochs": record.epochs, "best_epoch": record.best_epoch, "steps": record.steps,
              "history": record.history, "best_state": best_state is not None,
              "seconds": round(record.seconds, 3)}
    write_snapshot(path, {"format": FORMAT, "version": VERSION, **identity}, tensors, header, hooks)


def load(path: Path, identity: dict[str, Any], policy: torch.nn.Module, optimizer: torch.optim.Optimizer,
         generators: WakeGenerators, hooks: Any = None) -> tuple[WakeRecord, dict[str, torch.Tensor] | None]:
    """Restore a wake from its snapshot into the freshly built ``policy``, ``optimizer`` and ``generators`` (and the
    process's global generators); returns the loop's record and the best epoch's weights (None when the wake keeps
    its last ones). A snapshot of another wake, format or policy is a :class:`~sr_imitation.io.CorruptFileError`
    naming the file."""
    tensors, header = read_snapshot(path, {"format": FORMAT, "version": VERSION, **identity}, hooks)
    load_weights(path, policy, prefixed(tensors, "policy."), "policy")
    restore_optimizer("optimizer", optimizer, tensors)
    for name, generator in generators.named().items():
        generator.set_state(tensors[f"rng.{name}"])
    record = WakeRecord(epochs=int(header["epochs"]), best_epoch=int(header["best_epoch"]),
                        best_val_l1=float(tensors["loop.best_val_l1"]), steps=int(header["steps"]),
                        history=list(header["history"]), seconds=float(header.get("seconds", 0.0)))
    return record, (prefixed(tensors, "best.") if header["best_state"] else None)
