"""Normalization statistics that may change under a policy: a floor on standard deviations, the statistics of
several skills together, and re-expressing an ACT-SR policy, its memories' targets and its processors in other
statistics without changing what it does.

LeRobot normalizes with ``(x - mean) / (std + 1e-8)`` and unnormalizes actions with ``y * std + mean``. A dimension
that is constant in a dataset (the needle's jaw while placing) has std 0, so any other value of it becomes ~1e8
standard deviations: a memory of another skill, re-expressed into such statistics, has losses of 1e13. Every
statistic built here has ``std >= min_std`` (our choice: 1e-2, the stream's ``stats_min_std``), which changes
nothing on the dataset itself (a constant dimension still normalizes to 0) and bounds everything else.

Re-expressing (our choice; used by ``--stream.stats=seen`` when the statistics change at a wake, and by ``sr-sleep``
when the deployed policy's statistics cannot hold its memories): ACT reads the normalized state through linear
input projections and writes the normalized action through a linear head, so with statistics (m, s) replaced by
(m', s') the layers below are rewritten to keep the policy's raw-space behaviour:

- input projection ``W x_n + b`` of a state (or, in the VAE encoder, of an action): ``W' = W diag(r)``,
  ``b' = b + W (m' - m) / (s + eps)`` with ``r = (s' + eps) / (s + eps)`` - exact where ``s >= min_std``; an old
  ``s`` below the floor is first raised to it (the same outputs on the data those statistics came from, where the
  dimension is constant, and finite ones elsewhere);
- action head ``y = W h + b`` (raw action ``y s + m``): ``W' = diag(s / s') W``, ``b' = (b s + m - m') / s'`` - exact,
  also where ``s = 0`` (the head then outputs the constant ``m`` for that dimension, as before).

Camera images keep their statistics (a vision backbone reads them; image statistics never collapse to a point).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from types import MappingProxyType
from typing import Any

import torch
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE
from torch import Tensor

logger = logging.getLogger(__name__)

MIN_STD = 1e-2
"""Default floor on every standard deviation (our choice; ``--stream.stats_min_std``'s default)."""
EPS = 1e-8
"""LeRobot's normalizer epsilon (``NormalizerProcessorStep.eps``)."""
FAR_OUTSIDE = 10.0
"""A dataset whose mean lies more than this many standard deviations of the statistics in use from their mean, in
some dimension, is reported before its first gradient (our choice: RESULTS' regrasp under approach's statistics
sat 30-55 standard deviations away and was not learned; within 10 the skills of our presets were)."""

Stats = dict[str, dict[str, Tensor]]

INPUT_LAYERS: dict[str, tuple[str, ...]] = {
    OBS_STATE: ("model.encoder_robot_state_input_proj", "model.vae_encoder_robot_state_input_proj"),
    OBS_ENV_STATE: ("model.encoder_env_state_input_proj",),
    ACTION: ("model.vae_encoder_action_input_proj",),
}
"""ACT's linear layers that read a normalized vector (state dict prefixes), by the statistics' key."""
ACTION_HEAD = "model.action_head"
"""ACT's linear layer that writes the normalized action chunk."""


def _tensor(value: object) -> Tensor:
    return torch.as_tensor(value, dtype=torch.float32).detach().clone().cpu()


def floor_std(stats: Mapping[str, Mapping[str, object]], min_std: float = MIN_STD,
              keys: Sequence[str] | None = None) -> Stats:
    """A copy of ``stats`` (float32 tensors) with every ``std`` of ``keys`` (default all) at least ``min_std``."""
    out: Stats = {}
    for key, entry in stats.items():
        out[key] = {name: _tensor(v) for name, v in entry.items()}
        if "std" in out[key] and (keys is None or key in keys):
            out[key]["std"] = out[key]["std"].clamp_min(min_std)
    return out


def pooled(stats_list: Sequence[Mapping[str, Mapping[str, object]]], min_std: float = MIN_STD) -> Stats:
    """Mean and std of several skills' statistics together, each skill weighted equally (our choice: a processor
    keeps no frame count), std floored; ``min``/``max`` the extremes."""
    out: Stats = {}
    for key in stats_list[0]:
        entries = [{n: _tensor(v) for n, v in s[key].items()} for s in stats_list if key in s]
        means = torch.stack([e["mean"] for e in entries])
        second = torch.stack([e["std"] ** 2 + e["mean"] ** 2 for e in entries]).mean(0)
        mean = means.mean(0)
        entry = {"mean": mean, "std": (second - mean**2).clamp_min(0).sqrt().clamp_min(min_std)}
        if all("min" in e and "max" in e for e in entries):
            entry["min"] = torch.stack([e["min"] for e in entries]).amin(0)
            entry["max"] = torch.stack([e["max"] for e in entries]).amax(0)
        out[key] = entry
    return out


def same_stats(a: Mapping[str, Mapping[str, Tensor]], b: Mapping[str, Mapping[str, Tensor]],
               keys: Sequence[str]) -> bool:
    """Whether ``a`` and ``b`` normalize ``keys`` identically (mean and std bit for bit)."""
    for key in keys:
        if (key in a) != (key in b):
            return False
        if key in a and not all(torch.equal(_tensor(a[key][n]), _tensor(b[key][n])) for n in ("mean", "std")):
            return False
    return True


def map_actions(targets: Tensor, old: Mapping[str, Tensor], new: Mapping[str, Tensor]) -> Tensor:
    """Normalized action chunks under ``old`` (``mean``, ``std`` of the action) re-expressed under ``new``: the same
    raw actions (LeRobot's unnormalize ``y s + m``, then normalize ``(a - m') / (s' + eps)``)."""
    raw = targets.float() * _tensor(old["std"]) + _tensor(old["mean"])
    return (raw - _tensor(new["mean"])) / (_tensor(new["std"]) + EPS)


def _input_key(key: str, stats: Mapping[str, object]) -> str | None:
    if key in stats:
        return key
    return OBS_STATE if key == OBS_ENV_STATE and OBS_STATE in stats else None  # state-only ACT: the state's copy


def reexpress_state_dict(state: Mapping[str, Tensor], old: Mapping[str, Mapping[str, Tensor]],
                         new: Mapping[str, Mapping[str, Tensor]], min_std: float = MIN_STD,
                         inputs: bool = True) -> dict[str, Tensor]:
    """An ACT-SR policy's weights ``state`` under statistics ``old`` rewritten for ``new`` (module docstring); layers
    or keys absent from either are left as they are. ``inputs=False`` rewrites the action head only: the input
    projections keep their weights and read the inputs in ``new``'s statistics (the policy's behaviour then changes
    where the inputs' statistics changed; ``--stream.reexpress_inputs=false``, exploratory)."""
    out = dict(state)
    for key, layers in INPUT_LAYERS.items() if inputs else ():
        k_old, k_new = _input_key(key, old), _input_key(key, new)
        if k_old is None or k_new is None:
            continue
        s_old = _tensor(old[k_old]["std"])
        s_old = torch.where(s_old < min_std, torch.full_like(s_old, min_std), s_old)
        m_old, m_new, s_new = _tensor(old[k_old]["mean"]), _tensor(new[k_new]["mean"]), _tensor(new[k_new]["std"])
        ratio, shift = (s_new + EPS) / (s_old + EPS), (m_new - m_old) / (s_old + EPS)
        for layer in layers:
            if f"{layer}.weight" not in out:
                continue
            weight = out[f"{layer}.weight"]
            w = weight.detach().float().cpu()
            out[f"{layer}.bias"] = (out[f"{layer}.bias"].detach().float().cpu() + w @ shift).to(weight)
            out[f"{layer}.weight"] = (w * ratio[None, :]).to(weight)
    if ACTION in old and ACTION in new and f"{ACTION_HEAD}.weight" in out:
        s_old, m_old = _tensor(old[ACTION]["std"]), _tensor(old[ACTION]["mean"])
        s_new, m_new = _tensor(new[ACTION]["std"]), _tensor(new[ACTION]["mean"])
        weight, bias = out[f"{ACTION_HEAD}.weight"], out[f"{ACTION_HEAD}.bias"]
        out[f"{ACTION_HEAD}.weight"] = (weight.detach().float().cpu() * (s_old / s_new)[:, None]).to(weight)
        out[f"{ACTION_HEAD}.bias"] = ((bias.detach().float().cpu() * s_old + m_old - m_new) / s_new).to(bias)
    return out


def reexpress_policy(policy: torch.nn.Module, old: Mapping[str, Mapping[str, Tensor]],
                     new: Mapping[str, Mapping[str, Tensor]], min_std: float = MIN_STD, inputs: bool = True) -> None:
    """:func:`reexpress_state_dict` applied to ``policy`` in place."""
    state = dict(policy.state_dict())
    changed = reexpress_state_dict(state, old, new, min_std, inputs)
    with torch.no_grad():
        for name, tensor in policy.state_dict().items():
            if changed[name] is not state[name]:
                tensor.copy_(changed[name])


def far_outside(data: Mapping[str, Mapping[str, object]], in_use: Mapping[str, Mapping[str, object]],
                keys: Sequence[str], limit: float = FAR_OUTSIDE) -> tuple[str, int, float] | None:
    """The key, dimension and distance (in standard deviations of ``in_use``) of the dimension of ``keys`` whose
    dataset mean (``data``) lies farthest from ``in_use``'s mean, when that is beyond ``limit``; else ``None``."""
    worst: tuple[str, int, float] | None = None
    for key in keys:
        if key not in data or key not in in_use:
            continue
        z = (_tensor(data[key]["mean"]) - _tensor(in_use[key]["mean"])).abs() / (_tensor(in_use[key]["std"]) + EPS)
        z = z.flatten()
        if z.numel() and float(z.max()) > limit and (worst is None or float(z.max()) > worst[2]):
            worst = (key, int(z.argmax()), float(z.max()))
    return worst


def retarget(memory: Any, targets: Tensor) -> None:
    """Replace an actor memory's ``target`` tensor (the same raw actions in other statistics: :func:`map_actions`).
    Memories are immutable to everything that trains with them; only the stream, when ``--stream.stats=seen``
    changes the statistics between phases, re-expresses them here (our choice)."""
    tensors = dict(memory.tensors)
    tensors["target"] = targets.detach().clone().requires_grad_(False)
    object.__setattr__(memory, "_tensors", MappingProxyType(tensors))
