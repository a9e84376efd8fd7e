"""Sleeping Robots (paper, Algorithm 1) and its wake-only ablation.

Wake: the skill's own objective plus, on substrates whose wake distils (ACT), gamma_k times the summed distillation
losses of the frozen memories M_1..M_{k-1} (paper Eq. L_wake); a memory M_k after every wake; for k >= 2 a sleep
over M_1..M_k (Nash bargaining, Eq. 1, with the anchor of Eq. 2), run by the engine.
"""

from __future__ import annotations

from collections.abc import Sequence

from sr_imitation.core.memory import Memory
from sr_imitation.stream.methods.base import ContinualMethod
from sr_imitation.stream.methods.registry import register_method


@register_method
class SleepingRobots(ContinualMethod):
    """SR: wake with distillation from the memories, sleep after every skill from the second on. With sleep turned
    off by the run's configuration (``--sleep.enabled=false``) this is the wake-only
    ablation, as :class:`WakeOnly` is by name."""

    name = "sr"

    @property
    def stores_memories(self) -> bool:  # type: ignore[override]
        """Memories serve the sleep and, where the wake distils (ACT), the wake; a SAC run without sleep (the
        wake-only ablation) uses none and keeps none (its memory budget is 0)."""
        return self.settings.sleep or self.settings.distill_weight is not None

    def sleeps_after(self, skill_number: int) -> bool:
        return self.settings.sleep and skill_number >= 2

    def wake_memories(self, skill_number: int, memories: Sequence[Memory]) -> tuple[list[Memory], float]:
        weight = self.settings.distill_weight
        if weight is None:  # the substrate's wake has no distillation term (SAC: the paper's wake is plain SAC)
            return [], 0.0
        return list(memories), weight(skill_number)



@register_method
class WakeOnly(SleepingRobots):
    """The paper's "SR Wake-Only" ablation: the same wake (and memories), never a sleep."""

    name = "wake_only"

    @property
    def stores_memories(self) -> bool:  # type: ignore[override]
        return self.settings.distill_weight is not None  # only a distilling wake (ACT) uses them

    def sleeps_after(self, skill_number: int) -> bool:
        return False

