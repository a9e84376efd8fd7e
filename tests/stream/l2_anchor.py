"""L2 anchor: every wake pulls the policy toward its weights after the previous skill's wake,

    loss + lambda / 2 * || theta - theta_{k-1}^wake ||^2,

the example method of docs/ARCHITECTURE.md's "Adding a method" (as a file of ``sr_imitation/stream/methods/`` it
would be registered by that package; tests import it). No memories, no sleep; it asks nothing of the substrate
beyond the :class:`~sr_imitation.stream.substrate.Substrate` protocol, so it runs on every substrate.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar

from torch import Tensor

from sr_imitation.core.memory import Memory
from sr_imitation.stream.methods.base import ContinualMethod, WakeStep
from sr_imitation.stream.methods.registry import register_method
from sr_imitation.stream.substrate import Substrate


@dataclass(frozen=True)
class L2AnchorConfig:
    lam: float = 1.0
    """lambda, the weight of the pull (``--method_options='{lam: 10}'``)."""


@register_method
class L2Anchor(ContinualMethod):
    """A quadratic pull toward the previous skill's wake weights in every wake update."""

    name = "l2_anchor"
    resumable_wake_hooks = True  # the anchor is fixed in begin_wake: nothing carried from one update to the next
    config: ClassVar[L2AnchorConfig] = L2AnchorConfig()

    def begin_wake(self, k: int, memories: Sequence[Memory], substrate: Substrate) -> None:
        super().begin_wake(k, memories, substrate)
        # from the run directory's checkpoint, not from memory of the process: a resumed run computes the same
        self.anchor = [p.detach().clone() for p in substrate.parameters_at(k - 1, "wake")] if k > 0 else None

    def wake_loss(self, loss: Tensor, step: WakeStep) -> Tensor:
        if self.anchor is None:
            return loss
        pull = sum((p - a).pow(2).sum() for p, a in zip(step.parameters, self.anchor, strict=True))
        return loss + 0.5 * self.config.lam * pull
