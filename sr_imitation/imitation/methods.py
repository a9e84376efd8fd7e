"""Continual methods as strategies of one stream loop.

The stream trainer asks a method three questions per skill; everything else (data, wake loop, checkpoints,
evaluation, metrics, resume) is shared. New methods (EWC, LwF, M2Distill, a multi-task oracle) subclass
:class:`ContinualMethod` and register themselves, without copying the loop.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

from sr_imitation.core.memory import Memory


class ContinualMethod:
    """Default: sequential behaviour cloning (no memories used, no sleep)."""

    name: ClassVar[str] = "sequential_bc"
    stores_memories: ClassVar[bool] = False

    def __init__(self, policy_cfg: Any) -> None:
        self.policy_cfg = policy_cfg

    def wake_memories(self, skill_number: int, memories: Sequence[Memory]) -> tuple[list[Memory], float]:
        """Memories and weight gamma_k for the wake objective of the ``skill_number``-th skill (1-based)."""
        return [], 0.0

    def sleeps_after(self, skill_number: int) -> bool:
        return False

    def describe(self) -> dict[str, Any]:
        return {"method": self.name}


class SleepingRobots(ContinualMethod):
    """Wake with multi-anchor distillation from frozen actor memories; Nash sleep for k >= 2 when ``sleep``.

    With ``policy.sleep=false`` this is the paper's "SR Wake-Only" ablation (same wake, no sleep).
    """

    name = "sr"
    stores_memories = True

    def wake_memories(self, skill_number: int, memories: Sequence[Memory]) -> tuple[list[Memory], float]:
        return list(memories), self.policy_cfg.distill_weight(skill_number)

    def sleeps_after(self, skill_number: int) -> bool:
        return bool(self.policy_cfg.sleep) and skill_number >= 2

    def describe(self) -> dict[str, Any]:
        variant = "sleeping_robots" if self.policy_cfg.sleep else "sr_wake_only"
        return {"method": self.name, "variant": variant, "aggregator": self.policy_cfg.aggregator}


METHODS: dict[str, type[ContinualMethod]] = {cls.name: cls for cls in (ContinualMethod, SleepingRobots)}


def make_method(name: str, policy_cfg: Any) -> ContinualMethod:
    try:
        return METHODS[name](policy_cfg)
    except KeyError:
        raise ValueError(f"unknown method {name!r}; choose from {sorted(METHODS)}") from None
