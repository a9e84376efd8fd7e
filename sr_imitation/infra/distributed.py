"""Several processes for one run: the wake's updates data-parallel, the main process the only writer of the run.

``torchrun --nproc_per_node=N -m sr_imitation.cli ...`` (on GPUs also ``accelerate launch --multi_gpu
--num_processes=N -m sr_imitation.cli ...``; ``accelerate launch --cpu`` starts one process) starts N copies of
``sr-train``; :func:`start` joins them through accelerate's ``PartialState`` (gloo on CPU, NCCL
on CUDA), the way ``lerobot-train`` does. Every process runs the whole stream engine, because what each phase
needs (the policy, the earlier skills' memories, the sleep's anchor) is the same on every process and cheaper to
recompute than to send:

- **wake**: every process draws the same global batch (the same data loader, seeded alike) and trains on its own
  contiguous slice of it (:func:`shard`); after the backward pass the gradients are averaged over the processes,
  each weighted by its share of the batch (:func:`average_gradients`, one all-reduce of the flattened gradients),
  so each optimizer step sees the gradient of the whole batch: a one-process run with the same batch size, up to
  float summation order. Terms every process computes alike (the distillation loss on stored memories, a method's
  penalty) keep their full weight. Random draws inside the forward pass (dropout, ACT's VAE) differ from a
  one-process run's, so its results are equal only without them (they are equal in distribution).
- **sleep**: on every process, identically (the same memories, seeds and weights give the same steps; the other
  processes would otherwise wait for the main one).
- **evaluation**: on the main process only; the others wait at the next collective.
- **files**: the main process writes the run directory (checkpoints, memories, logs, results, videos). The others
  keep their own copy of the run's state in a private scratch folder (:func:`scratch_output`, removed at the end;
  one a killed process left is removed when the next run starts, :func:`remove_stale_scratch`),
  so that the engine's loads and a resume work unchanged; a resume first copies the run directory there.
"""

from __future__ import annotations

import logging
import os
import re
import shutil
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Processes:
    """Where this process stands among the run's processes (one process: rank 0 of 1)."""

    rank: int = 0
    world_size: int = 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world_size > 1


def launched_world_size() -> int:
    """The number of processes a launcher (``torchrun``, ``accelerate launch``) started, from its environment."""
    return int(os.environ.get("WORLD_SIZE", "1"))


def start(cpu: bool) -> Processes:
    """Join the other processes of a launched run (accelerate's ``PartialState``: gloo on CPU); one process: nothing
    to join. ``cpu``: the run's device is the CPU (CUDA processes take the GPU of their local rank)."""
    if launched_world_size() <= 1:
        return Processes()
    from accelerate import PartialState

    state = PartialState(cpu=cpu)
    logger.info("process %d of %d (%s, backend %s)", state.process_index, state.num_processes,
                state.distributed_type, state.backend)
    return Processes(state.process_index, state.num_processes)


def current() -> Processes:
    """This process's place, once :func:`start` has joined the group (otherwise: one process)."""
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        return Processes(torch.distributed.get_rank(), torch.distributed.get_world_size())
    return Processes()


def barrier() -> None:
    """Wait for every process (nothing to wait for with one)."""
    if current().distributed:
        torch.distributed.barrier()


def shard(batch: Mapping[str, Any], processes: Processes, pad_key: str | None = None) -> tuple[dict[str, Any], float]:
    """This process's contiguous slice of a global batch (every tensor and list cut along its first dimension, as
    ``torch.tensor_split`` cuts: sizes differ by at most one) and its share of the batch. A batch with fewer
    rows than processes (an epoch's last one) is not cut: every process takes all of it with share 1 / N, so that
    every process runs the same forward passes (and draws from the same generators). One process: the batch
    itself, share 1.

    Args:
        batch: the global batch (the same on every process).
        processes: this process among the run's.
        pad_key: a boolean padding mask in ``batch`` (True = padded) when the loss is a mean over its non-padded
            elements (LeRobot 0.6's ACT L1 loss divides by their count): the share is then this slice's count of
            non-padded elements over the batch's, so that the share-weighted sum of the slices' losses is the
            batch's loss. ``None`` (or no such key): the share of rows.

    Returns:
        The slice and its share (the shares of all processes sum to 1).
    """
    if not processes.distributed:
        return dict(batch), 1.0
    sizes = {len(v) for v in batch.values() if isinstance(v, torch.Tensor | list)}
    if len(sizes) != 1:
        raise ValueError(f"shard: a batch's fields have different lengths {sorted(sizes)}")
    n = sizes.pop()
    if n < processes.world_size:
        return dict(batch), 1.0 / processes.world_size
    bounds = [len(part) for part in torch.tensor_split(torch.arange(n), processes.world_size)]
    start = sum(bounds[: processes.rank])
    stop = start + bounds[processes.rank]
    out = {k: v[start:stop] if isinstance(v, torch.Tensor | list) else v for k, v in batch.items()}
    if pad_key is not None and isinstance(batch.get(pad_key), torch.Tensor):
        valid = ~batch[pad_key].bool()
        total = int(valid.sum())
        if total > 0:
            return out, int(valid[start:stop].sum()) / total
    return out, (stop - start) / n


