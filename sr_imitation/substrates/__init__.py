"""The substrates: one folder each (``act``: ACT-SR on LeRobot; ``sac``: SAC with critic memories on Meta-World).

Adding a substrate: a folder ``sr_imitation/substrates/<name>/`` whose ``__init__.py`` registers its command
(:mod:`sr_imitation.substrates.registry`; docs/ARCHITECTURE.md, "Adding a substrate"). Every sub-package of this
package is imported by :func:`discover` (which ``sr-train`` calls), so the folder alone registers the substrate;
importing one substrate imports no other. Substrates never import one another
(tests/test_architecture.py).
"""

from __future__ import annotations

import importlib
import pkgutil

from sr_imitation.substrates.registry import SUBSTRATES, SubstrateCommand, register_substrate


def discover() -> dict[str, type[SubstrateCommand]]:
    """Import every substrate folder of this package (its ``__init__.py`` registers it) and return the registry.
    Folders already imported are not imported again; one added to ``__path__`` since is found."""
    for module in pkgutil.iter_modules(__path__):
        if module.ispkg and not module.name.startswith("_"):
            importlib.import_module(f"{__name__}.{module.name}")
    return SUBSTRATES


def substrate_command(name: str) -> type[SubstrateCommand]:
    """The command registered as ``name``; ``ValueError`` naming ``substrate`` and the choices otherwise."""
    found = discover()
    if name not in found:
        raise ValueError(f"substrate: unknown substrate {name!r}; choose from {sorted(found)}")
    return found[name]


__all__ = ["SUBSTRATES", "SubstrateCommand", "discover", "register_substrate", "substrate_command"]
