"""ActorMemory: the imitation memory M_k^pi = (pi_{theta_k^wake}, B_k) of Section 3 on the core interface.

The buffer B_k holds |B_k| unordered observations of skill k (wrist images as uint8, robot state as float32),
never actions. The objective is the paper's L_k^pi(theta) = E_{o ~ B_k} ||pi_theta(o) - pi_{theta_k^wake}(o)||^2
with pi(o) the deterministic action chunk (zero latent), compared in the stream's fixed normalized action space.
By default the squared difference is averaged over the chunk's elements (``reduction="mean"``, the "mean squared
difference" of the issue, on the same per-element scale as ACT's l1 loss); ``"sum"`` is the literal squared norm,
16 x 7 = 112 times larger for a 16-step chunk of 7-d actions, which at the paper's distillation weights lets the
distillation term dominate the wake loss (docs/RESULTS.md).

The wake-end snapshot never changes, so its chunks on the buffer are computed once when the memory is created
and stored as ``target``; neither wake distillation nor sleep runs the snapshot again (the saving is measured
in docs/BENCHMARKS.md). The snapshot's weights are the stage checkpoint ``skill_k/wake`` (``config["snapshot"]``)
and :meth:`ActorMemory.verify_targets` recomputes the targets from it when an audit is wanted.

It lives in the plugin because the policy writes it (``--policy.sleep``, :mod:`.modeling_act_sr`) and the stream's
ACT substrate (``sr_imitation.substrates.act``), which imports the plugin, loads and trains on it; the kind name
``act_actor`` is the one every saved file carries.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import torch
from torch import Tensor

from sr_imitation.core.memory import OutputDistillationMemory, register_memory

ObservationFn = Callable[[Mapping[str, Tensor]], Tensor]


def images_to_uint8(images: Tensor) -> Tensor:
    """Float images in [0, 1] (LeRobot's dataset format) to uint8, losslessly for images that came from uint8."""
    if images.dtype == torch.uint8:
        return images
    return (images.clamp(0.0, 1.0) * 255.0).round().to(torch.uint8)


@register_memory
class ActorMemory(OutputDistillationMemory):
    """Frozen ACT actor snapshot + unordered observation buffer (squared error, mean or sum over the chunk)."""

    kind = "act_actor"
    contents = "observations (state; wrist images as uint8) + the actor's action chunks on them"
    provenance_keys = ("snapshot",)  # each skill's memory names its own checkpoint; the objective is the same

    @classmethod
    def from_observations(
        cls,
        skill: str,
        chunk_fn: ObservationFn,
        observations: Mapping[str, Tensor],
        snapshot: str = "",
        batch_size: int = 64,
        reduction: str = "mean",
    ) -> ActorMemory:
        """Store ``observations`` (keys like ``observation.state``; images as uint8) and the snapshot's chunks.

        ``chunk_fn`` maps a dict of raw buffered observations to the snapshot's normalized action chunks
        (B, chunk, action_dim); it is evaluated once, here. ``reduction``: ``"mean"`` or ``"sum"`` over the chunk.
        """
        obs = {k: images_to_uint8(v) if k.startswith("observation.images") else v.float()
               for k, v in observations.items()}
        base = OutputDistillationMemory.from_snapshot(skill, chunk_fn, obs, batch_size=batch_size, reduction=reduction)
        return cls(skill, dict(base.tensors), {**base.config, "snapshot": snapshot})

    def observations(self) -> dict[str, Tensor]:
        """The buffered observations, keyed as in the dataset."""
        return {k.removeprefix("input."): v for k, v in self.tensors.items() if k.startswith("input.")}

    def verify_targets(self, chunk_fn: ObservationFn, atol: float = 1e-5, batch_size: int = 64) -> float:
        """Recompute the snapshot's chunks with ``chunk_fn`` and return the max abs difference to ``target``.

        Raises:
            ValueError: if the difference exceeds ``atol`` (the memory does not match that snapshot).
        """
        obs = self.observations()
        n = self.size
        worst = 0.0
        with torch.no_grad():
            for start in range(0, n, batch_size):
                chunk = chunk_fn({k: v[start : start + batch_size] for k, v in obs.items()})
                ref = self.tensors["target"][start : start + batch_size].to(chunk.device, chunk.dtype)
                worst = max(worst, float((chunk - ref).abs().max()))
        if worst > atol:
            raise ValueError(f"memory {self.skill!r}: recomputed snapshot chunks differ by {worst:.3g} > {atol}")
        return worst

    def describe(self) -> dict[str, Any]:
        return {"skill": self.skill, "size": self.size, "bytes": self.nbytes(),
                "snapshot": self.config.get("snapshot", "")}
