"""Every setting the type it claims: numbers refuse booleans, null and text; booleans refuse numbers."""

from __future__ import annotations

import dataclasses
import functools
import types
import typing
from collections.abc import Mapping, Sequence
from typing import Any

import draccus

NUMBER_KINDS = {int: "an integer", float: "a number"}
"""What a numeric field expects, as the messages say it."""
BOOL_WORDS = ("true", "false")
"""The texts draccus reads as a boolean (YAML 1.2's; ``yes``/``on`` reach it as booleans already)."""


@functools.cache
def field_types(klass: type) -> dict[str, Any]:
    """The resolved annotations of a dataclass's fields (``{}`` if one cannot be resolved: nothing is checked then).

    Args:
        klass: a dataclass.

    Returns:
        Field name -> type.
    """
    try:
        return typing.get_type_hints(klass)
    except Exception:  # noqa: BLE001 (an unresolvable annotation: left to draccus)
        return {}


def _members(tp: Any) -> tuple[list[Any], bool]:
    """The members of a union type (or ``[tp]``) without ``None``, and whether ``None`` is one of them."""
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        return [a for a in args if a is not type(None)], type(None) in args
    return [tp], False


def _dataclass_for(tp: Any, value: Mapping) -> type | None:
    """The dataclass a mapping ``value`` of a field of type ``tp`` is decoded into (a draccus choice type by its
    ``type`` key), or None."""
    for member in _members(tp)[0]:
        if isinstance(member, type) and issubclass(member, draccus.ChoiceRegistry):
            return member.get_known_choices().get(value.get("type")) if isinstance(value.get("type"), str) else None
        if isinstance(member, type) and dataclasses.is_dataclass(member):
            return member
    return None


