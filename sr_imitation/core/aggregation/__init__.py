"""Gradient aggregators for sleep consolidation: Nash bargaining (Eq. 1), mean, PCGrad.

All aggregators take the k x k Gram matrix of raw per-memory gradients and return raw-gradient weights.
"""

from __future__ import annotations

from typing import Any

from sr_imitation.core.aggregation._base import Aggregation, Aggregator
from sr_imitation.core.aggregation._gram import GRAD_NORM_EPS, normalized_gram
from sr_imitation.core.aggregation._mean import MeanAggregator
from sr_imitation.core.aggregation._nash import NASH_EPS, NashAggregator, frank_wolfe_nash, nash_objective
from sr_imitation.core.aggregation._pcgrad import PCGradAggregator

AGGREGATORS: dict[str, type[Aggregator]] = {
    cls.name: cls for cls in (NashAggregator, MeanAggregator, PCGradAggregator)
}


def make_aggregator(name: str, **kwargs: Any) -> Aggregator:
    """Build an aggregator by name (``nash``, ``mean`` or ``pcgrad``)."""
    try:
        cls = AGGREGATORS[name]
    except KeyError:
        raise ValueError(f"unknown aggregator {name!r}; choose from {sorted(AGGREGATORS)}") from None
    return cls(**kwargs)


def nash_weights(gram, iterations: int = 50, **kwargs: Any) -> Aggregation:
    """One cold-started Nash solve (Eq. 1) on a raw Gram matrix; see :class:`NashAggregator`."""
    return NashAggregator(iterations=iterations, **kwargs)(gram)


__all__ = [
    "AGGREGATORS",
    "GRAD_NORM_EPS",
    "NASH_EPS",
    "Aggregation",
    "Aggregator",
    "MeanAggregator",
    "NashAggregator",
    "PCGradAggregator",
    "frank_wolfe_nash",
    "make_aggregator",
    "nash_objective",
    "nash_weights",
    "normalized_gram",
]
