"""``sr-train``: one command for every substrate.

    sr-train --config_path=configs/needle_cpu.json                    # ACT-SR on the needle stream (substrate act)
    sr-train --config_path=configs/sac_mt5_cpu.json --seed=1          # SAC on Meta-World MT5 (the file says sac)
    sr-train --substrate=sac --stream.name=mt5 --sleep.enabled=false  # flags alone; SR wake-only
    sr-train --config_path=outputs/run1/train_config.json --resume=true  # any run, wherever it was copied
    sr-train --substrate=sac --help                                   # the SAC substrate's flags

The substrate comes from ``--substrate=<name>``, else from the config file's ``substrate`` key (a run's stored
config always has it; an ``sr-main`` preset's under ``train``), else ``act``. Shared concepts have the same flags
on every substrate (:mod:`sr_imitation.stream.config`); a flag of an earlier version is answered with its new name.
``sr-rl-train`` is ``sr-train --substrate=sac``.

Substrates are folders of :mod:`sr_imitation.substrates`, each registering its command
(:mod:`sr_imitation.substrates.registry`); this module lists none. A substrate's command module is imported only
when it runs, so the ACT command never imports Meta-World and the SAC command never imports LeRobot's policy registry.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from sr_imitation.infra.cli_errors import check_config_file, run_cli, split_config_path
from sr_imitation.infra.cli_parsing import take_flag
from sr_imitation.stream.config import RunConfig, renamed_flag_hint, renamed_key_hint
from sr_imitation.stream.methods import replaced_setting_refusal
from sr_imitation.substrates import substrate_command

DEFAULT_SUBSTRATE = "act"
"""The substrate of a command line that names none (nor does its config file)."""


def substrate_of(args: list[str], config: object = None) -> str:
    """The substrate a command line asks for (see the module docstring); ``config`` is the ``--config_path`` file's
    JSON when the caller has read it already. Raises ``ValueError`` naming the choices."""
    name = None
    for arg in args:
        if arg.startswith("--substrate="):
            name = arg.split("=", 1)[1]
    if name is None:
        if config is None:
            config_path, _ = split_config_path(args)
            config = _read_config(config_path) if config_path else None
        name = _config_substrate(config)
    name = name or DEFAULT_SUBSTRATE
    substrate_command(name)  # a one-line ValueError naming the registered substrates
    return name


def _read_config(config_path: str) -> object:
    try:
        return json.loads(Path(config_path).read_text())
    except (OSError, json.JSONDecodeError):
        return None  # the substrate's parser reports the file


def _config_substrate(data: object) -> str | None:
    """The ``substrate`` key of a config file's JSON (an ``sr-main`` preset's under ``train``)."""
    return _config_key(data, "substrate")


def _config_key(data: object, key: str) -> str | None:
    """The text under ``key`` in a config file's JSON (an ``sr-main`` preset's under ``train``), or ``None``."""
    if not isinstance(data, dict):
        return None
    train = data.get("train") if isinstance(data.get("train"), dict) else {}
    found = data.get(key, train.get(key))
    return found if isinstance(found, str) else None


def method_of(args: list[str], config: object = None) -> str:
    """The method a command line asks for: ``--method``, else its config file's (``config``, the JSON), else the
    default (:class:`~sr_imitation.stream.config.RunConfig`'s)."""
    return take_flag(list(args), "--method")[1] or _config_key(config, "method") or RunConfig.method


def check_replaced_settings(args: list[str], config: object = None) -> None:
    """One-line ``ValueError`` for a flag of a shared setting that the run's method replaces with an option of its
    own (``--method=reset_distill --sleep.max_iterations=3``: the method's ``iterations``), before anything is
    parsed or written; the rule for every method (docs/ARCHITECTURE.md, "Adding a method")."""
    refusal = replaced_setting_refusal(method_of(args, config), args)
    if refusal is not None:
        raise ValueError(refusal)


def _function(args: list[str], which: str) -> Callable[[list[str]], Any]:
    hint = renamed_flag_hint(args)
    if hint is not None:
        raise ValueError(hint)
    config_path, _ = split_config_path(args)
    config = check_config_file(config_path)
    hint = renamed_key_hint(config)
    if hint is not None:
        raise ValueError(f"{config_path}: {hint}")
    check_replaced_settings(args, config)
    return substrate_command(substrate_of(args, config)).function(which)


def parse_args(args: list[str]) -> Any:
    """The run configuration a command line describes (its substrate's config class), without running it."""
    return _function(args, "parse")(args)


def train_main(args: list[str] | None = None) -> Any:
    """Run (or resume) a stream on the substrate the command line names."""
    args = list(sys.argv[1:] if args is None else args)
    return _function(args, "main")(args)


def train_entry() -> None:
    """Console script ``sr-train`` (one-line user errors; ``--debug`` for tracebacks)."""
    run_cli("sr-train", train_main)


def rl_train_entry() -> None:
    """Console script ``sr-rl-train``: ``sr-train --substrate=sac``."""
    run_cli("sr-rl-train", lambda args: train_main(["--substrate=sac", *args]))


if __name__ == "__main__":
    train_entry()
