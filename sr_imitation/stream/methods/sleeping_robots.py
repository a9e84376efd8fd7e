"""Sleeping Robots (paper, Algorithm 1) and its wake-only ablation.

Wake: the skill's own objective plus, on substrates whose wake distils (ACT), gamma_k times the summed distillation
losses of the frozen memories M_1..M_{k-1} (paper Eq. L_wake); a memory M_k after every wake; for k >= 2 a sleep
over M_1..M_k (Nash bargaining, Eq. 1, with the anchor of Eq. 2), run by the engine.

Two options (``--method_options``, :class:`SleepingRobotsConfig`; both off by default, which is the paper's SR) serve
the question why SR's SAC sleep keeps less than Reset & Distill: ``expert_memory`` adds to each skill's memory
(``beside``) or puts in its place (``instead``) the wake-end actor's Gaussian on the memory's states, so the sleep
bargains over distillation objectives (Reset & Distill's expert memory and loss, the paper's IL memory objective);
``reset_wake`` gives every wake fresh networks (Reset & Distill's wake) and starts every sleep from the shared actor
the previous sleep left.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

from torch import Tensor

from sr_imitation.core.memory import Memory
from sr_imitation.stream.capabilities import GaussianActor, ResettableNetworks, capability
from sr_imitation.stream.methods.base import ContinualMethod
from sr_imitation.stream.methods.der import gaussian_memory, state_gaussian
from sr_imitation.stream.methods.registry import register_method
from sr_imitation.stream.substrate import MethodSettings, SleepProblem, Substrate

EXPERT_MEMORY = ("off", "instead", "beside")
EXPERT = "expert"
"""The file name of the expert memories (``<stage>/expert.safetensors``; Reset & Distill's name for the same kind)."""


@dataclass(frozen=True)
class SleepingRobotsConfig:
    """SR's options (``--method_options={...}``); the defaults are the paper's method."""

    expert_memory: str = "off"
    """``off``: each skill's memory is the substrate's (SAC: the frozen critic; ACT: the actor snapshot).
    ``instead``: the wake-end actor's pre-tanh Gaussian [mean, log std] on the memory's states, with the loss
    ||[mu_theta, log sigma_theta] - [mu_i, log sigma_i]||^2 summed over the 8 numbers (Reset & Distill's expert memory;
    substrates with a Gaussian actor). ``beside``: both, two objectives per skill in the bargaining (our choice for
    the SAC sleep's screening)."""
    reset_wake: bool = False
    """Every wake from freshly initialized actor, critic and temperature (Reset & Distill's wake; the normalizer is
    kept), and every sleep from the shared actor the previous sleep left (after skill 1: the first wake's actor)
    instead of from the wake's actor (the SAC protocol's candidate c; substrates with resettable networks)."""

    def __post_init__(self) -> None:
        if self.expert_memory not in EXPERT_MEMORY:
            raise ValueError(f"method_options: expert_memory must be one of {list(EXPERT_MEMORY)}, got "
                             f"{self.expert_memory!r}")


class _MemoryPolicy:
    """The policy as each memory kind evaluates it: a frozen critic calls it on raw states (actions), an expert
    memory on ``{"state": states}`` batches (the Gaussian)."""

    def __init__(self, action: Any, gaussian: Any) -> None:
        self.action, self.gaussian = action, gaussian

    def __call__(self, x: Tensor | Mapping[str, Tensor]) -> Tensor:
        return self.gaussian(x) if isinstance(x, Mapping) else self.action(x)


@register_method
class SleepingRobots(ContinualMethod):
    """SR: wake with distillation from the memories, sleep after every skill from the second on. With sleep turned
    off by the run's configuration (``--sleep.enabled=false``) this is the wake-only
    ablation, as :class:`WakeOnly` is by name."""

    name = "sr"
    config: ClassVar[SleepingRobotsConfig] = SleepingRobotsConfig()
    option_requires = (GaussianActor, ResettableNetworks)  # expert_memory, reset_wake

    def __init__(self, settings: MethodSettings) -> None:
        super().__init__(settings)
        c = self.config
        needs = ((GaussianActor,) if c.expert_memory != "off" else ()) + ((ResettableNetworks,) if c.reset_wake else ())
        self.requires = tuple(type(self).requires) + needs  # checked by the engine before anything is written
        if c.expert_memory == "instead":
            self.memory_name = EXPERT  # what a resume loads back
        self._substrate: Substrate | None = None

    def setup(self, substrate: Substrate) -> None:
        self._substrate = substrate

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

    def begin_wake(self, k: int, memories: Sequence[Memory], substrate: Substrate) -> None:
        super().begin_wake(k, memories, substrate)
        if self.config.reset_wake:
            capability(substrate, ResettableNetworks).reset_networks(k)

    def make_memory(self, k: int, substrate: Substrate) -> Memory:
        mode = self.config.expert_memory
        if mode == "off":
            return substrate.make_memory(k)
        expert = gaussian_memory(substrate, k)  # the policy is theta_k^wake now
        if mode == "instead":
            return self.save_memory(k, substrate, expert)
        memory = substrate.make_memory(k)
        substrate.save_memory(k, expert, name=EXPERT)
        return memory

    def sleep_memories(self, k: int, memories: Sequence[Memory]) -> list[Memory]:
        kept = list(memories[: k + 1])
        if self.config.expert_memory != "beside":
            return kept
        if self._substrate is None:
            raise RuntimeError("SleepingRobots.setup was not called")
        return kept + [self._substrate.load_memory(i, name=EXPERT) for i in range(k + 1)]

    def prepare_sleep(self, k: int, problem: SleepProblem, substrate: Substrate) -> SleepProblem:
        c = self.config
        if c.reset_wake and k > 0:  # the shared actor as the previous sleep (or, after skill 1, the wake) left it
            capability(substrate, ResettableNetworks).load_actor(k - 1, "sleep" if self.sleeps_after(k) else "wake")
        if c.expert_memory == "off":
            return problem
        return dataclasses.replace(problem, policy=_MemoryPolicy(problem.policy, state_gaussian(substrate)))



@register_method
class WakeOnly(SleepingRobots):
    """The paper's "SR Wake-Only" ablation: the same wake (and memories), never a sleep."""

    name = "wake_only"

    @property
    def stores_memories(self) -> bool:  # type: ignore[override]
        return self.settings.distill_weight is not None  # only a distilling wake (ACT) uses them

    def sleeps_after(self, skill_number: int) -> bool:
        return False

