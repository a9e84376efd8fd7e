"""The method registry: ``--method=<name>`` looks methods up here.

Which methods run on a substrate follows from what each method asks (:attr:`ContinualMethod.requires`, the wake
hooks it overrides, and an explicit :attr:`ContinualMethod.substrates` where a comparison restricts it) and what the
substrate provides, so a new substrate gets every method it can run without any method file changing.
"""

from __future__ import annotations

import dataclasses
import importlib
import json
import pkgutil
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any, TypeVar

from sr_imitation.infra.cli_parsing import take_flag
from sr_imitation.infra.fingerprint import to_jsonable
from sr_imitation.stream.capabilities import missing_capabilities
from sr_imitation.stream.methods.base import ContinualMethod, with_options
from sr_imitation.stream.substrate import MethodSettings

METHODS: dict[str, type[ContinualMethod]] = {}
"""Every registered method by name (filled by :func:`register_method` as the method modules are imported)."""

M = TypeVar("M", bound=type[ContinualMethod])


def register_method[M: type[ContinualMethod]](cls: M) -> M:
    """Class decorator: register ``cls`` under ``cls.name`` (names are unique)."""
    if not cls.name:
        raise TypeError(f"{cls.__name__} must set name")
    if cls.name in METHODS and METHODS[cls.name] is not cls:
        raise ValueError(f"method {cls.name!r} is registered twice ({METHODS[cls.name].__name__}, {cls.__name__})")
    METHODS[cls.name] = cls
    return cls


def import_method_files(package: str, path: Iterable[str], skip: Iterable[str] = ()) -> None:
    """Import every module of a methods folder (``package``, its ``__path__``) whose name does not start with ``_``
    and is not in ``skip``: each registers its methods. The substrate-free methods (:mod:`sr_imitation.stream.methods`)
    and a substrate's own (``sr_imitation/substrates/<name>/methods/``) are found so."""
    for module in pkgutil.iter_modules(list(path)):
        if not module.name.startswith("_") and module.name not in set(skip):
            importlib.import_module(f"{package}.{module.name}")


def method_class(name: str, substrate: str | None = None) -> type[ContinualMethod]:
    """The method registered as ``name``; with ``substrate`` (a substrate's name), also refused when the method is
    restricted to other substrates. ``ValueError`` naming ``method`` and the choices otherwise. What the substrate
    must provide is checked once the substrate exists (:func:`make_method`)."""
    cls = METHODS.get(name)
    if cls is None:
        raise ValueError(f"method: unknown method {name!r}; choose from {sorted(METHODS)}")
    if substrate is not None and cls.substrates is not None and substrate not in cls.substrates:
        open_here = sorted(n for n, c in METHODS.items() if c.substrates is None or substrate in c.substrates)
        raise ValueError(f"method: {_restricted(cls, substrate)}; choose from {open_here}")
    return cls


def refusal(method: type[ContinualMethod] | ContinualMethod, substrate: Any) -> str | None:
    """Why ``method`` (a class or an instance) cannot run on ``substrate`` (a substrate instance or class), in one
    sentence that begins with the method's quoted name; ``None`` when it can."""
    cls = method if isinstance(method, type) else type(method)
    if cls.substrates is not None and substrate.name not in cls.substrates:
        return _restricted(cls, substrate.name)
    lacking = missing_capabilities(substrate, method.requires)  # an instance's: its options may add some
    if lacking:
        return (f"{cls.name!r} needs a substrate with {', '.join(lacking)} (sr_imitation.stream.capabilities); "
                f"the {substrate.name} substrate does not provide it")
    hooks = sorted(cls.wake_hooks_used() - set(substrate.wake_hooks))
    if hooks:
        return (f"{cls.name!r} needs the wake hooks {hooks}; the {substrate.name} substrate's wake does not "
                "call them")
    return None


def _restricted(cls: type[ContinualMethod], substrate: str) -> str:
    return (f"{cls.name!r} is compared on the {', '.join(sorted(cls.substrates or ()))} substrate only, "
            f"not on {substrate}")


def methods_for(substrate: Any) -> list[str]:
    """Names of the methods that run on ``substrate`` (a substrate instance or class)."""
    return sorted(name for name, cls in METHODS.items() if refusal(cls, substrate) is None)


def check_method(name: str, substrate: Any) -> type[ContinualMethod]:
    """The method registered as ``name`` if it runs on ``substrate`` (a substrate instance or class); a one-line
    ``ValueError`` naming ``method``, why, and the methods that run on the substrate otherwise."""
    cls = method_class(name)
    reason = refusal(cls, substrate)
    if reason is not None:
        raise ValueError(f"method: {reason}; choose from {methods_for(substrate)}")
    return cls


