"""Continual methods as plugins of the stream engine: one file per method, registered by name.

Adding a method: write ``sr_imitation/stream/methods/<name>.py`` with a :class:`ContinualMethod` subclass decorated
by :func:`register_method` (docs/ARCHITECTURE.md, "Adding a method"). Every module of this package whose name does not
start with ``_`` is imported here, so the file alone registers the method.
"""

from sr_imitation.stream.methods.base import ContinualMethod, WakeStep
from sr_imitation.stream.methods.registry import (
    METHODS,
    check_method,
    import_method_files,
    make_method,
    method_class,
    method_config,
    methods_for,
    register_method,
    replaced_key_refusal,
    replaced_setting_refusal,
)

import_method_files(__name__, __path__, skip=("base", "registry"))  # each file registers its methods

__all__ = ["METHODS", "ContinualMethod", "WakeStep", "check_method", "make_method", "method_class", "method_config",
           "methods_for", "register_method", "replaced_key_refusal", "replaced_setting_refusal"]
