"""The stream engine: Algorithm 1 once for both substrates, continual methods as plugins.

- :mod:`~sr_imitation.stream.engine`: :class:`StreamEngine` (the phases, resume, the one call of the core's sleep);
- :mod:`~sr_imitation.stream.substrate`: the :class:`Substrate` protocol a policy family implements;
- :mod:`~sr_imitation.stream.methods`: :class:`ContinualMethod` and the registry (one file per method);
- :mod:`~sr_imitation.stream.rundir`: the run directory (fingerprint check before writing, progress, leftovers).

Substrate-free: nothing here imports LeRobot, MuJoCo or Meta-World (tested).
"""

from sr_imitation.stream.engine import StreamEngine
from sr_imitation.stream.methods import (
    METHODS,
    ContinualMethod,
    check_method,
    make_method,
    method_class,
    method_config,
    methods_for,
    register_method,
)
from sr_imitation.stream.rundir import RunDirectory
from sr_imitation.stream.substrate import MethodSettings, SleepProblem, Substrate

__all__ = ["METHODS", "ContinualMethod", "MethodSettings", "RunDirectory", "SleepProblem", "StreamEngine",
           "Substrate", "check_method", "make_method", "method_class", "method_config", "methods_for",
           "register_method"]
