"""Sequential fine-tuning (sequential BC on ACT, plain sequential SAC): no memories, no sleep (paper, appendix B)."""

from __future__ import annotations

from sr_imitation.stream.methods.base import ContinualMethod
from sr_imitation.stream.methods.registry import register_method


@register_method
class SequentialFinetuning(ContinualMethod):
    """Each skill trains the shared policy on its own data only; nothing protects earlier skills."""

    name = "sequential_bc"
