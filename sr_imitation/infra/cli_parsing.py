"""The draccus parser of every ``sr-*`` command: a command line that teaches.

* ``--help`` gives every flag a meaning. draccus takes a field's help from the docstring under it, but misses
  some: a docstring whose first line holds one colon reads to it as a field definition, and a class docstring's
  ``Args:`` list shadows the fields it names (its lines look like field definitions too). The help is therefore
  filled in where draccus found none, in this order: :data:`INHERITED_FIELD_HELP` (fields of LeRobot's classes
  that have no, or a wrong, description there), the field's own docstring (read from the source with :mod:`ast`),
  the comment draccus found, and the field's entry in an ``Args:``/``Attributes:`` list of its class's (or a base
  class's) docstring, which is where LeRobot documents ACT's fields.
* A flag the command does not know is one line naming the nearest ones (``did you mean --sleep.anchor_strength?``)
  instead of argparse's usage dump; a flag of another program (LeRobot's ``--steps``, ``--batch_size``) is
  accepted as the flag it maps to or answered with its name here (``names``, e.g.
  :data:`sr_imitation.stream.config.LEROBOT_TRAIN_FLAGS`). Every other usage error argparse finds (a choice
  outside the list, a missing value) is one line too: :class:`~sr_imitation.infra.cli_errors.UsageError`, which
  :func:`~sr_imitation.infra.cli_errors.run_cli` prints with a pointer to ``--help``.
* Every value is the type its field claims, on the command line and in the ``--config_path`` file: a number refuses
  a boolean, null and text that is not a number, a boolean refuses a number (:mod:`sr_imitation.infra.value_types`;
  draccus would take ``--sleep.lr=true`` as 1.0 and ``"max_epochs": true`` as 1), one line naming the key and the
  value, before anything is built.
* Abbreviated flags are refused (argparse would take ``--wake.batch=4`` as ``--wake.batch_size=4``): a prefix of
  a flag is answered like any other unknown flag, with the full name.
"""

from __future__ import annotations

import ast
import copy
import dataclasses
import difflib
import functools
import inspect
import logging
import re
import sys
import textwrap
import types
import typing
from argparse import Namespace
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, NoReturn, TypeVar

import draccus
from draccus import cfgparsing
from draccus import utils as draccus_utils
from draccus.argparsing import ArgumentParser
from draccus.parsers.decoding import decode
from draccus.wrappers import docstring as draccus_docstring

from sr_imitation.infra.cli_errors import UsageError, split_config_path
from sr_imitation.infra.config_file import ConfigFile, config_file
from sr_imitation.infra.value_types import check_settings, flag_problem

logger = logging.getLogger(__name__)

T = TypeVar("T")

HELP_FLAGS = ("-h", "--help")

INHERITED_FIELD_HELP: dict[str, str] = {
    "PreTrainedConfig.repo_id": "Hugging Face Hub repository (<user>/<name>) that --policy.push_to_hub=true pushes "
                                "the policy to.",
    "PreTrainedConfig.license": "License written into the model card of a policy pushed to the Hub (LeRobot's "
                                "default apache-2.0).",
}
"""``<class>.<field>`` -> help, for fields of classes this project cannot edit (LeRobot's ``PreTrainedConfig``)
that have no description there (``repo_id``) or a wrong one (``license`` carries the comment of ``tags``). It wins
over everything else found for that class's field; a subclass's own docstring of the field wins over it."""

ARGS_SECTION = re.compile(r"^(Args|Arguments|Attributes)\b[^:]*:\s*$")
"""The heading of a Google-style list of fields in a class docstring (``Args:``, ``Args (beyond ACT's):``)."""
ARGS_ENTRY = re.compile(r"^([A-Za-z_][\w ,/]*?)\s*:\s*(.*)$")
"""One entry of that list: ``name: text``, or several names (``e_min, e_max: ...``, ``a / b: ...``)."""


@functools.cache
def _attribute_docstring(klass: type, field_name: str) -> Any:
    return _DRACCUS_ATTRIBUTE_DOCSTRING(klass, field_name)


def _memoized_attribute_docstring(klass: type, field_name: str) -> Any:
    """draccus' ``get_attribute_docstring``, read once a process per (class, field) (our choice, for speed): draccus
    reads and tokenizes the whole source of a field's class again for every field at every parse, about 1.4 s of
    each 1.5 s ``sr-train`` parse on a 2-core CPU (``python -m sr_imitation.benchmarks.cli_parse``). A class's
    source does not change while a process runs; each caller gets its own copy of the record."""
    return dataclasses.replace(_attribute_docstring(klass, field_name))


