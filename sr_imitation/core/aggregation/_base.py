"""The aggregator interface: a k x k Gram matrix in, raw-gradient weights out."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from sr_imitation.core.aggregation._gram import GRAD_NORM_EPS


@dataclass(frozen=True)
class Aggregation:
    """Result of combining k per-memory gradients.

    Attributes:
        weights: raw-gradient weights ``w`` (k,); the combined direction is ``d = sum_j w_j g_j``.
        alpha: the weights on the *normalized* gradients g_hat_j (k,); convex (on the simplex) for Nash and
            mean_normalized, the effective projection coefficients for PCGrad; for mean_grad the uniform
            weights 1/k of the raw gradients.
        iterations: solver iterations used (0 for closed forms).
        gap: Frank-Wolfe duality gap at return (0 for closed forms).
        objective: the aggregator's objective at ``alpha`` (Eq. 1 for Nash; NaN when undefined).
        active: boolean mask (k,) of memories that took part (zero gradients are masked out).
        status: how the weights were obtained: ``closed_form``, ``optimal``, ``pareto_stationary`` (Nash: the
            maximizer opposed some memory, so the min-norm point), ``max_iterations``, ``stalled``,
            ``all_zero``; ``approximate`` for fixed-iteration Frank-Wolfe.
    """

    weights: np.ndarray
    alpha: np.ndarray
    iterations: int = 0
    gap: float = 0.0
    objective: float = float("nan")
    active: np.ndarray = field(default_factory=lambda: np.ones(0, dtype=bool))
    status: str = "closed_form"


class Aggregator(ABC):
    """Maps the Gram matrix ``G = J J^T`` of raw per-memory gradients to raw-gradient weights.

    Working on the Gram matrix keeps the solver O(k^2) per iteration, independent of the number of policy
    parameters P; the O(k^2 P) Gram product and the O(k P) combination happen once per sleep step outside.
    """

    name: ClassVar[str]

    def __init__(self, eps: float = GRAD_NORM_EPS) -> None:
        if not eps > 0:
            raise ValueError(f"eps must be > 0, got {eps}")
        self.eps = float(eps)

    @abstractmethod
    def __call__(self, gram: np.ndarray) -> Aggregation:
        """Aggregate; ``gram`` must be finite (a ValueError names the non-finite rows otherwise)."""

    def reset(self) -> None:  # noqa: B027 - optional hook, stateless aggregators need nothing
        """Forget any warm-start state (call between sleep phases of different runs)."""

    def state(self) -> dict[str, Any]:
        """What the aggregator carries from one call to the next (a warm start, a generator), as JSON values:
        :meth:`load_state` on an aggregator built with the same settings makes its next calls return what this
        one's would. Default: nothing (stateless)."""
        return {}

    def load_state(self, state: dict[str, Any]) -> None:  # noqa: B027 - optional hook, stateless: nothing to load
        """Restore what :meth:`state` returned."""

    def __repr__(self) -> str:
        return f"{type(self).__name__}(eps={self.eps:g})"
