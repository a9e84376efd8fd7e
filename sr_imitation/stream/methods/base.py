"""The continual-method plugin interface (in the spirit of Continual World's and Avalanche's hooks).

The engine asks a method, per skill, which memories its wake distils from and with what weight, whether it stores
a memory, and whether it sleeps; ``on_skill_start`` / ``on_skill_end`` let a method compute what it keeps (e.g. a
Fisher estimate). Everything else (data, wake loop, checkpoints, evaluation, metrics, resume) belongs to the engine
and the substrate, so a baseline is one file: subclass :class:`ContinualMethod`, decorate it with
:func:`register_method`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

from sr_imitation.core.memory import Memory
from sr_imitation.stream.substrate import MethodSettings, Substrate


class ContinualMethod:
    """A continual-learning method. Class attributes declare what it is; hooks default to "do nothing".

    Attributes:
        name: the registry name (``--method``).
        substrates: the substrates (``Substrate.name``) the method is defined for.
        stores_memories: whether a frozen memory M_k is made after each wake (needed by sleep and distillation).
    """

    name: ClassVar[str] = ""
    substrates: ClassVar[frozenset[str]] = frozenset()
    stores_memories: ClassVar[bool] = False

    def __init__(self, settings: MethodSettings) -> None:
        self.settings = settings

    def wake_memories(self, skill_number: int, memories: Sequence[Memory]) -> tuple[list[Memory], float]:
        """Memories and weight gamma_k of the wake's distillation term for the ``skill_number``-th skill
        (1-based); none by default."""
        return [], 0.0

    def sleeps_after(self, skill_number: int) -> bool:
        """Whether a sleep follows the wake of the ``skill_number``-th skill (1-based)."""
        return False

    def on_skill_start(self, k: int, substrate: Substrate) -> None:
        """Called before the wake of stage ``k`` (0-based), also when that wake is resumed."""

    def on_skill_end(self, k: int, substrate: Substrate) -> None:
        """Called after stage ``k``'s last phase (also for stages completed before a resume)."""

    def describe(self) -> dict[str, Any]:
        return {"method": self.name}
