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

The ``--config_path`` file is read once, here (:func:`~sr_imitation.infra.config_file.read_config_file`), and the
substrate's parser is handed that reading (:func:`~sr_imitation.infra.config_file.config_scope`).

Substrates are folders of :mod:`sr_imitation.substrates`, each registering its command
(:mod:`sr_imitation.substrates.registry`); this module lists none. A substrate's command module is imported only
when it runs, so the ACT command never imports Meta-World and the SAC command never imports LeRobot's policy registry.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from typing import Any

from sr_imitation.infra.cli_errors import run_cli
from sr_imitation.infra.cli_parsing import take_flag
from sr_imitation.infra.config_file import ConfigFile, config_scope, split_config
from sr_imitation.stream.config import RunConfig, renamed_flag_hint, renamed_key_hint
from sr_imitation.stream.methods import replaced_key_refusal, replaced_setting_refusal
from sr_imitation.substrates import substrate_command

DEFAULT_SUBSTRATE = "act"
"""The substrate of a command line that names none (nor does its config file)."""


def substrate_of(args: list[str], config: ConfigFile | None = None) -> str:
    """The substrate a command line asks for (see the module docstring); ``config`` is its ``--config_path`` file
    when the caller has read it already. Raises ``ValueError`` naming the choices."""
    name = None
    for arg in args:
        if arg.startswith("--substrate="):
            name = arg.split("=", 1)[1]
    if name is None:
        if config is None:
            config, _ = split_config(args)
        name = _config_key(config, "substrate")
    name = name or DEFAULT_SUBSTRATE
    substrate_command(name)  # a one-line ValueError naming the registered substrates
    return name


def _config_key(config: ConfigFile | None, key: str) -> str | None:
    """The text under ``key`` in a config file (an ``sr-main`` preset's under ``train``), or ``None``."""
    if config is None:
        return None
    data = config.settings
    train = data.get("train") if isinstance(data.get("train"), dict) else {}
    found = data.get(key, train.get(key))
    return found if isinstance(found, str) else None


def method_of(args: list[str], config: ConfigFile | None = None) -> str:
    """The method a command line asks for: ``--method``, else its config file's (``config``), else the default
    (:class:`~sr_imitation.stream.config.RunConfig`'s)."""
    return take_flag(list(args), "--method")[1] or _config_key(config, "method") or RunConfig.method


def check_replaced_settings(args: list[str], config: ConfigFile | None = None) -> None:
    """One-line ``ValueError`` for a shared setting that the run's method replaces with an option of its own
    (``--method=reset_distill --sleep.max_iterations=3``: the method's ``iterations``), before anything is parsed or
    written: given as a flag, or set in a config file a person wrote for that method (one that names it as its
    ``method``; a preset of another method, or of none, is every method's, and a run's own ``train_config.json``
    holds every setting); the rule for every method (docs/ARCHITECTURE.md, "Adding a method")."""
    method = method_of(args, config)
    refusal = replaced_setting_refusal(method, args)
    if refusal is None and config is not None and not config.sealed and _config_key(config, "method") == method:
        prefix = "train." if config.is_main_job_preset else ""
        refusal = replaced_key_refusal(method, config.run_settings, str(config.path), prefix)
    if refusal is not None:
        raise ValueError(refusal)


def _function(args: list[str], which: str) -> Callable[[list[str]], Any]:
    """The substrate's ``parse`` or ``main`` for ``args``, run with the ``--config_path`` file read here (once)."""
    hint = renamed_flag_hint(args)
    if hint is not None:
        raise ValueError(hint)
    config, _ = split_config(args)
    hint = renamed_key_hint(None if config is None else config.settings)
    if hint is not None:
        raise ValueError(f"{config.path}: {hint}")
    check_replaced_settings(args, config)
    function = substrate_command(substrate_of(args, config)).function(which)

    def run(given: list[str]) -> Any:
        with config_scope(config):
            return function(given)

    return run


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
