"""CLEAR (Rolnick et al., 2019) as the paper's MT5 baseline (appendix B.1): experience replay with behaviour
cloning, without V-trace.

After each skill i: ``transitions`` transitions (s, a, r, s', done) drawn uniformly from the skill's replay
(paper: 1000) and, as behaviour-cloning targets, the actor's Gaussian mean and log-std on their states at storage
time. In later wakes every SAC update trains critic and actor on a 50/50 mix: half of the current skill's batch is
replaced by replayed transitions (our choice: the batch size stays SAC's; replayed samples are spread evenly over
the past skills), and the actor loss gets

    beta_BC * E_{replayed s} || [mu_theta(s), log sigma_theta(s)] - [mu_i(s), log sigma_i(s)] ||^2   (beta_BC = 0.01)

(CLEAR's policy cloning as a squared error on the Gaussian's parameters: our reading of "behaviour-cloning
targets"; no value cloning).

Memory per skill: the transitions (1000 x (39 + 4 + 1 + 39 + 1) float32) and the targets (1000 x 8).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import torch
from torch import Tensor

from sr_imitation.core.memory import Memory, register_memory
from sr_imitation.stream.capabilities import GaussianActor, StoredTransitions, capability
from sr_imitation.stream.methods.base import ContinualMethod, WakeStep
from sr_imitation.stream.methods.registry import register_method
from sr_imitation.stream.substrate import Substrate


@dataclass(frozen=True)
class CLEARConfig:
    transitions: int = 1000
    """Transitions stored per skill (paper: 1000)."""
    replay_fraction: float = 0.5
    """Share of every update's batch that is replayed (paper: 50/50)."""
    bc_weight: float = 0.01
    """beta_BC, the behaviour-cloning coefficient (paper: 0.01)."""


@register_memory
class TransitionMemory(Memory):
    """Replayable transitions of one skill plus the actor's Gaussian (``target``) on their states (``obs``);
    :meth:`loss` is the behaviour-cloning error of ``policy`` (states -> [mean, log std]) on a batch."""

    kind = "transitions"
    contents = "transitions (s, a, r, s', done) + the actor's Gaussian on s (behaviour-cloning targets)"

    @property
    def buffer_keys(self) -> tuple[str, ...]:  # type: ignore[override]
        return tuple(sorted(self.tensors))

    def _validate(self) -> None:
        missing = {"obs", "target"} - set(self.tensors)
        if missing:
            raise ValueError(f"TransitionMemory({self.skill!r}) is missing {sorted(missing)}")
        super()._validate()

    def loss(self, policy: Any, batch: Mapping[str, Tensor]) -> Tensor:
        return (policy(batch["obs"]) - batch["target"]).pow(2).sum(-1).mean()


@register_method
class CLEAR(ContinualMethod):
    """Replay of earlier skills' transitions in every update, with behaviour cloning toward the stored policy."""

    name = "clear"
    resumable_wake_hooks = True  # nothing carried from one update to the next
    requires = (GaussianActor, StoredTransitions)
    stores_memories = True
    memory_name = "clear"
    config: ClassVar[CLEARConfig] = CLEARConfig()

    @property
    def wake_transition_sample(self) -> int:
        return self.config.transitions

    def begin_wake(self, k: int, memories: Any, substrate: Substrate) -> None:
        super().begin_wake(k, memories, substrate)
        self._policy = capability(substrate, GaussianActor).gaussian_policy
        self._replayed: dict[str, Tensor] | None = None

    def wake_batch(self, step: WakeStep) -> Mapping[str, Tensor]:
        self._replayed = None
        if not self.memories:
            return step.batch
        size = len(next(iter(step.batch.values())))
        n = int(round(self.config.replay_fraction * size))
        shares = [n // len(self.memories) + (i < n % len(self.memories)) for i in range(len(self.memories))]
        parts = [m.sample(c, step.generator) for m, c in zip(self.memories, shares, strict=True) if c > 0]
        replayed = {key: torch.cat([p[key] for p in parts]) for key in parts[0]}
        self._replayed = replayed
        return {key: torch.cat([value[: size - n], replayed[key].to(value)]) for key, value in step.batch.items()}

    def wake_loss(self, loss: Tensor, step: WakeStep) -> Tensor:
        if self._replayed is None:
            return loss
        self._bc = self.memories[0].loss(self._policy, self._replayed)
        return loss + self.config.bc_weight * self._bc

    def adjust_gradients(self, step: WakeStep) -> dict[str, float]:  # reports only; the gradient is left alone
        if self._replayed is None:
            return {}
        return {"replayed": float(len(self._replayed["obs"])), "bc_loss": float(self._bc.detach())}

    def make_memory(self, k: int, substrate: Substrate) -> Memory:
        sample = capability(substrate, StoredTransitions).transition_sample(k)
        with torch.no_grad():
            target = capability(substrate, GaussianActor).gaussian_policy(sample["obs"])
        memory = TransitionMemory(substrate.memory_skill(k), {**sample, "target": target})
        return self.save_memory(k, substrate, memory)
