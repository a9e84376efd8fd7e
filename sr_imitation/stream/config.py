"""What every ``sr-train`` configuration shares, whatever its substrate.

Both substrates' run configurations (:class:`sr_imitation.substrates.act.trainer.TrainStreamConfig` for ACT,
:class:`sr_imitation.substrates.sac.config.RLTrainConfig` for SAC) use the same flag names for the same concepts::

    --substrate        act | sac (the key ``sr-train`` dispatches on; stored in the run's config)
    --method           the continual method (sr_imitation.stream.methods)
    --stream.*         the skills (--stream.skills), --stream.extend_from
    --sleep.*          the core's SleepConfig: --sleep.enabled, --sleep.lr, --sleep.aggregator, --sleep.anchor_*
    --memory.*         how skill memories are built: --memory.buffer_size
    --policy.sleep     the ACT-SR policy's name of --sleep.enabled (--policy.sleep_memory_size: --memory.buffer_size)
    --eval.*           evaluation: --eval.episodes, --eval.videos_per_skill, ...
    --wake.*           the wake budget and early stopping
    --seed --output_dir --resume --overwrite --progress --wandb.*

:class:`RunConfig` declares the run settings they share once (each substrate's config inherits it and adds its
own); :func:`check_shared_settings` validates what they share; :data:`RENAMED_FLAGS` turns the flags of earlier versions
into a one-line hint; :data:`POLICY_ALIASES` are the ACT-SR policy's own names (stock ``lerobot-train``'s, the
design card's ``--policy.sleep=true``) of shared settings, folded into them (:func:`fold_alias_flags`);
:data:`LEROBOT_TRAIN_FLAGS` and :data:`LEROBOT_EVAL_FLAGS` are ``lerobot-train``'s and ``lerobot-eval``'s flags,
accepted as the flag they map to or answered in one line with the names used here.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import draccus
from draccus.cfgparsing import parse_string
from draccus.utils import DecodingError

from sr_imitation.core.sleep import SleepConfig
from sr_imitation.infra.runlog import WandbConfig
from sr_imitation.stream.methods.registry import method_config


@dataclass
class StreamSleepConfig(SleepConfig):
    """``--sleep.*`` of a run: the core's sleep hyperparameters (:class:`~sr_imitation.core.sleep.SleepConfig`, the
    MT5 table's defaults) and whether the run sleeps at all, which the continual method reads (the core's
    ``sleep_consolidate`` has no such switch)."""

    enabled: bool = True
    """Sleep at all - false is the paper's SR Wake-Only ablation (read by the continual method)."""


@dataclass
class StreamSettings:
    """``--stream.*`` on every substrate; each substrate's stream configuration adds its skills and their data."""

    extend_from: Path | None = None
    """A finished run with these settings whose skills are this stream's first ones (e.g. MT8 from MT5): its stages
    are copied and the stream continues with the next skill."""


@dataclass
class RunConfig:
    """The run settings of ``sr-train`` on every substrate, declared once; a substrate's configuration inherits
    them and adds its own (policy, data, wake, memory, evaluation) and its defaults of ``output_dir`` and ``seed``."""

    method: str = "sr"
    """Continual method, by its registry name - one file each in sr_imitation/stream/methods (sr is Sleeping Robots);
    a method runs on every substrate that provides what it requires, and a name that does not run here is answered
    with the list of those that do."""
    method_options: dict[str, bool | float | str] = field(default_factory=dict)
    """Values for the method's own settings, e.g. --method_options='{lam: 100}' for EWC's lambda or
    --method_options='{expert_memory: beside, reset_wake: true}' for SR's options (each method's file lists them;
    true/false are read as booleans, numbers as floats, anything else as text)."""
    output_dir: Path = Path("outputs/stream")
    """Run directory (refused if it exists, unless --resume or --overwrite)."""
    seed: int = 0
    """Training seed - every phase seeds its generators from it."""
    resume: bool = False
    """Continue the run in output_dir (settings must equal its settings_fingerprint.json)."""
    overwrite: bool = False
    """Replace output_dir, only if it is a run of this package, and only once every input is checked (the old run is
    set aside until the new one has started, restored if the start fails); never a folder that holds an input."""
    progress: bool = True
    """Console progress bars."""
    wandb: WandbConfig = field(default_factory=WandbConfig)
    """Mirror the run log (log.jsonl) to Weights & Biases (--wandb.enable=true; offline by default)."""
    stream: StreamSettings = field(default_factory=StreamSettings)
    """The skills, in order, and their data (each substrate's stream configuration)."""

