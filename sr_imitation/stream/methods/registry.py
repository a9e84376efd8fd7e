"""The method registry: ``--method=<name>`` looks methods up here."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, TypeVar

from sr_imitation.infra.fingerprint import to_jsonable
from sr_imitation.stream.methods.base import ContinualMethod, with_options
from sr_imitation.stream.substrate import MethodSettings

METHODS: dict[str, type[ContinualMethod]] = {}
"""Every registered method by name (filled by :func:`register_method` as the method modules are imported)."""

M = TypeVar("M", bound=type[ContinualMethod])


def register_method(cls: M) -> M:
    """Class decorator: register ``cls`` under ``cls.name`` (names are unique; each method names its substrates)."""
    if not cls.name or not cls.substrates:
        raise TypeError(f"{cls.__name__} must set name and substrates")
    if cls.name in METHODS and METHODS[cls.name] is not cls:
        raise ValueError(f"method {cls.name!r} is registered twice ({METHODS[cls.name].__name__}, {cls.__name__})")
    METHODS[cls.name] = cls
    return cls


def methods_for(substrate: str) -> list[str]:
    """Names of the methods defined on ``substrate``."""
    return sorted(name for name, cls in METHODS.items() if substrate in cls.substrates)


def make_method(name: str, substrate: str, settings: MethodSettings) -> ContinualMethod:
    """The method ``name`` for ``substrate``; a ``ValueError`` naming the valid choices otherwise."""
    cls = METHODS.get(name)
    if cls is None or substrate not in cls.substrates:
        where = "" if cls is None else f" on the {substrate} substrate"
        raise ValueError(f"unknown method {name!r}{where}; choose from {methods_for(substrate)}")
    return cls(settings)


def method_config(name: str, options: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The settings method ``name`` runs with, as JSON data: its ``config`` dataclass's defaults with ``options``
    (``--method_options``) applied; ``{}`` for a method without settings of its own. Runs fingerprint this (key
    ``method_config``), so a changed default in the code (EWC's lambda, ...) refuses a resume or an archived run
    instead of changing results silently. ``ValueError`` naming ``method_options`` for an option the method lacks."""
    cls = METHODS.get(name)
    if cls is None:
        raise ValueError(f"method: unknown method {name!r}; choose from {sorted(METHODS)}")
    config = getattr(cls, "config", None)
    if options:
        config = with_options(name, config, options)
    return to_jsonable(config) if config is not None else {}
