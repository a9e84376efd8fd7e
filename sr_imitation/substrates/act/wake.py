"""Wake phase for ACT-SR (Appendix A.2, "Wake training"): behaviour cloning on the current skill's data, plus the
policy's own distillation term when earlier memories are attached; AdamW from ACT's optimizer preset (lr 1e-4,
backbone 1e-5, weight decay 1e-4); up to ``max_epochs`` epochs; early stopping on an l1 validation plateau after
``min_epochs``; the best-l1 weights restored at the end.

Each step is LeRobot's own ``update_policy`` (forward, backward, gradient clipping, optimizer step). Given a
``snapshot`` path, the wake keeps a snapshot every few minutes and a wake killed inside continues from it with
identical results (:mod:`sr_imitation.substrates.act.wake_snapshot`).
"""

from __future__ import annotations

import contextlib
import copy
import logging
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch
from accelerate import Accelerator
from lerobot.scripts.lerobot_train import update_policy
from lerobot.utils.constants import ACTION
from lerobot.utils.logging_utils import AverageMeter, MetricsTracker
from torch.utils.data import DataLoader, Subset

from sr_imitation.infra.distributed import Processes, average_gradients, average_scalars, current, shard
from sr_imitation.infra.snapshot import EVERY_S
from sr_imitation.progress import Progress
from sr_imitation.substrates.act import wake_snapshot
from sr_imitation.substrates.act.data import SkillData

logger = logging.getLogger(__name__)


RESTORE_CHOICES = ("best", "last")


class NonFiniteLossError(FloatingPointError):
    """A wake loss became NaN or Inf; training stops before the weights are touched by it."""


@dataclass
class WakeConfig:
    """Wake budget (paper: up to 100 epochs, early stopping after at least 30, batch 8).

    Each field is documented below (``--help`` shows it).
    """

    max_epochs: int = 100
    """Epoch budget per skill (paper 100)."""
    min_epochs: int = 30
    """Epochs before early stopping may trigger (paper 30)."""
    patience: int = 10
    """Epochs without a new best validation l1 before stopping."""
    batch_size: int = 8
    """Wake batch size (paper 8)."""
    val_fraction: float = 0.1
    """Share of each skill's episodes held out for the validation l1."""
    max_steps_per_epoch: int | None = None
    """Cap on optimizer steps per epoch (CPU presets); null = full epochs."""
    grad_clip_norm: float = 10.0
    """Gradient clipping, as in lerobot-train."""
    num_workers: int = 0
    """DataLoader workers (0-1 on a 2-core CPU; do not change results)."""
    snapshot_every_s: float = EVERY_S
    """Seconds of wall time between two mid-wake snapshots (:mod:`sr_imitation.substrates.act.wake_snapshot`, written at
    an epoch's end: a wake killed inside continues from the last one); 0 - at every epoch's end; negative - never. Does
    not change results (a resume may change it)."""
    restore: str = "best"
    """Weights kept at the end of the wake - best (the epoch with the lowest validation l1, the paper's early
    stopping) or last. The validation l1 is dominated by the expert's +-0.2 action noise and stops tracking
    closed-loop success early (docs/RESULTS.md), so a fixed budget keeping the last weights can be better
    (our choice for the CPU preset)."""

    def __post_init__(self) -> None:
        if self.min_epochs < 1:
            raise ValueError(f"wake.min_epochs must be >= 1, got {self.min_epochs}")
        if self.min_epochs > self.max_epochs:
            raise ValueError(f"wake.max_epochs={self.max_epochs} is below wake.min_epochs={self.min_epochs} (the "
                             f"epochs always trained before early stopping may end the wake); give "
                             f"--wake.min_epochs={self.max_epochs} too, or a wake.max_epochs >= {self.min_epochs}")
        if self.patience < 1 or self.batch_size < 1:
            raise ValueError("patience and batch_size must be >= 1")
        if not 0.0 <= self.val_fraction < 1.0:
            raise ValueError(f"val_fraction must be in [0, 1), got {self.val_fraction}")
        if self.restore not in RESTORE_CHOICES:
            raise ValueError(f"restore must be one of {RESTORE_CHOICES}, got {self.restore!r}")
        if self.max_steps_per_epoch is not None and self.max_steps_per_epoch < 1:
            raise ValueError(f"max_steps_per_epoch must be >= 1 or null, got {self.max_steps_per_epoch}")
        if math.isnan(self.snapshot_every_s):
            raise ValueError("wake.snapshot_every_s must be a number of seconds (negative: no snapshots), got nan")