RENAMED_FLAGS: dict[str, str] = {
    "--policy.sleep_lr": "--sleep.lr",
    "--policy.sleep_max_iterations": "--sleep.max_iterations",
    "--policy.sleep_batch_size": "--sleep.batch_size",
    "--policy.sleep_early_stop_tol": "--sleep.early_stop_tol",
    "--policy.sleep_early_stop_window": "--sleep.early_stop_window",
    "--policy.sleep_fw_iterations": "--sleep.fw_iterations",
    "--policy.grad_norm_eps": "--sleep.eps",
    "--policy.anchor_strength": "--sleep.anchor_strength",
    "--policy.anchor_tau": "--sleep.anchor_tau",
    "--policy.anchor_after_final": "--sleep.anchor_after_final",
    "--policy.aggregator": "--sleep.aggregator",
    "--policy.memory_buffer_size": "--memory.buffer_size",
    "--eval.n_episodes": "--eval.episodes",
    "--sleep_enabled": "--sleep.enabled",
    "--skills": "--stream.skills",
    "--extend_from": "--stream.extend_from",
}
"""Flags of earlier versions -> their name now (``sr-train`` answers an old flag with this hint instead of
draccus' generic error)."""

_CHECKPOINTS = ("sr-train saves the policy after every wake and every sleep "
                "(<output_dir>/skill_<k>_<skill>/wake|sleep/pretrained_model)")
_ONE_AT_A_TIME = "sr-train runs evaluation episodes one at a time (--eval.episodes per skill and evaluation seed)"

LEROBOT_TRAIN_FLAGS: dict[str, str] = {
    # accepted: the sr-train flag that means the same
    "--batch_size": "--wake.batch_size",
    "--num_workers": "--wake.num_workers",
    "--dataset.video_backend": "--stream.video_backend",
    # answered in one line
    "--steps": "the budget is per skill and phase - --wake.max_epochs (and --wake.max_steps_per_epoch) for each "
               "wake, --sleep.max_iterations for each sleep",
    "--dataset.repo_id": "a stream has one dataset per skill - --stream.repo_ids=[{value},...] with "
                         "--stream.skills=[...] in the same order (or --stream.dataset_paths, --stream.dataset_root)",
    "--dataset.root": "a stream has one dataset per skill - --stream.dataset_paths=[{value},...] with "
                      "--stream.skills=[...] in the same order, or --stream.dataset_root=<folder>/<skill>",
    "--dataset.episodes": "sr-train trains on every episode of each skill's dataset and holds out "
                          "--wake.val_fraction of them for validation",
    "--policy.path": "sr-train trains a stream from scratch; continue a run with "
                     "--config_path=<run>/train_config.json --resume=true, evaluate a checkpoint with "
                     "sr-eval --policy.path={value}, consolidate one with sr-sleep --policy.path={value}",
    "--env.type": "each skill is evaluated in its own environment - --eval.env=lerobot --eval.env_type={value} "
                  "(one task per skill in --eval.env_tasks=[...])",
    "--env.task": "one task per skill - --eval.env=lerobot --eval.env_type=<type> --eval.env_tasks=[{value},...]",
    "--eval_freq": "sr-train evaluates after every wake and every sleep (--eval.episodes, --eval.seeds)",
    "--env_eval_freq": "sr-train evaluates after every wake and every sleep (--eval.episodes, --eval.seeds)",
    "--eval.batch_size": _ONE_AT_A_TIME,
    "--eval.use_async_envs": _ONE_AT_A_TIME,
    "--save_freq": _CHECKPOINTS,
    "--save_checkpoint": _CHECKPOINTS,
    "--log_freq": "sr-train logs every phase to <output_dir>/log.jsonl (--progress for progress bars, "
                  "--wandb.enable=true for wandb)",
    "--optimizer.lr": "the wake optimizer is ACT's AdamW preset - --policy.optimizer_lr (backbone "
                      "--policy.optimizer_lr_backbone); the sleep's is --sleep.lr",
    "--optimizer.weight_decay": "the wake optimizer is ACT's AdamW preset - --policy.optimizer_weight_decay",
    "--use_policy_training_preset": "sr-train always trains with the policy's preset optimizer "
                                    "(--policy.optimizer_lr, --policy.optimizer_weight_decay)",
    "--scheduler.type": "ACT's training preset has no learning-rate schedule, and sr-train none either",
    "--job_name": "a run is named by --output_dir (on wandb by --wandb.run_name)",
    "--wandb.entity": "sr-train's wandb flags are --wandb.enable, --wandb.project, --wandb.mode, --wandb.run_name",
    "--wandb.notes": "sr-train's wandb flags are --wandb.enable, --wandb.project, --wandb.mode, --wandb.run_name",
}
"""``lerobot-train``'s flags (LeRobot 0.4) on ``sr-train`` (ACT substrate), for a LeRobot user's habits: a value that
is one ``--flag`` is that ``sr-train`` flag (accepted as it; giving both is refused), any other value is the one-line
answer (``{value}``: the value given). A flag ``sr-train`` has itself (``--seed``, ``--output_dir``, ``--resume``,
``--wandb.enable``, ``--policy.*``) is never looked up here, so a flag added to the config later wins over its entry.
``--policy.type`` other than ``act_sr`` is answered by :data:`LEROBOT_TRAIN_NOTES`; ``--eval.n_episodes`` by
:data:`RENAMED_FLAGS`. Applied by :func:`sr_imitation.infra.cli_parsing.parse_command`; docs/COMMANDS.md, "A command
line that teaches (coming from LeRobot)"."""

