"""Combining per-skill gradients during the wake (the paper's adapted Nash-MTL and PCGrad baselines, appendix B.1).

At every actor update of wake k > 1 the current skill's gradient g_k (SAC's actor loss) and one gradient per past
skill g_i = d L_i / d theta (the frozen-critic surrogate of SR's memory M_i, each on ``batch_size`` of its states)
are combined by an aggregator of the core (:mod:`sr_imitation.core.aggregation`, the one SR's sleep uses) on their
Gram matrix, and the combined direction replaces the actor's gradient. The bargaining happens during wake instead of
offline sleep; these methods never sleep. ``batch_size`` (64, the sleep's) is our choice.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import torch

from sr_imitation.core.aggregation import Aggregator
from sr_imitation.stream.methods._gradients import current_grad, flat_grad, set_grad
from sr_imitation.stream.methods.base import ContinualMethod, WakeStep


@dataclass(frozen=True)
class WakeBargainingConfig:
    batch_size: int = 64
    """States drawn from each past skill's memory per update (our choice: the sleep's batch size)."""


class WakeBargaining(ContinualMethod):
    """Base of Nash-MTL and PCGrad: subclasses name themselves and build their :meth:`aggregator`."""

    substrates = frozenset({"sac"})  # the MT5 comparison's: the past skills' gradients are of frozen-critic surrogates
    stores_memories = True
    resumable_wake_hooks = True  # the aggregator's warm start or generator is the wake state (wake_state)
    config: ClassVar[WakeBargainingConfig] = WakeBargainingConfig()

    def aggregator(self) -> Aggregator:
        raise NotImplementedError

    def begin_wake(self, k, memories, substrate) -> None:  # noqa: ANN001 - the base's signature
        super().begin_wake(k, memories, substrate)
        self._aggregator = self.aggregator()

    def wake_state(self) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
        """The aggregator's state (:meth:`~sr_imitation.core.aggregation.Aggregator.state`)."""
        return {}, {"aggregator": self._aggregator.state()}

    def load_wake_state(self, tensors: Mapping[str, torch.Tensor], record: Mapping[str, Any]) -> None:
        self._aggregator.load_state(record["aggregator"])

    def sleeps_after(self, skill_number: int) -> bool:
        return False

    def adjust_gradients(self, step: WakeStep) -> dict[str, float]:
        if not self.memories:
            return {}
        grads = [flat_grad(m.objective(step.policy, self.config.batch_size, step.generator), step.parameters)
                 for m in self.memories]
        jac = torch.stack([*grads, current_grad(step.parameters)])
        gram = (jac @ jac.T).double().cpu().numpy()
        agg = self._aggregator(0.5 * (gram + gram.T))
        set_grad(step.parameters, torch.as_tensor(agg.weights, dtype=jac.dtype) @ jac)
        return {"weight_current": float(np.asarray(agg.alpha)[-1]), "min_cosine_current": _min_cos(gram)}



def _min_cos(gram: np.ndarray) -> float:
    """The smallest cosine between the current skill's gradient (last row) and a past skill's."""
    d = np.sqrt(np.clip(np.diag(gram), 1e-30, None))
    return float((gram[-1, :-1] / (d[-1] * d[:-1])).min())
