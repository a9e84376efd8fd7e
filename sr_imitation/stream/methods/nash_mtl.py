"""Nash-MTL adapted to continual SAC (paper appendix B.1; Navon et al., 2022): per-skill gradients bargained by the
same Nash solver SR's sleep uses, at every wake update instead of in an offline sleep
(:mod:`sr_imitation.stream.methods._wake_bargaining`)."""

from __future__ import annotations

from sr_imitation.core.aggregation import Aggregator, NashAggregator
from sr_imitation.stream.methods._wake_bargaining import WakeBargaining
from sr_imitation.stream.methods.registry import register_method


@register_method
class NashMTL(WakeBargaining):
    """Eq. 1 on the current skill's and the past memories' gradients, solved exactly, warm-started per wake."""

    name = "nash_mtl"

    def aggregator(self) -> Aggregator:
        return NashAggregator()
