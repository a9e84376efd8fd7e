"""Mean of normalized gradients: the "Mean-grad" sleep ablation (paper Table "MT5 ablations")."""

from __future__ import annotations

import numpy as np

from sr_imitation.core.aggregation._base import Aggregation, Aggregator
from sr_imitation.core.aggregation._gram import as_gram, normalized_gram


class MeanAggregator(Aggregator):
    """``d = (1/k) sum_i g_hat_i``: every memory gets the same weight after l2 normalization.

    With two memories this equals Nash bargaining (Eq. 1 is maximized at (1/2, 1/2) for k = 2); the two
    differ from k = 3 on.
    """

    name = "mean"

    def __call__(self, gram: np.ndarray) -> Aggregation:
        gram = as_gram(gram)
        k = gram.shape[0]
        _, scale = normalized_gram(gram, self.eps)
        alpha = np.full(k, 1.0 / k)
        return Aggregation(alpha * scale, alpha, 0, 0.0, float("nan"), np.ones(k, dtype=bool))
