"""PCGrad (Yu et al. 2020) on normalized gradients, written on the Gram matrix.

For each memory i, start from g_hat_i and, for every other memory j in a random order, remove the component
along g_hat_j when the two conflict (negative inner product). The projected gradients are averaged. All
projections are tracked as coefficient vectors over the g_hat_j, so the whole procedure needs only the
normalized Gram matrix (O(k^3)), as in torchjd's ``PCGradWeighting``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from sr_imitation.core.aggregation._base import Aggregation, Aggregator
from sr_imitation.core.aggregation._gram import GRAD_NORM_EPS, as_gram, normalized_gram


class PCGradAggregator(Aggregator):
    """Projecting conflicting gradients, mean reduction, seeded random projection order.

    Args:
        eps: gradient-normalization constant.
        seed: seed of the generator that draws the projection order (reproducible runs).
        reduction: ``"mean"`` (default, same scale as a convex combination) or ``"sum"`` (original PCGrad).
        rescale: rescale the projected update to the norm of the same reduction of the *raw* gradients
            (``||mean_i g_i||`` or ``||sum_i g_i||``), as the paper's PCGrad baseline does ("the projected update
            is rescaled to the original gradient norm", appendix B; "original" read as the un-projected,
            un-normalized update: our reading). Computed from the Gram matrix, ``||J^T w||^2 = w^T G w``.
    """

    name = "pcgrad"

    def __init__(self, eps: float = GRAD_NORM_EPS, seed: int = 0, reduction: str = "mean",
                 rescale: bool = False) -> None:
        super().__init__(eps)
        if reduction not in ("mean", "sum"):
            raise ValueError(f"reduction must be 'mean' or 'sum', got {reduction!r}")
        self.seed = int(seed)
        self.reduction = reduction
        self.rescale = bool(rescale)
        self._rng = np.random.default_rng(self.seed)

    def reset(self) -> None:
        self._rng = np.random.default_rng(self.seed)

    def state(self) -> dict[str, Any]:
        """The projection-order generator's state."""
        return {"rng": self._rng.bit_generator.state}

    def load_state(self, state: dict[str, Any]) -> None:
        self._rng.bit_generator.state = state["rng"]

    def __call__(self, gram: np.ndarray) -> Aggregation:
        gram = as_gram(gram)
        k = gram.shape[0]
        g_hat, scale = normalized_gram(gram, self.eps)
        total = np.zeros(k)
        for i in range(k):
            coef = np.zeros(k)
            coef[i] = 1.0
            for j in self._rng.permutation(k):
                if j == i or g_hat[j, j] <= 0.0:
                    continue
                inner = float(g_hat[j] @ coef)
                if inner < 0.0:
                    coef[j] -= inner / g_hat[j, j]
            total += coef
        alpha = total / k if self.reduction == "mean" else total
        weights = alpha * scale
        if self.rescale:
            raw = np.full(k, 1.0 / k if self.reduction == "mean" else 1.0)
            target = float(raw @ gram @ raw)
            current = float(weights @ gram @ weights)
            factor = np.sqrt(max(target, 0.0) / current) if current > 0.0 else 0.0
            weights, alpha = weights * factor, alpha * factor
        return Aggregation(weights, alpha, 0, 0.0, float("nan"), np.ones(k, dtype=bool))

    def __repr__(self) -> str:
        return (f"PCGradAggregator(eps={self.eps:g}, seed={self.seed}, reduction={self.reduction!r}, "
                f"rescale={self.rescale})")
