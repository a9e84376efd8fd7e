"""Progress & Compress (Schwarz et al., 2018) as the paper's MT5 baseline (appendix B.1), without lateral
connections (our simplification; the paper's appendix names only the column reset, MSE distillation and EWC).

Progress: an active column (a freshly initialized actor and critic per skill, as in Reset & Distill) learns the
skill; it is frozen as the skill's expert (its Gaussian mean and log-std on ``states`` states of the skill).
Compress: the knowledge base, the shared and deployed actor, continues from the previous compression and is
trained on the *current* expert only, with EWC protecting what it held before:

    min_theta  E_{s ~ B_k} || [mu_theta(s), log sigma_theta(s)] - [mu_k(s), log sigma_k(s)] ||^2
               + (lambda / 2) sum_{i < k} sum_j F_{i,j} (theta_j - theta*_{i,j})^2

where theta*_i is the knowledge base after compression i and F_i its diagonal Fisher on skill i's states
(``fisher_states`` of them, normalized to unit Frobenius norm, as the paper says; estimated as in
:mod:`~sr_imitation.stream.methods.ewc`). The compression runs in the engine's sleep phase (as Reset & Distill's
distillation, with the EWC term as the sleep's regularizer); F_{k-1} is estimated when compression k starts, from
the knowledge base it starts from (= theta*_{k-1}), and saved. After the first skill the knowledge base starts as
the first active column (our choice). Compression: ``iterations`` Adam steps of ``batch_size`` states, ``lr``
(ours: Reset & Distill's values); lambda = 1 (ours: EWC's).

Memory: per skill the knowledge base's snapshot and Fisher (2 x the actor's parameters) and the expert's states and
outputs (kept for a resume; only the current one is used).
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import Any, ClassVar

import torch

from sr_imitation.core.memory import Memory
from sr_imitation.stream.capabilities import GaussianActor, LikelihoodPolicy, ResettableNetworks, capability
from sr_imitation.stream.methods.der import state_gaussian
from sr_imitation.stream.methods.ewc import FisherMemory
from sr_imitation.stream.methods.registry import register_method
from sr_imitation.stream.methods.reset_distill import ResetDistill
from sr_imitation.stream.substrate import SleepProblem, Substrate


@dataclass(frozen=True)
class ProgressCompressConfig:
    iterations: int = 2000
    """Compression steps after each skill (our choice: Reset & Distill's 2000)."""
    batch_size: int = 256
    """States of the current expert per step (our choice: Reset & Distill's 256)."""
    lr: float = 3e-4
    """Adam learning rate of the compression (our choice: SAC's actor learning rate)."""
    lam: float = 1.0
    """lambda of the EWC term (our choice: EWC's 1)."""
    fisher_states: int = 2000
    """States per skill for the knowledge base's Fisher (our choice: EWC's 2000)."""


@register_method
class ProgressCompress(ResetDistill):
    """An active column per skill, compressed into one knowledge base by distillation under EWC."""

    name = "progress_compress"
    # what Reset & Distill asks, and a Gaussian actor: the compression distils and weighs the Gaussian (SAC only)
    requires: ClassVar[tuple[Any, ...]] = (*ResetDistill.requires, GaussianActor)
    config: ClassVar[ProgressCompressConfig] = ProgressCompressConfig()  # type: ignore[assignment]

    @property
    def wake_state_sample(self) -> int:
        return self.config.fisher_states

    def sleep_memories(self, k: int, memories: Any) -> list[Memory]:
        return [memories[k]]  # only the current active column is compressed

    def _fisher(self, i: int, substrate: Substrate) -> FisherMemory:
        """F_i and theta*_i of the knowledge base after compression i (estimated now if not saved yet: the caller
        has the knowledge base at theta*_i)."""
        try:
            saved = substrate.load_memory(i, name="kb_fisher")
        except FileNotFoundError:
            s = capability(substrate, LikelihoodPolicy)
            memory = FisherMemory.estimate(substrate.memory_skill(i), s.policy_parameters(), s.log_likelihood,
                                           s.state_sample(i), torch.Generator().manual_seed(41 + i))
            substrate.save_memory(i, memory, name="kb_fisher")
            return memory
        if not isinstance(saved, FisherMemory):
            raise TypeError(f"stage {i + 1}: the saved kb_fisher memory is a {type(saved).__name__}, not a Fisher")
        return saved

    def prepare_sleep(self, k: int, problem: SleepProblem, substrate: Substrate) -> SleepProblem:
        fishers: list[FisherMemory] = []
        if k > 0:  # the knowledge base after compression k - 1
            capability(substrate, ResettableNetworks).load_actor(k - 1, "sleep")
            fishers = [self._fisher(i, substrate) for i in range(k)]
        config = self.own_sleep_config(problem.config)
        lam = self.config.lam

        def ewc(params: Any) -> torch.Tensor:
            return 0.5 * lam * sum(f.penalty(params) for f in fishers)

        parameters = capability(substrate, LikelihoodPolicy).policy_parameters()
        return SleepProblem(parameters, state_gaussian(substrate), config, regularizer=ewc if fishers else None)

    def extra_memories(self, substrate: Substrate, stages: int) -> list[Memory]:
        out = []
        for i in range(stages):
            with contextlib.suppress(FileNotFoundError):  # the last skill's Fisher: only if another skill follows
                out.append(substrate.load_memory(i, name="kb_fisher"))
        return out