def make_method(name: str, substrate: Any, settings: MethodSettings,
                options: Mapping[str, Any] | None = None) -> ContinualMethod:
    """The method ``name`` for ``substrate`` (a substrate instance or class), refused as :func:`check_method`
    says.

    Args:
        name: the registry name (``--method``).
        substrate: the substrate it runs on (instance or class).
        settings: what the substrate tells methods (``substrate.method_settings()``).
        options: ``--method_options``, straight from the run's configuration (they replace ``settings.options``;
            ``None`` keeps those).

    Returns:
        The method, its ``config`` with the options applied.
    """
    if options is not None:
        settings = dataclasses.replace(settings, options=dict(options))
    return check_method(name, substrate)(settings)


def method_config(name: str, options: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The settings method ``name`` runs with, as JSON data: its ``config`` dataclass's defaults with ``options``
    (``--method_options``) applied; ``{}`` for a method without settings of its own. Runs fingerprint this (key
    ``method_config``), so a changed default in the code (EWC's lambda, ...) refuses a resume or an archived run
    instead of changing results silently. ``ValueError`` naming ``method_options`` for an option the method lacks."""
    config = getattr(method_class(name), "config", None)
    if options:
        config = with_options(name, config, options)
    return to_jsonable(config) if config is not None else {}


def replaced_setting_refusal(name: str, args: Sequence[str], prefix: str = "") -> str | None:
    """Why a command line may not give a shared setting that method ``name`` replaces (its
    :attr:`~ContinualMethod.own_settings` and :attr:`~ContinualMethod.fixed_settings`), in one line naming the flag
    and the method option to give instead; ``None`` when it gives none (or ``name`` is not a registered method).

    Args:
        name: the run's method (``--method``, else its config file's).
        args: the command line's flags (a config file's values: :func:`replaced_key_refusal`).
        prefix: where the run's settings sit on this command line (``train.`` for ``sr-main``).

    Returns:
        The refusal, or ``None``.
    """
    found = _first_replaced(name, lambda setting: _flag_value(args, f"--{prefix}{setting}"))
    if found is None:
        return None
    cls, setting, option, value = found
    if option is None:
        return f"--{prefix}{setting}: {name} fixes it at {value!r} whatever the flag says; leave the flag out"
    return (f"--{prefix}{setting}: {name} sets it with its own option {option!r} (default "
            f"{getattr(cls.config, option)}); use --{prefix}method_options={{{option}: {value}}}")


def replaced_key_refusal(name: str, settings: Mapping[str, Any], source: str, prefix: str = "") -> str | None:
    """:func:`replaced_setting_refusal` for a config file's keys: why a file written for method ``name`` may not set
    a shared setting the method replaces, in one line naming the file, the key and the method option to set instead;
    ``None`` when it sets none. Call it only for a file a person wrote that names ``name`` as its method: a preset
    that names another method (or none) is shared by every method, and a run's own ``train_config.json`` holds
    every setting.

    Args:
        name: the run's method (the file's).
        settings: the run's settings in the file (an ``sr-main`` preset's ``train`` section).
        source: the file, as errors name it.
        prefix: where the run's settings sit in the file (``train.`` for an ``sr-main`` preset).

    Returns:
        The refusal, or ``None``.
    """
    found = _first_replaced(name, lambda setting: _nested(settings, setting))
    if found is None:
        return None
    cls, setting, option, value = found
    if option is None:
        return f"{source}: {prefix}{setting}: {name} fixes it at {value!r} whatever the file says; leave it out"
    return (f"{source}: {prefix}{setting}: {name} sets it with its own option {option!r} (default "
            f"{getattr(cls.config, option)}); set \"{prefix}method_options\": "
            f"{{\"{option}\": {json.dumps(value)}}} instead")


def _first_replaced(name: str, given: Callable[[str], Any]) -> tuple[type, str, str | None, Any] | None:
    """The first shared setting method ``name`` replaces that ``given`` finds a value for (:data:`_ABSENT`: not
    given).

    Returns:
        ``(the method's class, the setting, the method option that sets it or None where the method fixes it, the
        value given, or for a fixed setting the value the method fixes)``; ``None`` when none is given or ``name`` is
        not a registered method.
    """
    cls = METHODS.get(name)
    if cls is None:
        return None
    for setting, option in cls.own_settings.items():
        value = given(setting)
        if value is not _ABSENT:
            return cls, setting, option, value
    for setting, fixed in cls.fixed_settings.items():
        if given(setting) is not _ABSENT:
            return cls, setting, None, fixed
    return None


_ABSENT = object()


def _flag_value(args: Sequence[str], flag: str) -> Any:
    """The value ``flag`` has on the command line ``args``, or :data:`_ABSENT`."""
    value = take_flag(list(args), flag)[1]
    return _ABSENT if value is None else value


def _nested(settings: Mapping[str, Any], dotted: str) -> Any:
    """The value at ``dotted`` (``sleep.max_iterations``) in nested ``settings``, or :data:`_ABSENT`."""
    node: Any = settings
    for part in dotted.split("."):
        node = node.get(part, _ABSENT) if isinstance(node, Mapping) else _ABSENT
    return node