_DRACCUS_ATTRIBUTE_DOCSTRING = draccus_docstring.get_attribute_docstring
draccus_docstring.get_attribute_docstring = _memoized_attribute_docstring  # every draccus wrapper calls it through here


def wants_help(args: Sequence[str]) -> bool:
    """Whether a command line asks for ``--help`` (draccus' rule: the token itself, anywhere)."""
    return any(arg in HELP_FLAGS for arg in args)


def _raise_usage_error(message: str) -> NoReturn:
    """argparse's ``error`` (normally: usage, message, exit 2), as an exception ``run_cli`` prints on one line."""
    raise UsageError(message)


class SettingsParser(ArgumentParser):
    """draccus' parser given a config file's settings as parsed (:mod:`sr_imitation.infra.config_file`), where
    draccus' own takes a path and opens the file itself; the command line's flags override them as they would
    draccus' file."""

    def __init__(self, *args: Any, settings: Mapping[str, Any] | None = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.settings = settings

    def _postprocessing(self, parsed_args: Namespace) -> Any:
        """draccus' (0.11) ``ArgumentParser._postprocessing`` with :attr:`settings` in place of its config file:
        each flag's value read as YAML (``include <file>`` as that file's settings), the dotted flags nested and merged
        over the settings, the whole decoded into the config class."""
        values = vars(parsed_args)
        if values.pop(draccus_utils.CONFIG_ARG, None) is not None:
            raise UsageError("--config_path is given twice; give it once")
        for key, raw in values.items():
            value = cfgparsing.parse_string(raw)
            if isinstance(value, str) and value.startswith("include"):
                with open(value[len("include "):], encoding="utf-8") as f:  # noqa: PTH123 (draccus' own keyword)
                    value = cfgparsing.load_config(f)
            values[key] = value
        flags = draccus_utils.deflatten(values, sep=".")
        return decode(self.config_class, merged(copy.deepcopy(dict(self.settings or {})), flags))  # decode consumes it


def merged(settings: Mapping[str, Any], flags: Mapping[str, Any]) -> dict[str, Any]:
    """``settings`` with ``flags`` (nested the same way) over them: a section both have is merged key by key, any
    other value of ``flags`` replaces the setting's (draccus' merge of a file and the flags)."""
    out = dict(settings)
    for key, value in flags.items():
        below = out.get(key)
        out[key] = merged(below, value) if isinstance(below, Mapping) and isinstance(value, Mapping) else value
    return out


def command_parser(cls: type, *, prog: str, settings: Mapping[str, Any] | None = None,
                   field_help: Mapping[str, str] = INHERITED_FIELD_HELP) -> ArgumentParser:
    """draccus' parser of ``cls`` for the command ``prog`` (``settings``: a config file's, which the flags override),
    with the help of every flag filled in (module docstring) and argparse's usage errors raised as
    :class:`UsageError`. A config holding an ACT-SR policy must be built inside
    :func:`sr_imitation.substrates.act.cli.act_sr_choices_only`."""
    parser = SettingsParser(cls, settings=settings, prog=prog, allow_abbrev=False)
    parser.parser.error = _raise_usage_error  # type: ignore[method-assign]
    fill_help(parser, cls, field_help)
    return parser


def option_names(parser: ArgumentParser, prefix: str = "") -> list[str]:
    """The ``--`` flags ``parser`` takes; with ``prefix`` (``"train."``) only those under it, without it."""
    names = [s for action in parser.parser._actions for s in action.option_strings if s.startswith("--")]
    if not prefix:
        return names
    return [f"--{s[2 + len(prefix):]}" for s in names if s.startswith(f"--{prefix}")]


def nearest_flags(name: str, known: Sequence[str]) -> list[str]:
    """The flags of ``known`` that ``name`` most likely meant: up to three with the same last part, least nested first
    (``--batch_size`` -> ``--sac.batch_size``, ``--sleep.batch_size``), else the one closest in spelling
    (``--sleep.anchor_strenght`` -> ``--sleep.anchor_strength``). A section's own flag (``--sleep``, which takes a
    config file) is never proposed."""
    flags = [k for k in known if k != name and not any(other.startswith(f"{k}.") for other in known)]
    last = name.rsplit(".", 1)[-1].lstrip("-")
    same_last = sorted((k for k in flags if k.rsplit(".", 1)[-1].lstrip("-") == last),
                       key=lambda k: (k.count("."), len(k)))
    return same_last[:3] or difflib.get_close_matches(name, flags, n=1, cutoff=0.75)


def _flag_tokens(args: Sequence[str]) -> list[tuple[int, str, str | None]]:
    """``(index, --name, value)`` of each ``--flag`` token (value: after ``=``, else the next token unless it is a
    flag, else ``None``); scanning stops at a bare ``--``."""
    out = []
    for i, arg in enumerate(args):
        if arg == "--":
            break
        if not arg.startswith("--"):
            continue
        name, sep, value = arg.partition("=")
        if not sep:
            value = args[i + 1] if i + 1 < len(args) and not args[i + 1].startswith("--") else None
        out.append((i, name, value))
    return out


def apply_flag_names(args: Sequence[str], known: Sequence[str], names: Mapping[str, str], prog: str) -> list[str]:
    """``args`` with every flag of ``names`` that ``prog`` does not know itself replaced by the flag it maps to (a
    value of ``names`` that is one ``--flag``), or a :class:`UsageError` with its answer (any other value; ``{value}``
    in it is the value given). A mapped flag given together with its target is refused, naming both."""
    out = list(args)
    tokens = _flag_tokens(out)
    given = {name for _, name, _ in tokens}
    for i, name, value in tokens:
        if name in known or name not in names:
            continue
        target = names[name]
        if re.fullmatch(r"--[\w.]+", target) and target in known:
            if target in given:
                raise UsageError(f"{name} is {target} on {prog}, and both are given; give one of them")
            out[i] = target + out[i][len(name):]
            logger.info("%s is %s on %s", name, target, prog)
            continue
        raise UsageError(f"{prog} has no {name}: {target.replace('{value}', value or '<value>')}")
    return out


def take_flag(args: list[str], flag: str) -> tuple[list[str], str | None]:
    """``args`` without ``flag`` (``--flag=value`` or ``--flag value``, read as :func:`_flag_tokens` reads every flag)
    and its last value (None if not given; a ``flag`` without a value stays, for the parser to refuse)."""
    drop: set[int] = set()
    value = None
    for i, name, given in _flag_tokens(args):
        if name == flag and given is not None:
            value = given
            drop.update((i,) if "=" in args[i] else (i, i + 1))
    return [arg for j, arg in enumerate(args) if j not in drop], value


def check_flags_known(args: Sequence[str], known: Sequence[str]) -> None:
    """A :class:`UsageError` naming the first flag of ``args`` that is not in ``known``, with the nearest ones."""
    known_set = set(known)
    for _, name, _ in _flag_tokens(args):
        if name in known_set:
            continue
        near = nearest_flags(name, known)
        hint = f"; did you mean {', '.join(near[:-1])} or {near[-1]}?" if len(near) > 1 else ""
        hint = f"; did you mean {near[0]}?" if len(near) == 1 else hint
        raise UsageError(f"unknown flag {name}{hint}")


def parse_command[T](cls: type[T], args: Sequence[str] | None, *, prog: str,
                  config_path: str | Path | ConfigFile | None = None, prefix: str = "",
                  names: Mapping[str, str] | None = None, notes: Mapping[str, str] | None = None,
                  help_values: tuple[str, Mapping] | None = None) -> T:
    """``draccus.parse`` of ``cls`` for the command ``prog`` (module docstring): ``--help`` prints every flag's
    meaning and exits 0, with the values of the ``--config_path`` file as the defaults it shows (or of
    ``help_values``: (where they come from, the settings), e.g. a preset's ``train`` section); flags of ``names`` are
    mapped or answered (:func:`apply_flag_names`); an unknown flag is a :class:`UsageError` naming the nearest ones;
    any other argparse error is a :class:`UsageError` too, with the sentence ``notes`` holds for its flag appended
    (``--policy.type``: what the command trains).

    ``args`` None: ``sys.argv[1:]``. ``config_path``: the config file, read or to read
    (:func:`~sr_imitation.infra.config_file.config_file`); without it, a ``--config_path`` of ``args``. draccus gets
    its settings, not its path. ``prefix`` (``"train."``) parses ``args`` as flags of the section ``prefix`` names
    (``--seed=1`` is ``--train.seed=1``); errors name the flags as given."""
    args = list(sys.argv[1:] if args is None else args)
    if config_path is None:
        config_path, args = split_config_path(args)
    config = config_file(config_path)
    settings = None if config is None else config.settings
    parser = command_parser(cls, prog=prog, settings=settings)
    if wants_help(args):
        if help_values is None and config is not None:
            help_values = (str(config.path), config.settings)
        if help_values is not None:
            show_values_as_defaults(parser, *help_values)
        parser.parse_args(["--help"])  # prints the help and exits 0
    known = option_names(parser, prefix)
    args = apply_flag_names(args, known, names or {}, prog)
    check_flags_known(args, known)
    check_flag_types(cls, args, prefix)
    if config is not None:
        check_settings(cls, config.settings, str(config.path))
    full = [f"--{prefix}{a[2:]}" if prefix and a.startswith("--") and a != "--" else a for a in args]
    full = keep_text_verbatim(cls, full)
    try:
        return parser.parse_args(full)
    except UsageError as exc:
        message = str(exc).replace(f"--{prefix}", "--") if prefix else str(exc)
        for flag, note in (notes or {}).items():
            if message.startswith(f"argument {flag}:"):
                message = f"{message}; {note}"
        raise UsageError(message) from None


def check_flag_types(cls: type, args: Sequence[str], prefix: str = "") -> None:
    """A :class:`UsageError` naming the first flag of ``args`` whose value is not the type of its field: a number
    given a boolean, null or text, a boolean given a number (:func:`~sr_imitation.infra.value_types.flag_problem`;
    draccus would take ``--sleep.lr=true`` as 1.0). Flags are named as given (``prefix``: as in
    :func:`parse_command`).

    Args:
        cls: the command's config dataclass.
        args: the command line.
        prefix: the section the flags address (``train.``), or "".
    """
    for _, name, value in _flag_tokens(args):
        if value is None or name == "--config_path":
            continue
        problem = flag_problem(cls, f"{prefix}{name[2:]}", value)
        if problem is not None:
            raise UsageError(f"{name[2:]}: {problem} ({name}={value})")


_YAML_SHAPED = re.compile(r"^\s*[\[{#&*!|>%@`-]|: |:$| #")
"""What YAML reads as other than the plain text: a list or mapping (flow or block), ``key: value``, a comment, an
anchor, alias, tag, block scalar or directive (YAML's indicator characters at the start)."""


def keep_text_verbatim(cls: type, args: Sequence[str]) -> list[str]:
    """``args`` with the value of every flag of a text field (``str`` or ``str | None``) that YAML would read as other
    than its text (``--note=a: b`` is the mapping ``{a: b}`` to draccus, stored as the text ``"{'a': 'b'}"``) quoted,
    so the field holds what was typed. Values already quoted, and every other field, are left to draccus."""
    out = list(args)
    for i, name, value in _flag_tokens(out):
        if value is None or value[:1] in ("'", '"') or not _YAML_SHAPED.search(value):
            continue
        found = _field_class(cls, name[2:])
        if found is None or _field_types(found[0]).get(found[1]) not in (str, str | None):
            continue
        quoted = "'" + value.replace("'", "''") + "'"
        if "=" in out[i]:
            out[i] = f"{name}={quoted}"
        else:
            out[i + 1] = quoted
    return out


def show_values_as_defaults(parser: ArgumentParser, source: str, values: Mapping) -> int:
    """Make ``parser``'s help show, as each flag's default, the value ``values`` (a config file's nested settings)
    gives it, and say so under the usage line; returns how many flags took a value. Only for ``--help``: the parse
    itself hands draccus the settings (:class:`SettingsParser`)."""
    count = 0
    for action in parser.parser._actions:
        node: Any = values
        for part in action.dest.split("."):
            node = node.get(part, _ABSENT) if isinstance(node, Mapping) else _ABSENT
        if node is _ABSENT or isinstance(node, Mapping) or not action.option_strings or action.dest == "config_path":
            continue
        action.default = node
        count += 1
    note = f"Defaults shown are the values of {source} ({count} settings); the others are the code's defaults."
    parser.parser.description = f"{parser.parser.description or ''}\n\n{note}".strip()
    return count


_ABSENT = object()


# --- help ------------------------------------------------------------------------------------------------------------

def fill_help(parser: ArgumentParser, cls: type, field_help: Mapping[str, str] = INHERITED_FIELD_HELP) -> None:
    """Give every flag of ``parser`` (built from ``cls``) the help the module docstring describes."""
    for action in parser.parser._actions:
        if not action.option_strings or action.dest in ("help", "config_path"):
            continue
        found = _field_class(cls, action.dest)
        if found is None:
            continue  # a section's own flag (``--policy``: "Config file for policy")
        klass, name = found
        drawn = action.help if isinstance(action.help, str) and action.help.strip() else None
        text = _own_help(klass, name, field_help)
        if text is None and drawn is None:
            text = _args_entry_help(klass, name)
        if text is not None:
            action.help = " ".join(text.split()).replace("%", "%%")


def _field_class(cls: type, dest: str) -> tuple[type, str] | None:
    """The dataclass (and field name) behind a flag's ``dest`` (``policy.dim_model``), following nested dataclasses,
    optional ones and draccus choice types (their registered classes)."""
    *path, name = dest.split(".")
    classes = [cls]
    for part in path:
        classes = [c for klass in classes for c in _dataclasses_in(_field_types(klass).get(part))]
    for klass in classes:
        if any(f.name == name for f in dataclasses.fields(klass)):
            return klass, name
    return None


@functools.cache
def _field_types(klass: type) -> dict[str, Any]:
    try:
        return typing.get_type_hints(klass)
    except Exception:  # noqa: BLE001 (an unresolvable annotation: no help from here, draccus' stays)
        return {}


def _dataclasses_in(tp: Any) -> list[type]:
    if isinstance(tp, type) and issubclass(tp, draccus.ChoiceRegistry):
        return list(tp.get_known_choices().values())
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):
        return [tp]
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        return [c for arg in typing.get_args(tp) for c in _dataclasses_in(arg)]
    return []