def _described(value: Any) -> str:
    """``value`` as a message names it: ``true``, ``null``, ``'abc'``, ``2.5``."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if value is None:
        return "null"
    return repr(value) if isinstance(value, str) else str(value)


def _parses_as(text: str, kind: type) -> bool:
    """Whether draccus reads the text ``text`` as a number of ``kind`` (``int``: digits; ``float``: any float)."""
    try:
        kind(text.strip())
    except ValueError:
        return False
    return True


def scalar_problem(value: Any, tp: Any, default: Any = dataclasses.MISSING, text_numbers: bool = True) -> str | None:
    """Why ``value`` is not a value of the field type ``tp`` (a number, a boolean, or either optional), or None if it
    is one, or ``tp`` is none of these (text, paths, lists, unions of other types: draccus' to check).

    A value of the type of the field's ``default`` is always accepted: a default that contradicts its annotation
    (LeRobot's ``replace_final_stride_with_dilation: int = False``, a ``lr: float = None``) says what the field
    really holds, and every stored config holds it.

    Args:
        value: the value as read from JSON or YAML (a flag's text is read as YAML first).
        tp: the field's annotation.
        default: the field's default value (``dataclasses.MISSING``: none, or a factory).
        text_numbers: a number may be given as its text (``'1e-3'``, which YAML 1.1 reads as text and draccus turns
            into the number); False where nothing converts it (``--method_options``).

    Returns:
        ``expects a number, got true``, or None.
    """
    if default is not dataclasses.MISSING and type(value) is type(default):
        return None
    members, optional = _members(tp)
    kinds = set(members)
    if value is None:
        wanted = _wanted(kinds)
        return None if optional or wanted is None else f"expects {wanted}, got null"
    if kinds and kinds <= {int, float}:
        kind = float if float in kinds else int
        text = isinstance(value, str) and _parses_as(value, kind)
        ok = (not isinstance(value, bool) and (isinstance(value, int) or (kind is float and isinstance(value, float)))
              or (text and text_numbers))
        hint = " (read as text: write it with a decimal point, e.g. 1.0e-3)" if text else ""
        return None if ok else f"expects {NUMBER_KINDS[kind]}, got {_described(value)}{hint}"
    if kinds == {bool}:
        ok = isinstance(value, bool) or (isinstance(value, str) and value in BOOL_WORDS)
        return None if ok else f"expects true or false, got {_described(value)}"
    return None


def _wanted(kinds: set[Any]) -> str | None:
    if kinds and kinds <= {int, float}:
        return NUMBER_KINDS[float if float in kinds else int]
    return "true or false" if kinds == {bool} else None


def _element_type(tp: Any) -> Any:
    """The element type of ``list[T]``, ``tuple[T, ...]``, ``Sequence[T]`` (of scalars), else None."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (list, Sequence, typing.Sequence, set, frozenset) and len(args) == 1:
        return args[0]
    if origin is tuple and len(args) == 2 and args[1] is Ellipsis:
        return args[0]
    return None


def value_problems(klass: type, settings: Mapping[str, Any], prefix: str = "", text_numbers: bool = True
                   ) -> list[tuple[str, Any, str]]:
    """Every value of ``settings`` (nested JSON/YAML data for the dataclass ``klass``) whose field is a number or a
    boolean and which is not one (:func:`scalar_problem`), in the data's order; nested dataclasses (draccus choice
    types by their ``type`` key) and lists of numbers or booleans are followed. Keys ``klass`` lacks are left to
    draccus.

    Args:
        klass: the dataclass ``settings`` describe.
        settings: the data.
        prefix: the dotted key of ``settings`` itself (``sleep.``).
        text_numbers: numbers may be given as text (:func:`scalar_problem`).

    Returns:
        ``(key, value, problem)`` of each, keys dotted (``sleep.lr``, ``seeds[1]``).
    """
    hints = field_types(klass)
    defaults = {f.name: f.default for f in dataclasses.fields(klass)} if dataclasses.is_dataclass(klass) else {}
    missing = dataclasses.MISSING
    out: list[tuple[str, Any, str]] = []
    for name, value in settings.items():
        if name not in hints:
            continue
        tp, key = hints[name], f"{prefix}{name}"
        if isinstance(value, Mapping):
            nested = _dataclass_for(tp, value)
            if nested is not None:
                out += value_problems(nested, value, f"{key}.", text_numbers)
            continue
        element = _element_type(_members(tp)[0][0]) if len(_members(tp)[0]) == 1 else None
        if element is not None and isinstance(value, list):
            out += [(f"{key}[{i}]", v, p) for i, v in enumerate(value)
                    if (p := scalar_problem(v, element, text_numbers=text_numbers))]
            continue
        problem = scalar_problem(value, tp, defaults.get(name, missing), text_numbers)
        if problem is not None:
            out.append((key, value, problem))
    return out


def check_settings(klass: type, settings: Mapping[str, Any], where: str, text_numbers: bool = True) -> None:
    """Refuse the first value of ``settings`` that is not the type of its field (:func:`value_problems`).

    Args:
        klass: the dataclass ``settings`` describe.
        settings: nested JSON data (a config file's, ``--method_options``).
        where: what holds them, first in the message (a file's path, ``method_options``).
        text_numbers: numbers may be given as text (:func:`scalar_problem`).

    Raises:
        ValueError: ``<where>: <key>: expects a number, got true`` (one line).
    """
    problems = value_problems(klass, settings, text_numbers=text_numbers)
    if problems:
        key, _, problem = problems[0]
        raise ValueError(f"{where}: {key}: {problem}")


def field_at(klass: type, dotted: str) -> tuple[Any, Any] | None:
    """The type of the field a dotted key (``sleep.lr``) names below the dataclass ``klass``, and its default
    (``dataclasses.MISSING`` if none); None if the key names no field (a section, a choice's ``type``, a key of
    another class).

    Args:
        klass: the command's config dataclass.
        dotted: the flag's name without ``--``.

    Returns:
        ``(type, default)`` or None.
    """
    *path, name = dotted.split(".")
    classes = [klass]
    for part in path:
        classes = [c for k in classes for c in _dataclasses_in(field_types(k).get(part))]
    for k in classes:
        if name in field_types(k) and dataclasses.is_dataclass(k):
            default = next((f.default for f in dataclasses.fields(k) if f.name == name), dataclasses.MISSING)
            return field_types(k)[name], default
    return None


def _dataclasses_in(tp: Any) -> list[type]:
    """Every dataclass a field of type ``tp`` may hold (a choice type's registered classes)."""
    out: list[type] = []
    for member in _members(tp)[0] if tp is not None else []:
        if isinstance(member, type) and issubclass(member, draccus.ChoiceRegistry):
            out += list(member.get_known_choices().values())
        elif isinstance(member, type) and dataclasses.is_dataclass(member):
            out.append(member)
    return out


def flag_problem(klass: type, dotted: str, text: str) -> str | None:
    """Why the flag ``--<dotted>=<text>`` gives its field a value of another type, or None.

    Args:
        klass: the command's config dataclass.
        dotted: the flag's name without ``--`` (``sleep.lr``).
        text: the flag's value as typed; read as draccus reads it (YAML: ``true``, ``null``, ``[1, 2]``).

    Returns:
        ``expects a number, got true``, or None.
    """
    found = field_at(klass, dotted)
    if found is None:
        return None
    tp, default = found
    value = read_flag_value(text)
    element = _element_type(_members(tp)[0][0]) if len(_members(tp)[0]) == 1 else None
    if element is not None and isinstance(value, list):
        return next((f"[{i}] {p}" for i, v in enumerate(value) if (p := scalar_problem(v, element))), None)
    return scalar_problem(value, tp, default)


def read_flag_value(text: str) -> Any:
    """A flag's value as draccus reads it (its YAML parser; the empty text stays text).

    Args:
        text: the value as typed.

    Returns:
        The value (``true`` -> True, ``null`` -> None, ``1e-3`` -> the text ``'1e-3'``, which draccus turns into a
        float); the text itself if it is not valid YAML (draccus reports that).
    """
    from draccus.parsers.config_parsers import YAMLParser  # noqa: PLC0415

    try:
        return YAMLParser.parse_string(text)
    except Exception:  # noqa: BLE001 (invalid YAML: the parser's own error, later, names it)
        return text

