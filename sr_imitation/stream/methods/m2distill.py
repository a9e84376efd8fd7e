"""M2Distill (Roy et al., 2024, "Multi-Modal Distillation for Lifelong Imitation Learning") ported to ACT, as the
paper's imitation baseline (appendix B: "distillation ... of intermediate visual features in addition to action
outputs").

The teacher is the policy as it was before this skill's wake (one rolling teacher, as in M2Distill and LwF). At every
update of wake k > 1 the loss gets, on the update's observations o of skill k,

    lambda_a * mean || pi_theta(o) - pi_prev(o) ||^2  +  lambda_f * sum_m mean || f_m(o) - f_m^prev(o) ||^2

where pi is the deterministic action chunk (zero latent, as at inference) and f_m the policy's intermediate features
(``ACTSRPolicy.action_chunk_and_features``): every input modality's embedding (each camera's ResNet feature map
with images, the state tokens' input projections) and the transformer encoder's output tokens. Our port, following
the notes (shared/notes/continual-learning-baselines.md §4.1): ACT has no GMM head, so M2Distill's Monte-Carlo KL
between action distributions becomes the squared error of action chunks; there is no language input, so no L_text;
proprioception is the state token (M2Distill's L_extra). No replay buffer: nothing of earlier skills' data is kept;
the teacher, one copy of the policy's weights, is counted in the memory budget as LwF's.
lambda_a = lambda_f = 1 (our choice; M2Distill tunes per suite, the paper does not give them).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import torch
from torch import Tensor

from sr_imitation.stream.capabilities import IntermediateFeatures, PolicySnapshots, capability
from sr_imitation.stream.methods.base import WakeStep
from sr_imitation.stream.methods.lwf import LwF
from sr_imitation.stream.methods.registry import register_method
from sr_imitation.stream.substrate import Substrate


@dataclass(frozen=True)
class M2DistillConfig:
    action_weight: float = 1.0
    """lambda_a, the weight of the action-chunk distillation (our choice)."""
    feature_weight: float = 1.0
    """lambda_f, the weight of each feature's distillation (our choice)."""


def feature_distance(current: dict[str, Tensor], previous: dict[str, Tensor]) -> Tensor:
    """sum over features m of mean ||f_m - f_m^prev||^2 (the same features on both sides)."""
    if current.keys() != previous.keys():
        raise ValueError(f"feature sets differ: {sorted(current)} vs {sorted(previous)}")
    return sum((current[m] - previous[m]).pow(2).mean() for m in sorted(current))  # type: ignore[return-value]


@register_method
class M2Distill(LwF):
    """LwF's rolling teacher, distilled through the intermediate features as well as the actions."""

    name = "m2distill"
    requires = (PolicySnapshots, IntermediateFeatures)
    config: ClassVar[M2DistillConfig] = M2DistillConfig()  # type: ignore[assignment]

    def begin_wake(self, k: int, memories: Any, substrate: Substrate) -> None:
        super().begin_wake(k, memories, substrate)  # LwF's teacher: the policy before this wake
        self.current = capability(substrate, IntermediateFeatures).chunk_and_features

    def wake_loss(self, loss: Tensor, step: WakeStep) -> Tensor:
        if self.teacher is None:
            return loss
        with torch.no_grad():
            target_chunk, target_features = self.teacher.action_chunk_and_features(step.batch)
        chunk, features = self.current(step.batch)
        c = self.config
        action = (chunk - target_chunk).pow(2).mean()
        return loss + c.action_weight * action + c.feature_weight * feature_distance(features, target_features)
