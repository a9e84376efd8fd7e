"""LwF (Li and Hoiem, 2017) as the paper's imitation baseline (appendix B): learning without forgetting by
distilling the previous policy's outputs on the current skill's observations.

At the start of wake k > 1 the policy is frozen as it is (the rolling previous actor: the policy after stage k-1,
before this skill's wake); at every update of wake k the loss gets

    lambda_LwF * mean || pi_theta(o) - pi_prev(o) ||^2      over the update's observations o of skill k,

the action chunk on the batch's normalized observations, averaged over its elements (lambda_LwF = 1: our choice; the
paper does not give it). Nothing is stored between skills except that one snapshot (memory: 0 skill data; the
snapshot, one copy of the policy's weights, is counted in the memory budget as a ``policy_snapshot``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import torch
from torch import Tensor

from sr_imitation.core.memory import Memory, PolicySnapshot
from sr_imitation.stream.capabilities import PolicySnapshots, capability
from sr_imitation.stream.methods.base import ContinualMethod, WakeStep
from sr_imitation.stream.methods.registry import register_method
from sr_imitation.stream.substrate import Substrate


@dataclass(frozen=True)
class LwFConfig:
    weight: float = 1.0
    """lambda_LwF, the weight of the output distillation (our choice)."""


@register_method
class LwF(ContinualMethod):
    """Output distillation from the policy as it was before this skill's wake, on this skill's observations."""

    name = "lwf"
    resumable_wake_hooks = True  # nothing carried from one update to the next
    requires: ClassVar[tuple[type, ...]] = (PolicySnapshots,)
    config: ClassVar[LwFConfig] = LwFConfig()

    def begin_wake(self, k: int, memories: Any, substrate: Substrate) -> None:
        super().begin_wake(k, memories, substrate)
        self.teacher = capability(substrate, PolicySnapshots).frozen_policy() if k > 0 else None

    def wake_loss(self, loss: Tensor, step: WakeStep) -> Tensor:
        if self.teacher is None:
            return loss
        with torch.no_grad():
            target = self.teacher.action_chunk(step.batch)
        return loss + self.config.weight * (step.policy(step.batch) - target).pow(2).mean()

    def extra_memories(self, substrate: Substrate, stages: int) -> list[Memory]:
        """The teacher of the last wake (the policy after stage K-1): one copy of the policy's weights."""
        if stages < 2:
            return []
        weights = capability(substrate, PolicySnapshots).policy_weights()
        return [PolicySnapshot(substrate.memory_skill(stages - 2), weights)]