@dataclass
class WakeResult:
    skill: str
    epochs: int
    best_epoch: int
    best_val_l1: float
    steps: int
    history: list[dict[str, float]] = field(default_factory=list)
    seconds_before_resume: float = 0.0
    """Wall time the wake had run before the snapshot it resumed from (0 for a wake run in one go): a phase's time is
    measured from the process that finishes it, so the caller adds this to report the wake's whole compute time. Not
    part of :meth:`history_record`: it depends on where the wake was killed."""

    def history_record(self) -> dict[str, Any]:
        """What ``wake_history.json`` keeps: the same for a wake run in one go and for one killed and resumed."""
        record = asdict(self)
        del record["seconds_before_resume"]
        return record


def masked_chunk_l1(policy: Any, batch: dict[str, torch.Tensor]) -> tuple[float, int]:
    """Sum and count of the deterministic chunk's l1 error on non-padded steps (normalized actions)."""
    with torch.no_grad():
        pred = policy.action_chunk(batch)
        err = (pred - batch[ACTION]).abs() * (~batch["action_is_pad"]).unsqueeze(-1)
        return float(err.sum()), int((~batch["action_is_pad"]).sum()) * pred.shape[-1]


def validation_l1(policy: Any, preprocessor: Any, loader: DataLoader) -> float:
    total, count = 0.0, 0
    for raw in loader:
        s, c = masked_chunk_l1(policy, preprocessor(raw))
        total, count = total + s, count + c
    return total / max(count, 1)


def _loader(data: SkillData, indices: list[int], batch_size: int, shuffle: bool, seed: int, workers: int):
    return DataLoader(
        Subset(data.dataset, indices), batch_size=batch_size, shuffle=shuffle, num_workers=workers,
        generator=torch.Generator().manual_seed(seed), drop_last=False,
    )


@contextlib.contextmanager
def mixed_precision(policy: Any) -> Iterator[None]:
    """``--policy.use_amp``: the wake's forward passes (and a method's loss terms) under bfloat16 autocast, as
    accelerate's ``mixed_precision="bf16"`` runs them (``torch.autocast``; on CPU and on GPUs with bfloat16, no loss
    scaling needed); the backward pass, gradients, optimizer state and weights stay float32, and so do the
    validation l1, the sleep and the evaluation (our choice: the sleep's Gram matrix and Nash weights want float32).
    Without ``use_amp``: nothing."""
    if not policy.config.use_amp:
        yield
        return
    with torch.autocast(device_type=torch.device(policy.config.device).type, dtype=torch.bfloat16):
        yield


