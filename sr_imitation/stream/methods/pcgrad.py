"""PCGrad adapted to continual SAC (paper appendix B.1; Yu et al., 2020): the same per-skill wake gradients as
Nash-MTL, conflicting normalized gradients projected, the projected update rescaled to the original gradient norm
(:mod:`sr_imitation.stream.methods._wake_bargaining`)."""

from __future__ import annotations

from sr_imitation.core.aggregation import Aggregator, PCGradAggregator
from sr_imitation.stream.methods._wake_bargaining import WakeBargaining
from sr_imitation.stream.methods.registry import register_method


@register_method
class PCGrad(WakeBargaining):
    """PCGrad with the paper's rescaling; the projection order is drawn from a generator seeded per wake."""

    name = "pcgrad"

    def aggregator(self) -> Aggregator:
        return PCGradAggregator(seed=0, rescale=True)