def average_gradients(params: Sequence[torch.nn.Parameter], share: float) -> None:
    """Replace every parameter's gradient by the share-weighted sum over the processes, sum_r share_r * g_r, i.e. the
    gradient of the whole batch when each process's loss is a mean over its slice. One all-reduce of the flattened
    gradients; which parameters have a gradient is the same on every process (the same model and forward pass)."""
    if not current().distributed:
        return
    used = [p for p in params if p.grad is not None]
    if not used:
        return
    flat = torch.cat([p.grad.reshape(-1) for p in used]) * share
    torch.distributed.all_reduce(flat, op=torch.distributed.ReduceOp.SUM)
    offset = 0
    for p in used:
        n = p.numel()
        p.grad = flat[offset : offset + n].view_as(p).clone()
        offset += n


def average_scalars(values: Sequence[float], share: float) -> list[float]:
    """The share-weighted sums of per-process numbers (slices' mean losses -> the batch's), in one all-reduce."""
    if not current().distributed:
        return list(values)
    t = torch.tensor([v * share for v in values], dtype=torch.float64)
    torch.distributed.all_reduce(t, op=torch.distributed.ReduceOp.SUM)
    return t.tolist()


def scratch_output(output_dir: Path, resume: bool, processes: Processes) -> Path:
    """Where a process other than the main one keeps its copy of the run (a fresh private folder; on ``resume`` a
    copy of the run directory, taken before any process touches it). The main process: ``output_dir`` itself."""
    remove_stale_scratch()  # what a killed process of an earlier run left
    if processes.is_main:
        return output_dir
    scratch = Path(tempfile.mkdtemp(prefix=f"{SCRATCH_PREFIX}{processes.rank}-pid{os.getpid()}-")) / Path(
        output_dir).name
    if resume and Path(output_dir).is_dir():
        shutil.copytree(output_dir, scratch, symlinks=True)
    return scratch


SCRATCH_PREFIX = "sr-train-rank"
"""``<tmp>/sr-train-rank<rank>-pid<process id>-<random>/``: a non-main process's scratch (:func:`scratch_output`)."""


def remove_stale_scratch(root: Path | None = None) -> list[Path]:
    """Remove the scratch folders (:data:`SCRATCH_PREFIX`, in ``root``: the temporary folder) of processes that no
    longer run (a killed rank skips :func:`remove_scratch`); a folder whose process still runs, or that another user
    owns, is kept. Returns the folders removed."""
    root = Path(tempfile.gettempdir() if root is None else root)
    removed = []
    for folder in root.glob(f"{SCRATCH_PREFIX}*-pid*-*"):
        match = re.fullmatch(rf"{SCRATCH_PREFIX}\d+-pid(\d+)-.+", folder.name)
        try:
            mine = folder.is_dir() and not folder.is_symlink() and folder.stat().st_uid == os.getuid()
        except OSError:
            continue
        if match is None or not mine or _running(int(match.group(1))):
            continue
        shutil.rmtree(folder, ignore_errors=True)
        logger.info("removed %s (the scratch copy of a process that no longer runs)", folder)
        removed.append(folder)
    return removed


def _running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_scratch(path: Path, processes: Processes) -> None:
    """Remove a non-main process's scratch folder (:func:`scratch_output`); the main process's output stays."""
    if not processes.is_main:
        shutil.rmtree(Path(path).parent, ignore_errors=True)
