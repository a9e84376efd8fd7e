"""What the mid-wake snapshots of both substrates share (:mod:`sr_imitation.substrates.act.wake_snapshot`,
:mod:`sr_imitation.substrates.sac.wake_snapshot`): the snapshot's frame (:func:`write_snapshot` / :func:`read_snapshot`:
the identity that names the wake, checked before anything is restored; the process's global generators, torch's, CUDA's
when initialized, NumPy's and Python's; the state of a continual method's wake hooks where they can carry it,
``WakeHooks.state``, their method's name joining the identity), and optimizer states and weights as tensors.

A snapshot is one checked safetensors file (:func:`~sr_imitation.io.save_checked_safetensors`): tensors plus a JSON
header; each substrate adds its own parts to both. 0-d tensors (Adam's step, torch's scalars) are stored as they are.
"""

from __future__ import annotations

import random
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sr_imitation.io import CorruptFileError, load_checked_safetensors, save_checked_safetensors

EVERY_S = 300.0
"""The default seconds of wall time between two snapshots of one wake (``--wake.snapshot_every_s`` of both
substrates; our choice: a kill loses at most about five minutes of a wake)."""


def write_snapshot(path: Path, identity: dict[str, Any], tensors: dict[str, torch.Tensor], header: dict[str, Any],
                   hooks: Any = None) -> None:
    """Write a wake's snapshot atomically: the substrate's ``tensors`` and ``header`` with its ``identity`` (format,
    version and what names the wake), the process's global generators and the state of ``hooks`` (a resumable
    ``sr_imitation.stream.methods.base.WakeHooks``, or None)."""
    rng_tensors, rng_header = _global_rng_state()
    hook_tensors, hook_header = _hooks_state(hooks)
    save_checked_safetensors(path, {**tensors, **rng_tensors, **hook_tensors},
                             {**identity, **_hooks_identity(hooks), **header, **rng_header, **hook_header})


def read_snapshot(path: Path, identity: dict[str, Any], hooks: Any = None
                  ) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """Read a snapshot :func:`write_snapshot` wrote, check that it is the one of this wake (``identity`` and the
    hooks' method), then restore the process's global generators and ``hooks``; returns its tensors and header for
    the substrate's own parts. Another wake's snapshot is a :class:`CorruptFileError` naming the file and what
    differs, raised before anything is restored."""
    tensors, header = load_checked_safetensors(path)
    want = {**identity, **_hooks_identity(hooks)}
    got = {k: header.get(k) for k in want}
    if got != want:
        raise CorruptFileError(path, f"wake snapshot of {got}, expected {want}; remove it to redo the wake from "
                                     "its start")
    _restore_global_rng(tensors, header)
    if hooks is not None:
        hooks.load_state(prefixed(tensors, "hooks."), header["hooks"])
    return tensors, header


def load_weights(path: Path, module: torch.nn.Module, weights: dict[str, torch.Tensor], what: str) -> None:
    """``module.load_state_dict(weights, strict=True)``; a misfit is a :class:`CorruptFileError` naming the file."""
    try:
        module.load_state_dict(weights, strict=True)
    except RuntimeError as exc:
        raise CorruptFileError(path, f"the snapshot's {what} does not fit this configuration: {exc}") from exc


def prefixed(tensors: dict[str, torch.Tensor], prefix: str) -> dict[str, torch.Tensor]:
    """The tensors named ``<prefix><name>``, by ``name``."""
    return {n.removeprefix(prefix): t for n, t in tensors.items() if n.startswith(prefix)}


def optimizer_tensors(name: str, optimizer: torch.optim.Optimizer) -> dict[str, torch.Tensor]:
    """An optimizer's per-parameter state as ``<name>.<index>.<field>`` tensors (its parameter groups are rebuilt
    with it, not stored)."""
    return {f"{name}.{index}.{field}": value
            for index, state in optimizer.state_dict()["state"].items() for field, value in state.items()}


def restore_optimizer(name: str, optimizer: torch.optim.Optimizer, tensors: dict[str, torch.Tensor]) -> None:
    """Load what :func:`optimizer_tensors` stored under ``name`` into a freshly built ``optimizer``."""
    state = optimizer.state_dict()
    for key, value in prefixed(tensors, f"{name}.").items():
        index, field = key.split(".", 1)
        state["state"].setdefault(int(index), {})[field] = value
    optimizer.load_state_dict(state)


def _global_rng_state() -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """The process's global generators as tensors (``global_rng.*``) and a header entry (``global_rng``)."""
    tensors = {"global_rng.torch": torch.get_rng_state()}
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        tensors["global_rng.cuda"] = torch.cuda.get_rng_state()
    kind, keys, pos, has_gauss, cached = np.random.get_state()
    tensors["global_rng.numpy.keys"] = torch.from_numpy(np.asarray(keys, dtype=np.int64))
    version, python_state, gauss = random.getstate()
    tensors["global_rng.python"] = torch.tensor(python_state, dtype=torch.int64)
    header = {"numpy": {"kind": kind, "pos": int(pos), "has_gauss": int(has_gauss), "cached": float(cached)},
              "python": {"version": version, "gauss": gauss}}
    return tensors, {"global_rng": header}


def _restore_global_rng(tensors: dict[str, torch.Tensor], header: dict[str, Any]) -> None:
    """Set the process's global generators to what :func:`_global_rng_state` stored."""
    torch.set_rng_state(tensors["global_rng.torch"])
    if "global_rng.cuda" in tensors and torch.cuda.is_available():
        torch.cuda.set_rng_state(tensors["global_rng.cuda"])
    n, p = header["global_rng"]["numpy"], header["global_rng"]["python"]
    keys = tensors["global_rng.numpy.keys"].numpy().astype(np.uint32)
    np.random.set_state((n["kind"], keys, n["pos"], n["has_gauss"], n["cached"]))
    random.setstate((p["version"], tuple(tensors["global_rng.python"].tolist()), p["gauss"]))


def _hooks_identity(hooks: Any) -> dict[str, Any]:
    """The method whose hooks shaped the wake (None: no hooks): part of what names a wake."""
    return {"method_hooks": None if hooks is None else hooks.method.name}


def _hooks_state(hooks: Any) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """A wake's method hooks as tensors (``hooks.generator``, ``hooks.method.<name>``: the method's own) and a header
    entry (``hooks``: their update count, sums and the method's record, or None)."""
    if hooks is None:
        return {}, {"hooks": None}
    tensors, record = hooks.state()
    return {f"hooks.{n}": t for n, t in tensors.items()}, {"hooks": record}
