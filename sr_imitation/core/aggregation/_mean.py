"""Gradient means: the paper's Mean-grad ablation (raw gradients) and the mean of normalized gradients."""

from __future__ import annotations

import numpy as np

from sr_imitation.core.aggregation._base import Aggregation, Aggregator
from sr_imitation.core.aggregation._gram import as_gram, normalized_gram


class MeanGradAggregator(Aggregator):
    """``d = (1/k) sum_i g_i`` on the **raw** gradients: the paper's Mean-grad ablation (Table "MT5 ablations").

    The paper motivates Nash by the mean being "sensitive to gradient scale" (Section 3): here a memory with a
    10x larger gradient moves the policy 10x more. ``alpha`` reports the uniform weights 1/k of the raw
    gradients (so the recorded sleep objective ``alpha . losses`` is the mean memory loss).
    """

    name = "mean_grad"

    def __call__(self, gram: np.ndarray) -> Aggregation:
        gram = as_gram(gram)
        k = gram.shape[0]
        weights = np.full(k, 1.0 / k)
        return Aggregation(weights, weights.copy(), 0, 0.0, float("nan"), np.ones(k, dtype=bool))


class MeanNormalizedAggregator(Aggregator):
    """``d = (1/k) sum_i g_hat_i``: every memory gets the same weight after l2 normalization (our variant).

    Not the paper's Mean-grad ablation (that is :class:`MeanGradAggregator`): normalization already removes the
    scale sensitivity, and with two memories this equals Nash bargaining (Eq. 1 is maximized at (1/2, 1/2) for
    k = 2); the two differ from k = 3 on.
    """

    name = "mean_normalized"

    def __call__(self, gram: np.ndarray) -> Aggregation:
        gram = as_gram(gram)
        k = gram.shape[0]
        _, scale = normalized_gram(gram, self.eps)
        alpha = np.full(k, 1.0 / k)
        return Aggregation(alpha * scale, alpha, 0, 0.0, float("nan"), np.ones(k, dtype=bool))
