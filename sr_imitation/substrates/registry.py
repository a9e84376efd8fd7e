"""The substrate registry: ``sr-train --substrate=<name>`` looks substrates up here.

A substrate is a folder, ``sr_imitation/substrates/<name>/``, whose ``__init__.py`` registers a
:class:`SubstrateCommand` with :func:`register_substrate`. The package :mod:`sr_imitation.substrates` imports every
such folder (:func:`sr_imitation.substrates.discover`), as :mod:`sr_imitation.stream.methods` imports every method
file, so the folder alone registers the substrate; nothing else lists substrates. A folder's ``__init__.py`` stays
light (no LeRobot, no simulator): the command module it names is imported only when ``sr-train`` runs it, so the ACT
command never imports Meta-World and the SAC command never imports LeRobot's policy registry.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any, ClassVar, TypeVar


class SubstrateCommand:
    """What ``sr-train --substrate=<name>`` runs: two functions of a module imported on use.

    Subclass it in the substrate folder's ``__init__.py``, set :attr:`name` and :attr:`module` (and the function
    names if they are not ``parse`` / ``main``) and decorate the class with :func:`register_substrate`."""

    name: ClassVar[str] = ""
    """``--substrate`` (and a config file's ``substrate`` key); the substrate class's own ``name``."""
    module: ClassVar[str] = ""
    """The module holding the two functions (imported when ``sr-train`` runs the substrate)."""
    parse_function: ClassVar[str] = "parse"
    """``parse(args) -> config``: the run configuration a command line describes, without running it."""
    main_function: ClassVar[str] = "main"
    """``main(args)``: parse the command line and run (or resume) the stream."""

    @classmethod
    def function(cls, which: str) -> Callable[[list[str]], Any]:
        """The module's ``parse`` (``which="parse"``) or ``main`` (``which="main"``) function."""
        attribute = cls.parse_function if which == "parse" else cls.main_function
        return getattr(importlib.import_module(cls.module), attribute)


C = TypeVar("C", bound=type[SubstrateCommand])

SUBSTRATES: dict[str, type[SubstrateCommand]] = {}
"""Every registered substrate by name (filled by :func:`register_substrate` as the substrate folders are imported)."""


def register_substrate[C: type[SubstrateCommand]](cls: C) -> C:
    """Class decorator: register ``cls`` under ``cls.name`` (names are unique)."""
    if not cls.name or not cls.module:
        raise TypeError(f"{cls.__name__} must set name and module")
    if cls.name in SUBSTRATES and SUBSTRATES[cls.name] is not cls:
        raise ValueError(f"substrate {cls.name!r} is registered twice ({SUBSTRATES[cls.name].__name__}, "
                         f"{cls.__name__})")
    SUBSTRATES[cls.name] = cls
    return cls
