"""Continual methods as plugins of the stream engine: one file per method, registered by name.

Adding a baseline: write ``sr_imitation/stream/methods/<name>.py`` with a :class:`ContinualMethod` subclass
decorated by :func:`register_method`, and import it below.
"""

from sr_imitation.stream.methods import (  # noqa: F401  (register the methods)
    agem,
    clear,
    der,
    ewc,
    lwf,
    m2distill,
    nash_mtl,
    pcgrad,
    progress_compress,
    replay,
    reset_distill,
    sequential_bc,
    sleeping_robots,
)
from sr_imitation.stream.methods.base import ContinualMethod, WakeStep
from sr_imitation.stream.methods.registry import METHODS, make_method, method_config, methods_for, register_method

__all__ = ["METHODS", "ContinualMethod", "WakeStep", "make_method", "method_config", "methods_for",
           "register_method"]
