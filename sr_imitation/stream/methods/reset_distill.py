"""Reset & Distill (Wolczyk et al., 2022) as the paper's MT5 baseline (appendix B.1).

Each skill is learned by a freshly initialized actor and critic (the global random state is left alone; the
observation normalizer is shared); the trained actor is frozen as that skill's expert: its Gaussian mean and log-std
on ``states`` states of the skill (paper: 1000; ours are the late-wake states SR's memory holds). After each skill
every expert so far is distilled into the shared actor, the deployed policy:

    min_theta  mean_{i <= k} E_{s ~ B_i} || [mu_theta(s), log sigma_theta(s)] - [mu_i(s), log sigma_i(s)] ||^2

for ``iterations`` Adam steps (paper: 2000), ``batch_size`` states per expert per step (paper: batch 256; per
expert is our reading), learning rate ``lr`` (our choice: SAC's actor learning rate), no anchor, no early stop.
The distillation runs in the engine's sleep phase (``sr_imitation.core.sleep_consolidate`` with the raw-gradient
mean, i.e. the gradient of the mean loss), so it is checkpointed, logged and resumed like SR's sleep. The shared
actor continues from the previous distillation; after the first skill it starts as the first expert (our choice).
``wake.eval`` measures the expert, ``sleep.eval`` the shared actor.

Memory per skill: the states (1000 x 39 float32) and the expert's outputs on them (1000 x 8): 0.19 MB.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, ClassVar

from sr_imitation.core.memory import Memory
from sr_imitation.stream.capabilities import GaussianActor, LikelihoodPolicy, ResettableNetworks, capability
from sr_imitation.stream.methods.base import ContinualMethod
from sr_imitation.stream.methods.der import gaussian_memory, state_gaussian
from sr_imitation.stream.methods.registry import register_method
from sr_imitation.stream.substrate import SleepProblem, Substrate


@dataclass(frozen=True)
class ResetDistillConfig:
    iterations: int = 2000
    """Distillation steps after each skill (paper: 2000)."""
    batch_size: int = 256
    """States per expert per step (paper: batch 256)."""
    lr: float = 3e-4
    """Adam learning rate of the distillation (our choice: SAC's actor learning rate)."""


@register_method
class ResetDistill(ContinualMethod):
    """A fresh network per skill, then all experts distilled into one shared actor."""

    name = "reset_distill"
    requires: ClassVar[tuple[type, ...]] = (GaussianActor, ResettableNetworks, LikelihoodPolicy)
    stores_memories = True
    memory_name = "expert"
    config: ClassVar[ResetDistillConfig] = ResetDistillConfig()

    def sleeps_after(self, skill_number: int) -> bool:
        return True  # the distillation, after every skill (not SR's sleep: --sleep.enabled does not apply)

    def begin_wake(self, k: int, memories: Any, substrate: Substrate) -> None:
        super().begin_wake(k, memories, substrate)
        capability(substrate, ResettableNetworks).reset_networks(k)

    def make_memory(self, k: int, substrate: Substrate) -> Memory:
        return self.save_memory(k, substrate, gaussian_memory(substrate, k))

    def prepare_sleep(self, k: int, problem: SleepProblem, substrate: Substrate) -> SleepProblem:
        if k > 0:  # the shared actor as the previous distillation left it
            capability(substrate, ResettableNetworks).load_actor(k - 1, "sleep")
        c = self.config
        config = dataclasses.replace(problem.config, aggregator="mean_grad", max_iterations=c.iterations,
                                     batch_size=c.batch_size, lr=c.lr, anchor_strength=0.0, early_stop_tol=0.0)
        parameters = capability(substrate, LikelihoodPolicy).policy_parameters()
        return SleepProblem(parameters, state_gaussian(substrate), config)