class _NoHooks:
    """The identity hooks (a method without wake hooks) for :func:`hooked_update`."""

    def batch(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        return batch

    def loss(self, loss: torch.Tensor) -> torch.Tensor:
        return loss

    def adjust(self) -> None:
        return None


def hooked_update(tracker: MetricsTracker, policy: Any, batch: dict[str, torch.Tensor], optimizer: Any,
                  grad_clip_norm: float, hooks: Any, processes: Processes | None = None
                  ) -> tuple[MetricsTracker, dict]:
    """LeRobot's ``update_policy`` step (forward, backward, gradient clipping, optimizer step) with a continual
    method's hooks between: ``hooks.batch(batch)`` gives the batch the update trains on (experience replay mixes in
    stored frames), ``hooks.loss(loss)`` replaces the loss before the backward pass and ``hooks.adjust()`` may
    change the gradients before clipping; the forward pass under :func:`mixed_precision`. Used when the method has
    hooks, ``--policy.use_amp`` is on or the run has several processes (without any, LeRobot's ``update_policy``
    itself: its CPU accelerator's calls reduce to these).

    Several ``processes`` (:mod:`sr_imitation.infra.distributed`): the method's batch (the same on every process) is
    cut into one contiguous slice per process, each process's loss is the mean over its slice plus the terms every
    process computes alike, and the gradients are averaged with each process's share of the rows before the method
    adjusts them, so the step is the one-process step on the whole batch up to float summation order; the logged
    loss and outputs are the batch's (share-weighted sums, one all-reduce)."""
    start = time.perf_counter()
    processes = processes or Processes()
    policy.train()
    # LeRobot 0.6's ACT L1 loss is a mean over non-padded elements: slices are weighted by their count of them.
    batch, share = shard(hooks.batch(batch), processes, pad_key="action_is_pad")
    with mixed_precision(policy):
        loss, output = policy.forward(batch)
        loss = hooks.loss(loss)
    loss.backward()
    if processes.distributed:
        average_gradients(list(policy.parameters()), share)
    hooks.adjust()
    limit = grad_clip_norm if grad_clip_norm > 0 else float("inf")
    grad_norm = torch.nn.utils.clip_grad_norm_(policy.parameters(), limit, error_if_nonfinite=False)
    optimizer.step()
    optimizer.zero_grad()
    loss_value = loss.item()
    if processes.distributed:
        keys = list(output)
        loss_value, *values = average_scalars([loss_value, *(float(output[k]) for k in keys)], share)
        output = dict(zip(keys, values, strict=True))
    tracker.loss = loss_value  # a MetricsTracker records what is set (reading it back gives its AverageMeter)
    tracker.grad_norm = grad_norm.item()
    tracker.lr = optimizer.param_groups[0]["lr"]
    tracker.update_s = time.perf_counter() - start
    return tracker, output


def wake_train(
    policy: Any,
    preprocessor: Any,
    data: SkillData,
    cfg: WakeConfig,
    seed: int,
    progress: bool = True,
    on_epoch: Callable[[int, dict[str, float]], None] | None = None,
    hooks: Any = None,
    snapshot: Path | None = None,
) -> WakeResult:
    """Train ``policy`` in place on one skill; returns the history and the restored best epoch.

    ``snapshot``: where the wake keeps its snapshot (:mod:`sr_imitation.substrates.act.wake_snapshot`), written at the
    end of an epoch every ``cfg.snapshot_every_s`` seconds (never if negative); a wake that finds one continues from it,
    and removes it when it ends. Ignored with ``hooks`` that do not declare their state (``not hooks.resumable``: such
    a wake, killed, starts again)."""
    device = policy.config.device
    accelerator = Accelerator(cpu=device == "cpu")
    processes = current()
    if policy.config.use_amp:
        logger.info("policy.use_amp: the wake's forward passes run under bfloat16 autocast on %s (backward pass, "
                    "weights, validation, sleep and evaluation in float32)", policy.config.device)
    optimizer = policy.config.get_optimizer_preset().build(policy.get_optim_params())
    train_loader = _loader(data, data.train_indices, cfg.batch_size, True, seed, cfg.num_workers)
    val_indices = data.val_indices or data.train_indices  # a one-episode dataset validates on its training data
    val_loader = _loader(data, val_indices, cfg.batch_size, False, seed, cfg.num_workers)
    steps_per_epoch = len(train_loader)
    if cfg.max_steps_per_epoch is not None:
        steps_per_epoch = min(steps_per_epoch, cfg.max_steps_per_epoch)
    tracker = MetricsTracker(cfg.batch_size, len(data.train_indices), max(1, len(data.train_indices)),
                             {"loss": AverageMeter("loss", ":.3f"), "grad_norm": AverageMeter("grdn", ":.3f"),
                              "lr": AverageMeter("lr", ":0.1e"), "update_s": AverageMeter("updt_s", ":.3f")})
    result = WakeResult(data.skill, 0, -1, math.inf, 0)
    best_state: dict[str, torch.Tensor] | None = None
    if hooks is not None and not hooks.resumable:
        snapshot = None  # hooks that do not declare their state: such a wake, killed, starts again
    generators = wake_snapshot.WakeGenerators(train_loader.generator, val_loader.generator,
                                              getattr(policy, "memory_generator", None))
    identity = {"skill": data.skill, "seed": seed, "train_frames": len(data.train_indices),
                "steps_per_epoch": steps_per_epoch, "max_epochs": cfg.max_epochs}
    if snapshot is not None and snapshot.is_file():
        loop, best_state = wake_snapshot.load(snapshot, identity, policy, optimizer, generators, hooks)
        result = WakeResult(data.skill, loop.epochs, loop.best_epoch, loop.best_val_l1, loop.steps, loop.history,
                            loop.seconds)
        logger.info("wake %s: resumed from %s after %d epochs (%d steps)", data.skill, snapshot, result.epochs,
                    result.steps)
    every_s = cfg.snapshot_every_s  # negative: none written (one found is still continued from, then removed)
    started = last_snapshot = time.perf_counter()
    bar = Progress(cfg.max_epochs * steps_per_epoch, f"wake {data.skill}", logger, enabled=progress,
                   initial=result.steps)
    for epoch in range(result.epochs, cfg.max_epochs):
        sums: dict[str, float] = {}
        for step, raw in enumerate(train_loader):
            if step >= steps_per_epoch:
                break
            batch = preprocessor(raw)
            try:
                if hooks is None and not policy.config.use_amp and not processes.distributed:
                    tracker, out = update_policy(tracker, policy, batch, optimizer, cfg.grad_clip_norm, accelerator)
                else:
                    tracker, out = hooked_update(tracker, policy, batch, optimizer, cfg.grad_clip_norm,
                                                 hooks or _NoHooks(), processes)
            except FloatingPointError as exc:
                raise NonFiniteLossError(
                    f"wake on skill {data.skill!r} ({data.root}): epoch {epoch} step {step}: {exc}"
                ) from exc
            for key, value in out.items():
                sums[key] = sums.get(key, 0.0) + float(value)
            # the loss the step minimised, a method's wake term (EWC's penalty, LwF's distillation) included: the
            # policy's outputs alone do not show it
            sums["loss"] = sums.get("loss", 0.0) + float(tracker.loss.val)
            result.steps += 1
            bar.update(1)
        val_l1 = validation_l1(policy, preprocessor, val_loader)
        record = {"epoch": epoch, "val_l1": val_l1, **{k: v / steps_per_epoch for k, v in sums.items()}}
        result.history.append(record)
        result.epochs = epoch + 1
        if val_l1 < result.best_val_l1:
            result.best_val_l1, result.best_epoch = val_l1, epoch
            if cfg.restore == "best":
                best_state = copy.deepcopy(policy.state_dict())
        bar.set_postfix(val_l1=f"{val_l1:.4f}", best=f"{result.best_val_l1:.4f}")
        logger.info("wake %s epoch %d: %s", data.skill, epoch, {k: round(v, 5) for k, v in record.items()})
        if on_epoch is not None:
            on_epoch(epoch, record)
        if epoch + 1 >= cfg.min_epochs and epoch - result.best_epoch >= cfg.patience:
            logger.info("wake %s: l1 plateau, stopping after epoch %d (best %d)", data.skill, epoch,
                        result.best_epoch)
            break
        if (snapshot is not None and processes.is_main and epoch + 1 < cfg.max_epochs and every_s >= 0
                and time.perf_counter() - last_snapshot >= every_s):
            loop = wake_snapshot.WakeRecord(result.epochs, result.best_epoch, result.best_val_l1, result.steps,
                                            result.history,
                                            result.seconds_before_resume + time.perf_counter() - started)
            wake_snapshot.save(snapshot, identity, loop, policy, optimizer, best_state, generators, hooks)
            last_snapshot = time.perf_counter()
    bar.close()
    if snapshot is not None and processes.is_main:
        snapshot.unlink(missing_ok=True)
    if best_state is not None:
        policy.load_state_dict(best_state)
    return result
