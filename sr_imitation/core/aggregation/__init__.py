"""Gradient aggregators for sleep consolidation: Nash bargaining (Eq. 1), its Frank-Wolfe ablation, means, PCGrad.

All aggregators take the k x k Gram matrix of raw per-memory gradients and return raw-gradient weights.

=================== =========================================================================================
name                what
=================== =========================================================================================
``nash``            Eq. 1 solved exactly (active-set Newton; the min-norm point when no direction agrees)
``nash_fw``         Eq. 1 by the paper's warm-started Frank-Wolfe with a fixed budget (approximate; ablation)
``mean_grad``       mean of the raw gradients (the paper's Mean-grad ablation)
``mean_normalized`` mean of the normalized gradients (equals ``nash`` for k = 2)
``pcgrad``          PCGrad on normalized gradients (optionally rescaled to the raw mean's norm)
=================== =========================================================================================
"""

from __future__ import annotations

from typing import Any

from sr_imitation.core.aggregation._base import Aggregation, Aggregator
from sr_imitation.core.aggregation._frank_wolfe import (
    FrankWolfeNashAggregator,
    extended_nash_objective,
    frank_wolfe_nash,
)
from sr_imitation.core.aggregation._gram import GRAD_NORM_EPS, cosine_matrix, normalized_gram
from sr_imitation.core.aggregation._mean import MeanGradAggregator, MeanNormalizedAggregator
from sr_imitation.core.aggregation._min_norm import min_norm_point
from sr_imitation.core.aggregation._nash import NASH_EPS, NashAggregator, NashSolution, nash_objective, solve_nash
from sr_imitation.core.aggregation._pcgrad import PCGradAggregator

AGGREGATORS: dict[str, type[Aggregator]] = {
    cls.name: cls
    for cls in (NashAggregator, FrankWolfeNashAggregator, MeanGradAggregator, MeanNormalizedAggregator,
                PCGradAggregator)
}


def make_aggregator(name: str, **kwargs: Any) -> Aggregator:
    """Build an aggregator by name (see the module docstring for the names)."""
    try:
        cls = AGGREGATORS[name]
    except KeyError:
        hint = " ('mean' was split into 'mean_grad' and 'mean_normalized')" if name == "mean" else ""
        raise ValueError(f"unknown aggregator {name!r}{hint}; choose from {sorted(AGGREGATORS)}") from None
    return cls(**kwargs)


def nash_weights(gram, **kwargs: Any) -> Aggregation:
    """One cold-started exact Nash solve (Eq. 1) on a raw Gram matrix; see :class:`NashAggregator`."""
    return NashAggregator(warm_start=False, **kwargs)(gram)


__all__ = [
    "AGGREGATORS",
    "GRAD_NORM_EPS",
    "NASH_EPS",
    "Aggregation",
    "Aggregator",
    "FrankWolfeNashAggregator",
    "MeanGradAggregator",
    "MeanNormalizedAggregator",
    "NashAggregator",
    "NashSolution",
    "PCGradAggregator",
    "cosine_matrix",
    "extended_nash_objective",
    "frank_wolfe_nash",
    "make_aggregator",
    "min_norm_point",
    "nash_objective",
    "nash_weights",
    "normalized_gram",
    "solve_nash",
]