def _own_help(klass: type, name: str, field_help: Mapping[str, str]) -> str | None:
    """The field's docstring, or its :data:`INHERITED_FIELD_HELP` entry, from the nearest class that declares it."""
    for base in klass.__mro__:
        if name not in base.__dict__.get("__annotations__", {}):
            continue
        doc = _field_docstrings(base).get(name)
        if doc:
            return doc
        if f"{base.__name__}.{name}" in field_help:
            return field_help[f"{base.__name__}.{name}"]
    return None


def _args_entry_help(klass: type, name: str) -> str | None:
    for base in klass.__mro__:
        doc = _docstring_args(base).get(name)
        if doc:
            return doc
    return None


@functools.cache
def _field_docstrings(klass: type) -> dict[str, str]:
    """Field name -> the string literal right under its annotation in ``klass``'s own source."""
    try:
        tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
    except (OSError, TypeError, SyntaxError):
        return {}
    node = next((n for n in tree.body if isinstance(n, ast.ClassDef)), None)
    if node is None:
        return {}
    out = {}
    for stmt, after in zip(node.body, node.body[1:], strict=False):
        if (isinstance(stmt, ast.AnnAssign) and isinstance(stmt.target, ast.Name) and isinstance(after, ast.Expr)
                and isinstance(after.value, ast.Constant) and isinstance(after.value.value, str)):
            out[stmt.target.id] = inspect.cleandoc(after.value.value)
    return out


@functools.cache
def _docstring_args(klass: type) -> dict[str, str]:
    """Field name -> its entry in the ``Args:``/``Attributes:`` lists of ``klass``'s own docstring."""
    doc = klass.__dict__.get("__doc__")
    if not isinstance(doc, str):
        return {}
    out: dict[str, str] = {}
    names: list[str] = []
    entry_indent = None
    in_section = False
    for line in inspect.cleandoc(doc).splitlines():
        indent, text = len(line) - len(line.lstrip()), line.strip()
        if ARGS_SECTION.match(text):
            in_section, entry_indent, names = True, None, []
            continue
        if not in_section or not text:
            continue
        if entry_indent is None:
            entry_indent = indent
        if indent < entry_indent:
            in_section = False
            continue
        match = ARGS_ENTRY.match(text) if indent == entry_indent else None
        if match:
            names = [n.strip() for n in re.split(r"[,/]", match.group(1)) if n.strip()]
            for n in names:
                out[n] = match.group(2)
        else:
            for n in names:
                out[n] = f"{out[n]} {text}"
    return out
