"""The substrate-agnostic core of Sleeping Robots: memories, Nash aggregation, sleep, excitability, metrics.

Formulas only. Depends on torch, numpy and :mod:`sr_imitation.io` (memories are saved through it); the run
infrastructure around it (settings fingerprints, run log, provenance, command lines) is :mod:`sr_imitation.infra`.
The ACT (imitation) and SAC (RL) substrates plug into it.
"""

from sr_imitation.core.aggregation import (
    AGGREGATORS,
    Aggregation,
    Aggregator,
    FrankWolfeNashAggregator,
    MeanGradAggregator,
    MeanNormalizedAggregator,
    NashAggregator,
    PCGradAggregator,
    make_aggregator,
    nash_weights,
)
from sr_imitation.core.excitability import ExcitabilityConfig, ExcitableReLU, update_excitability
from sr_imitation.core.memory import (
    Memory,
    OutputDistillationMemory,
    load_memory,
    register_memory,
)
from sr_imitation.core.metrics import (
    afsr_curve,
    bwt_curve,
    mean_sem,
    policy_motion,
    prs_curve,
    spi_at_stage,
    stream_metrics,
    subspace_preservation,
)
from sr_imitation.core.sleep import (
    NonFiniteSleepError,
    SleepConfig,
    SleepResult,
    anchor_coefficient,
    sleep_consolidate,
)

__all__ = [
    "AGGREGATORS",
    "Aggregation",
    "Aggregator",
    "ExcitabilityConfig",
    "ExcitableReLU",
    "FrankWolfeNashAggregator",
    "MeanGradAggregator",
    "MeanNormalizedAggregator",
    "Memory",
    "NashAggregator",
    "NonFiniteSleepError",
    "OutputDistillationMemory",
    "PCGradAggregator",
    "SleepConfig",
    "SleepResult",
    "afsr_curve",
    "anchor_coefficient",
    "bwt_curve",
    "load_memory",
    "make_aggregator",
    "mean_sem",
    "policy_motion",
    "nash_weights",
    "prs_curve",
    "register_memory",
    "sleep_consolidate",
    "spi_at_stage",
    "stream_metrics",
    "subspace_preservation",
    "update_excitability",
]