LEROBOT_TRAIN_NOTES: dict[str, str] = {
    "--policy.type": "sr-train trains ACT-SR (ACT with sleep consolidation) only; train other LeRobot policies with "
                     "lerobot-train",
}
"""A sentence appended to argparse's error about the flag (``invalid choice: 'diffusion' (choose from 'act_sr')``)."""

LEROBOT_EVAL_FLAGS: dict[str, str] = {
    "--policy.device": "--device",
    "--eval.n_episodes": "sr-eval runs --eval.episodes per skill and evaluation seed - --eval.episodes={value} "
                         "--eval.seeds=[0] for {value} episodes of each skill",
    "--eval.batch_size": "sr-eval runs episodes one at a time",
    "--eval.use_async_envs": "sr-eval runs episodes one at a time",
    "--env.type": "--eval.env=lerobot --eval.env_type={value} with the skills in --skills=[...] (each skill's name "
                  "is its task unless --eval.env_tasks=[...] gives one per skill); needle skills need neither",
    "--env.task": "--skills=[...] names the skills; with --eval.env=lerobot their tasks are "
                  "--eval.env_tasks=[{value},...]",
    "--seed": "sr-eval seeds the episodes of every skill from --eval.seeds=[...]",
    "--job_name": "sr-eval writes to --output_dir",
}
"""``lerobot-eval``'s flags on ``sr-eval``, as :data:`LEROBOT_TRAIN_FLAGS`."""


POLICY_ALIASES: dict[str, tuple[str, type]] = {
    "policy.sleep": ("sleep.enabled", bool),
    "policy.sleep_memory_size": ("memory.buffer_size", int),
}
"""ACT-SR policy settings that stock ``lerobot-train`` acts on (``lerobot_policy_act_sr.ACTSRConfig``) -> the
``sr-train`` setting they are another name of, and its type. On ``sr-train`` each pair is one setting, never two
that can disagree: the alias sets the shared setting, giving both with different values is a one-line error
naming both, and the alias is ``None`` in the parsed (and stored, fingerprinted) configuration."""


def _flag_value(args: list[str], key: str) -> tuple[list[int], str | None]:
    """Where ``--key=V`` / ``--key V`` occur in ``args`` (token indices) and the last raw value (argparse's rule)."""
    where, raw = [], None
    for i, arg in enumerate(args):
        if arg.startswith(f"--{key}="):
            where, raw = [*where, i], arg.split("=", 1)[1]
        elif arg == f"--{key}":
            has_value = i + 1 < len(args) and not args[i + 1].startswith("--")
            where = [*where, i, i + 1] if has_value else [*where, i]
            raw = args[i + 1] if has_value else ""
    return where, raw


def _decode(key: str, value: Any, typ: type, source: str) -> Any:
    """``value`` (a command-line string, or a config file's JSON value) as draccus decodes ``key``; ``None`` for
    null. ``ValueError`` naming ``key`` for a value that is not of ``typ``."""
    if isinstance(value, str) and source == "command line" and not value.strip():
        raise ValueError(f"{key}: expected {'true or false' if typ is bool else 'an integer'}, got no value")
    raw = parse_string(value) if isinstance(value, str) and source == "command line" else value
    try:
        return draccus.decode(typ | None, raw)
    except DecodingError:  # answered below, outside this block, so that the one-line error is ours
        pass
    where = "" if source == "command line" else f" ({source})"
    raise ValueError(f"{key}: expected {'true or false' if typ is bool else 'an integer'}{where}, got {value!r}")


def _file_value(config: Any, key: str) -> Any:
    for part in key.split("."):
        config = config.get(part) if isinstance(config, dict) else None
    return config


