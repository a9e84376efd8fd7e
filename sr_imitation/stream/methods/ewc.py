"""EWC (Kirkpatrick et al., 2017) as the paper's MT5 baseline (appendix B.1).

After each skill i: a snapshot theta_i* of the policy parameters and the diagonal Fisher information F_i of the
policy, estimated on ``fisher_states`` states of the skill (paper: 2000) and normalized to unit Frobenius norm
(paper). Later wakes add, at every policy update,

    (lambda / 2) sum_{i < k} sum_j F_{i,j} (theta_j - theta*_{i,j})^2                    (lambda = 1; paper)

to the substrate's policy loss (SAC: the actor loss). The Fisher is the policy's own (not the empirical one): for
each state s one action u ~ pi_theta(.|s) is drawn and F = mean_s (d log pi_theta(u|s) / d theta)^2 (our choice of
estimator; the paper names only the state count and the normalization). On SAC the log-likelihood is that of the
pre-tanh Gaussian (``SACSubstrate.log_likelihood``); only the actor is protected (the critic is relearned per skill,
as for every method here). On ACT (deterministic chunks) it is the empirical Fisher: the squared gradient of the
L1 behaviour-cloning loss of the deployed chunk on single demonstration frames (``ACTSubstrate.log_likelihood``);
the lambda for ACT is not tuned yet (the paper tunes it on MT5 only).

Memory per skill: theta* and F, one float32 each per actor parameter (the paper's table: 3.0 MB at K = 5).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import torch
from torch import Tensor

from sr_imitation.core.memory import Memory, register_memory
from sr_imitation.stream.capabilities import LikelihoodPolicy, capability
from sr_imitation.stream.methods.base import ContinualMethod, WakeStep
from sr_imitation.stream.methods.registry import register_method
from sr_imitation.stream.substrate import Substrate


@dataclass(frozen=True)
class EWCConfig:
    lam: float = 1.0
    """lambda of the penalty (paper: 1, tuned over {500, 100, 1} on MT5)."""
    fisher_states: int = 2000
    """States per skill the Fisher is estimated on (paper: 2000)."""


@register_memory
class FisherMemory(Memory):
    """theta_i* (``anchor.<n>``) and the normalized diagonal Fisher F_i (``fisher.<n>``), one pair per policy
    parameter in the substrate's parameter order. No buffer: :meth:`loss` takes the current parameters."""

    kind = "ewc_fisher"
    contents = "parameter snapshot theta* + diagonal Fisher"

    def _validate(self) -> None:
        super()._validate()
        n = len(self.tensors) // 2
        for i in range(n):
            a, f = self.tensors.get(f"anchor.{i:03d}"), self.tensors.get(f"fisher.{i:03d}")
            if a is None or f is None or a.shape != f.shape:
                raise ValueError(f"FisherMemory({self.skill!r}): parameter {i} needs an anchor and a Fisher of one "
                                 "shape")
        if 2 * n != len(self.tensors):
            raise ValueError(f"FisherMemory({self.skill!r}): tensors must be anchor/fisher pairs")

    @classmethod
    def estimate(cls, skill: str, parameters: Sequence[Tensor], log_likelihood: Any, states: Any,
                 generator: torch.Generator) -> FisherMemory:
        """F = mean over ``states`` of the squared gradient of ``log_likelihood(sample, generator)`` (one backward
        per sample), normalized to unit Frobenius norm over all parameters together. ``states``: a tensor (each row
        is passed as a batch of one) or a sequence of single-sample batches (ACT: preprocessed dataset items)."""
        fisher = [torch.zeros_like(p) for p in parameters]
        samples = [row[None] for row in states] if isinstance(states, Tensor) else list(states)
        for s in samples:
            grads = torch.autograd.grad(log_likelihood(s, generator).sum(), list(parameters), allow_unused=True)
            for f, g in zip(fisher, grads, strict=True):
                if g is not None:
                    f.add_(g.detach().pow(2))
        norm = torch.sqrt(sum(f.div_(len(samples)).pow(2).sum() for f in fisher))
        if not torch.isfinite(norm) or norm <= 0:
            raise ValueError(f"EWC on skill {skill!r}: the Fisher estimate is {float(norm)} (no gradient signal)")
        tensors = {f"anchor.{i:03d}": p.detach().clone() for i, p in enumerate(parameters)}
        tensors.update({f"fisher.{i:03d}": f / norm for i, f in enumerate(fisher)})
        return cls(skill, tensors, {"states": len(samples)})

    def penalty(self, parameters: Sequence[Tensor]) -> Tensor:
        """sum_j F_j (theta_j - theta*_j)^2 (without lambda / 2)."""
        if len(parameters) != len(self.tensors) // 2:
            raise ValueError(f"EWC memory {self.skill!r} protects {len(self.tensors) // 2} parameters, the policy "
                             f"has {len(parameters)}")
        return sum((self.tensors[f"fisher.{i:03d}"] * (p - self.tensors[f"anchor.{i:03d}"]).pow(2)).sum()
                   for i, p in enumerate(parameters))

    def loss(self, policy: Any, batch: Mapping[str, Tensor]) -> Tensor:
        return self.penalty(policy)


@register_method
class EWC(ContinualMethod):
    """Elastic weight consolidation: a Fisher-weighted pull toward every earlier skill's parameters in each wake."""

    name = "ewc"
    resumable_wake_hooks = True  # nothing carried from one update to the next
    requires = (LikelihoodPolicy,)
    stores_memories = True
    memory_name = "ewc"
    config: ClassVar[EWCConfig] = EWCConfig()

    @property
    def wake_state_sample(self) -> int:
        """States the substrate keeps from each wake for the Fisher (``SACSubstrate.state_sample``)."""
        return self.config.fisher_states

    def wake_loss(self, loss: Tensor, step: WakeStep) -> Tensor:
        if not self.memories:
            return loss
        penalty = sum(m.penalty(step.parameters) for m in self.memories if isinstance(m, FisherMemory))
        return loss + 0.5 * self.config.lam * penalty

    def make_memory(self, k: int, substrate: Substrate) -> Memory:
        s = capability(substrate, LikelihoodPolicy)
        generator = torch.Generator().manual_seed(31 + k)
        memory = FisherMemory.estimate(s.memory_skill(k), s.policy_parameters(), s.log_likelihood,
                                       s.state_sample(k, self.config.fisher_states), generator)
        return self.save_memory(k, substrate, memory)
