"""DER (Buzzega et al., 2020) as the paper's MT5 baseline (appendix B.1): dark experience replay of the policy's
own outputs.

After each skill i: ``states`` states of the skill (paper: 1000; ours are the late-wake states SR's critic memory
holds, so both methods see the same states) and the actor's Gaussian mean and log-std on them at storage time.
Later wakes add, at every policy update,

    alpha_DER * mean_{i < k} E_{s ~ B_i} || [mu_theta(s), log sigma_theta(s)] - [mu_i(s), log sigma_i(s)] ||^2

to the actor loss (alpha_DER = 0.1, paper), each memory on its own batch of ``batch_size`` states (our choice: the
sleep's batch size, 64; the mean over memories keeps the term's scale independent of k, also our choice).

Memory per skill: the states (1000 x 39 float32) and the targets (1000 x 8): 0.19 MB.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

from torch import Tensor

from sr_imitation.core.memory import Memory, OutputDistillationMemory, summed_objective
from sr_imitation.stream.capabilities import GaussianActor, capability
from sr_imitation.stream.methods.base import ContinualMethod, WakeStep
from sr_imitation.stream.methods.registry import register_method
from sr_imitation.stream.substrate import Substrate


@dataclass(frozen=True)
class DERConfig:
    alpha: float = 0.1
    """alpha_DER, the weight of the output-replay term (paper: 0.1)."""
    batch_size: int = 64
    """States drawn from each memory per update (our choice: the sleep's batch size)."""


def state_gaussian(substrate: Substrate) -> Callable[[Mapping[str, Tensor]], Tensor]:
    """The substrate's actor Gaussian ([mean, log std]) as a memory policy on ``{"state": states}`` batches."""
    actor = capability(substrate, GaussianActor)
    return lambda obs: actor.gaussian_policy(obs["state"])


def gaussian_memory(substrate: Substrate, k: int) -> OutputDistillationMemory:
    """The actor's Gaussian on the late-wake states of skill k, frozen now (DER's memory, R&D's expert)."""
    states = capability(substrate, GaussianActor).memory_states(k)
    return OutputDistillationMemory.from_snapshot(substrate.memory_skill(k), state_gaussian(substrate),
                                                  {"state": states}, reduction="sum")


@register_method
class DER(ContinualMethod):
    """Dark experience replay: keep the actor's Gaussian outputs on stored states close to what they were."""

    name = "der"
    resumable_wake_hooks = True  # nothing carried from one update to the next
    requires = (GaussianActor,)
    stores_memories = True
    memory_name = "der"
    config: ClassVar[DERConfig] = DERConfig()

    def begin_wake(self, k: int, memories: Any, substrate: Substrate) -> None:
        super().begin_wake(k, memories, substrate)
        self._policy = state_gaussian(substrate)

    def wake_loss(self, loss: Tensor, step: WakeStep) -> Tensor:
        if not self.memories:
            return loss
        replay = summed_objective(self.memories, self._policy, self.config.batch_size, step.generator) / len(
            self.memories)  # one actor forward for all memories
        return loss + self.config.alpha * replay

    def make_memory(self, k: int, substrate: Substrate) -> Memory:
        return self.save_memory(k, substrate, gaussian_memory(substrate, k))
