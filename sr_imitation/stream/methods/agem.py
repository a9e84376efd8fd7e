"""A-GEM (Chaudhry et al., 2019) as the paper's MT5 baseline (appendix B.1).

Memory per skill: raw states and the skill's frozen critic, i.e. SR's memory M_i (paper: 1000 states per past skill;
"reference gradient ... from the corresponding frozen critic"). In later wakes a reference gradient g_ref is the
gradient of the past skills' frozen-critic surrogates, sum_{i<k} L_i(theta) with L_i = -E_s Q_i(s, pi_theta(s)) (each
on ``batch_size`` of its states), recomputed every ``reference_every`` update-to-data steps (paper: 30). Every actor
gradient g that conflicts with it (g . g_ref < 0) is projected onto the half-space where it does not:

    g <- g - (g . g_ref / ||g_ref||^2) g_ref.

A non-conflicting gradient is left unchanged. ``batch_size`` (64, the sleep's) is our choice.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import torch

from sr_imitation.core.memory import summed_objective
from sr_imitation.stream.methods._gradients import current_grad, flat_grad, set_grad
from sr_imitation.stream.methods.base import ContinualMethod, WakeStep
from sr_imitation.stream.methods.registry import register_method
from sr_imitation.stream.substrate import Substrate


@dataclass(frozen=True)
class AGEMConfig:
    reference_every: int = 30
    """Update-to-data steps between recomputations of the reference gradient (paper: 30)."""
    batch_size: int = 64
    """States drawn from each past skill's memory for the reference gradient (our choice)."""


def agem_project(g: torch.Tensor, ref: torch.Tensor) -> tuple[torch.Tensor, bool]:
    """A-GEM's projection: ``g`` unchanged if ``g . ref >= 0``, else its projection onto ``ref``'s normal plane."""
    dot = torch.dot(g, ref)
    norm2 = torch.dot(ref, ref)
    if dot >= 0 or norm2 <= 0:
        return g, False
    return g - (dot / norm2) * ref, True


@register_method
class AGEM(ContinualMethod):
    """Averaged gradient episodic memory: never let an update raise the past skills' surrogate loss (to first
    order)."""

    name = "agem"
    substrates = frozenset({"sac"})  # the MT5 comparison's: its reference gradient is of frozen-critic surrogates
    stores_memories = True
    resumable_wake_hooks = True  # the reference gradient is the wake state (wake_state)
    config: ClassVar[AGEMConfig] = AGEMConfig()

    def begin_wake(self, k: int, memories: Any, substrate: Substrate) -> None:
        super().begin_wake(k, memories, substrate)
        self._reference: torch.Tensor | None = None

    def wake_state(self) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
        """The reference gradient g_ref in use until its next recomputation (none before the first)."""
        return ({} if self._reference is None else {"reference": self._reference}), {}

    def load_wake_state(self, tensors: Mapping[str, torch.Tensor], record: Mapping[str, Any]) -> None:
        self._reference = tensors.get("reference")

    def adjust_gradients(self, step: WakeStep) -> dict[str, float]:
        if not self.memories:
            return {}
        if self._reference is None or step.update % self.config.reference_every == 0:
            loss = summed_objective(self.memories, step.policy, self.config.batch_size, step.generator)
            self._reference = flat_grad(loss, step.parameters)
        g = current_grad(step.parameters)
        projected, conflicted = agem_project(g, self._reference.to(g.device))  # a snapshot's is on the CPU
        if conflicted:
            set_grad(step.parameters, projected)
        return {"agem_projected": float(conflicted)}