def fold_alias_flags(args: list[str], config: Any = None, source: str = "config file") -> list[str]:
    """``args`` with every :data:`POLICY_ALIASES` flag replaced by its shared setting's flag.

    ``--policy.sleep=true`` becomes ``--sleep.enabled=true``. ``config`` is the ``--config_path`` file's JSON (an
    ``sr-main`` preset's ``train`` section), named ``source`` in errors: the command line overrides the file, as
    for any flag; a file's alias is folded the same way (and passed on as ``null``, so the parsed configuration
    holds the shared setting only). Raises ``ValueError`` (one line, naming both keys) when the command line, or
    the file, gives an alias and its shared setting with different values.
    """
    out = list(args)
    drop: set[int] = set()
    extra: list[str] = []
    for alias, (target, typ) in POLICY_ALIASES.items():
        where, raw = _flag_value(out, alias)
        drop.update(where)
        a_cli = None if raw is None else _decode(f"--{alias}", raw, typ, "command line")
        t_where, t_raw = _flag_value(out, target)
        t_cli = None if t_raw is None else _decode(f"--{target}", t_raw, typ, "command line")
        a_file = _decode(alias, _file_value(config, alias), typ, source)
        t_file = _decode(target, _file_value(config, target), typ, source)
        if a_cli is not None and t_cli is not None and a_cli != t_cli:
            raise ValueError(f"--{alias}={_show(a_cli)} and --{target}={_show(t_cli)} disagree: --{alias} is "
                             f"another name of --{target}; give one of them")
        if a_file is not None and t_file is not None and a_file != t_file:
            raise ValueError(f"{source}: {alias}={_show(a_file)} and {target}={_show(t_file)} disagree: {alias} is "
                             f"another name of {target}; give one of them")
        value = a_cli if a_cli is not None else (a_file if not t_where else None)
        if value is not None:
            extra.append(f"--{target}={_show(value)}")
        if a_file is not None:
            extra.append(f"--{alias}=null")
    return [arg for i, arg in enumerate(out) if i not in drop] + extra


def fold_alias_settings(cfg: Any) -> None:
    """The :data:`POLICY_ALIASES` rule on a parsed configuration (one built in Python, or by ``sr-main``): an alias
    given (not ``None``) must equal its shared setting, and is then set to ``None``. ``ValueError`` naming both keys
    otherwise. ``sr-train`` folds the flags before parsing (:func:`fold_alias_flags`)."""
    for alias, (target, _) in POLICY_ALIASES.items():
        section, name = alias.split(".")
        holder = getattr(cfg, section, None)
        value = getattr(holder, name, None)
        if value is None:
            continue
        t_section, t_name = target.split(".")
        shared = getattr(getattr(cfg, t_section), t_name)
        if value != shared:
            raise ValueError(f"{alias}={_show(value)} and {target}={_show(shared)} disagree: {alias} is another "
                             f"name of {target}; give one of them")
        setattr(holder, name, None)


def _show(value: Any) -> str:
    return str(value).lower() if isinstance(value, bool) else str(value)


def renamed_flag_hint(args: list[str]) -> str | None:
    """A one-line hint for the first renamed flag in ``args`` (``None`` if there is none)."""
    for arg in args:
        name = arg.split("=", 1)[0]
        if name in RENAMED_FLAGS:
            return f"{name} was renamed: use {RENAMED_FLAGS[name]} (the same name on every substrate)"
    return None


def renamed_key_hint(config: Any, prefix: str = "") -> str | None:
    """:func:`renamed_flag_hint` for the keys of a config file's JSON tree (``{"policy": {"sleep_lr": ...}}``);
    an ``sr-main`` preset's ``train`` section is read as the run's config."""
    if not isinstance(config, dict):
        return None
    for key, value in config.items():
        dotted = f"{prefix}{key}" if prefix or key != "train" else ""
        if dotted and f"--{dotted}" in RENAMED_FLAGS:
            return (f"config key {dotted!r} was renamed: use {RENAMED_FLAGS['--' + dotted][2:]!r} "
                    f"(the same name on every substrate)")
        found = renamed_key_hint(value, f"{dotted}." if dotted else "")
        if found is not None:
            return found
    return None


def check_choices(key: str, given: Sequence[str], known: Iterable[str]) -> None:
    """``ValueError`` naming ``key``, the unknown values and the valid ones, unless every value of ``given`` is
    one of ``known`` (the experiment drivers' variant and option lists)."""
    known = list(known)
    unknown = [v for v in given if v not in known]
    if unknown:
        raise ValueError(f"{key}: unknown {unknown}; choose from {sorted(known)}")


def check_shared_settings(cfg: Any, substrate: str) -> None:
    """Refuse a configuration of another substrate, a hand-set ``sleep.seed`` (set per stage from ``--seed``) and
    ``method_options`` the method lacks or of another type than its option (a number given text: one line naming
    the option, the type and the value, :func:`~sr_imitation.stream.methods.base.with_options`), before anything
    is built. Raises ``ValueError`` naming the key."""
    if cfg.substrate != substrate:
        raise ValueError(f"substrate: this configuration is for {substrate!r}, got {cfg.substrate!r}")
    if cfg.sleep.seed != 0:
        raise ValueError("sleep.seed: set per stage from --seed by the substrate; leave it 0 and change --seed")
    if cfg.resume and cfg.overwrite:
        raise ValueError("--resume and --overwrite exclude each other")
    if cfg.method_options:
        method_config(cfg.method, cfg.method_options)
