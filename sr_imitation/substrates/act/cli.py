"""Command-line entry points ``sr-train``, ``sr-eval`` and ``sr-sleep`` (draccus, LeRobot's flag style).

    sr-train --config_path=configs/needle_cpu.json
    sr-train --policy.type=act_sr --policy.sleep=true --stream.skills=[approach,place,insert] \\
             --stream.dataset_root=datasets/needle --output_dir=outputs/run1
    sr-train --config_path=outputs/run1/train_config.json --resume=true   # resumes outputs/run1, wherever it is
    sr-eval --policy.path=outputs/run1/skill_5_pullout/sleep/pretrained_model --skills=[approach,pullout]
    sr-sleep --policy.path=<pretrained_model> --memories=[a.safetensors,b.safetensors] --output_dir=outputs/slept
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import os
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from lerobot.configs.policies import PreTrainedConfig

import lerobot_policy_act_sr  # noqa: F401  (registers act_sr with LeRobot's config registry)
from sr_imitation.envs.needle.skills import SKILL_NAMES as SURGICAI_SKILLS
from sr_imitation.infra.cli_errors import run_cli, setup_logging
from sr_imitation.infra.cli_parsing import parse_command, take_flag, wants_help
from sr_imitation.infra.config_file import ConfigFile, config_file, split_config
from sr_imitation.infra.fingerprint import RUN_DIRECTORY, output_dir_for
from sr_imitation.infra.folder_lock import hold_folder, remove_leftovers, remove_staging_beside
from sr_imitation.io import read_checked_json, read_config_json, verify_checkpoint, write_checked_json
from sr_imitation.offscreen import setup_offscreen_rendering
from sr_imitation.stream.config import LEROBOT_EVAL_FLAGS, LEROBOT_TRAIN_FLAGS, LEROBOT_TRAIN_NOTES, fold_alias_flags
from sr_imitation.substrates.act.config import LEGACY_DEFAULTS, MainJobConfig
from sr_imitation.substrates.act.evaluate import EvalConfig, episode_positions, evaluate_skills, make_env_factory
from sr_imitation.substrates.act.trainer import TrainStreamConfig, train_stream
from sr_imitation.video import PARTIAL_VIDEO

logger = logging.getLogger(__name__)


@contextlib.contextmanager
def act_sr_choices_only() -> Iterator[None]:
    """Within the block, ``--policy.type`` knows ``act_sr`` only.

    LeRobot registers every policy type with ``PreTrainedConfig``; draccus builds flags (and extracts help text
    from the source) for all of them on every parse: 3.7 s per parse here and a ``--help`` of ~2000 lines of
    unrelated policies. ``sr-train`` trains ACT-SR only, so the registry is narrowed while parsing (0.6 s) and
    any other ``--policy.type`` is refused by argparse naming the valid choice."""
    saved = PreTrainedConfig.__dict__["_choice_registry"]
    PreTrainedConfig._choice_registry = {k: v for k, v in saved.items() if k == "act_sr"}
    try:
        yield
    finally:
        PreTrainedConfig._choice_registry = saved


T = TypeVar("T")


def parse_config[T](cls: type[T], config_path: str | os.PathLike[str] | ConfigFile | None, args: list[str], *,
                 prog: str = "sr-train", prefix: str = "", names: dict[str, str] | None = None,
                 notes: dict[str, str] | None = None, help_values: tuple[str, dict] | None = None) -> T:
    """``draccus.parse`` of a config holding an ACT-SR policy (see :func:`act_sr_choices_only`), with the teaching
    command line of :func:`~sr_imitation.infra.cli_parsing.parse_command` (``config_path``: the config file, read or
    to read; ``prefix``, ``names``, ``notes``, ``help_values`` there)."""
    with act_sr_choices_only():
        return parse_command(cls, args, prog=prog, config_path=config_path, prefix=prefix, names=names, notes=notes,
                             help_values=help_values)


def _setup_logging() -> None:
    setup_offscreen_rendering()
    setup_logging()


def parse_train_config(config_path: str | os.PathLike[str] | ConfigFile | None, args: list[str]
                       ) -> TrainStreamConfig:
    """The ``sr-train`` config of a command line. ``--config_path`` (read or to read:
    :func:`~sr_imitation.infra.config_file.config_file`) may name a run's ``train_config.json`` (its ``output_dir``
    "." is the run directory, wherever it was copied) or an ``sr-main`` preset such as ``configs/needle_cpu.json``,
    whose ``train`` section is used with the datasets at ``record.root`` (flags then address that section as usual:
    ``--seed=1``). The ACT-SR policy's names of shared settings (``--policy.sleep`` for ``--sleep.enabled``,
    ``--policy.sleep_memory_size`` for ``--memory.buffer_size``) are folded into them
    (:func:`~sr_imitation.stream.config.fold_alias_flags`)."""
    config = config_file(config_path)
    data = {} if config is None else config.settings
    preset = config is not None and config.is_main_job_preset
    if preset and wants_help(args):
        parse_config(TrainStreamConfig, None, ["--help"],  # the flags that address the preset's train section; exits
                     help_values=(f"{config.path}'s train section", data["train"]))
    run_settings = {} if config is None else config.run_settings
    args = fold_alias_flags(args, run_settings, str(None if config is None else config.path))
    args = implied_policy_type(run_settings, legacy_flags(data, args))
    lerobot = {"names": LEROBOT_TRAIN_FLAGS, "notes": LEROBOT_TRAIN_NOTES}
    if preset:
        cfg = parse_preset(config, args, **lerobot)[0].train
        cfg.output_dir = Path(cfg.output_dir)
        return cfg
    cfg = parse_config(TrainStreamConfig, config, args, **lerobot)
    cfg.output_dir = output_dir_for(None if config is None else config.path, args, cfg.output_dir)
    return cfg


def parse_preset(config_path: str | os.PathLike[str] | ConfigFile, args: list[str], **names: Any
                 ) -> tuple[MainJobConfig, bool]:
    """An ``sr-main`` preset with ``sr-train`` flags applied to its train section (``--seed=1``), and whether the
    stream reads datasets of the user's own: ``--stream.dataset_root`` names where they are, instead of the preset's
    ``record.root`` (where the preset records them; never dropped silently)."""
    args, root = take_flag(list(args), "--stream.dataset_root")
    cfg = parse_config(MainJobConfig, config_path, args, prefix="train.", **names)
    if root is not None:
        cfg.train.stream.dataset_root = Path(root)
    return cfg, root is not None


def legacy_flags(data: dict, args: list[str]) -> list[str]:
    """``args`` with, for a run's own config file (``output_dir`` "."), the recorded value of every
    :data:`~sr_imitation.substrates.act.config.LEGACY_DEFAULTS` setting the file lacks and no flag gives."""
    if data.get("output_dir") != RUN_DIRECTORY:
        return args
    extra = []
    for key, value in LEGACY_DEFAULTS.items():
        node: Any = data
        for part in key.split("."):
            node = node.get(part, _MISSING) if isinstance(node, dict) else _MISSING
        if node is _MISSING and not any(a.split("=", 1)[0] == f"--{key}" for a in args):
            extra.append(f"--{key}={value}")
    return [*extra, *args]


_MISSING = object()


def implied_policy_type(data: object, args: list[str]) -> list[str]:
    """``args`` with ``--policy.type=act_sr`` first when they set a ``--policy.*`` flag and neither they nor the
    config file name the policy type: sr-train trains ACT-SR only (draccus would otherwise ask for a dict with a
    'type' key)."""
    flags = [a.split("=", 1)[0] for a in args if a.startswith("--policy.")]
    policy = data.get("policy") if isinstance(data, dict) else None
    if not flags or "--policy.type" in flags or (isinstance(policy, dict) and "type" in policy):
        return args
    return ["--policy.type=act_sr", *args]


def parse_train_args(args: list[str]) -> TrainStreamConfig:
    """:func:`parse_train_config` of a whole command line (``--config_path`` included)."""
    config, rest = split_config(list(args))
    return parse_train_config(config, rest)


def train_main(args: list[str] | None = None) -> None:
    """``sr-train``: run (or resume) a wake-sleep stream."""
    _setup_logging()
    cfg = parse_train_args(list(sys.argv[1:] if args is None else args))
    results = train_stream(cfg)
    if "metrics" not in results:  # a process other than the main one of a several-process run: it reports nothing
        return
    m = results["metrics"]
    if results.get("evaluation") == "none":
        losses = results["losses"]
        print(f"results: {cfg.output_dir / 'results.json'}, {cfg.output_dir / 'results.md'} (evaluation: none - "
              "no success measured; AFSR, PRS, BWT and SPI are null)")
        print("final memory losses " + ", ".join(f"{s}={'-' if v is None else f'{v:.4f}'}" for s, v in zip(
            results["skills"], losses["memory_loss"][-1], strict=True)) + "; validation l1 " + ", ".join(
            f"{s}={v:.4f}" for s, v in zip(results["skills"], losses["validation_l1"][-1], strict=True)))
        return
    print(f"results: {cfg.output_dir / 'results.json'} (plots: metrics.png, success_matrix.png; videos: videos/)")
    names = ("afsr", "prs", "bwt", "bwt_wake", "spi")
    print("final " + ", ".join(f"{k.upper()}={m[k]['final']:.3f}" for k in names
                               if k in m and m[k]["final"] is not None)
          + " (BWT: reference after stage i; BWT_WAKE: reference right after skill i's own wake)")


@dataclass
class PolicyPath:
    """The checkpoint to load."""

    path: Path = Path("")
    """A LeRobot pretrained_model directory (config.json and model.safetensors), e.g.
    outputs/run1/skill_5_pullout/sleep/pretrained_model."""


@dataclass
class EvalCommandConfig:
    """``sr-eval`` configuration (``--eval.env`` as for ``sr-train``: needle, metaworld, gym or lerobot; one entry of
    ``--eval.gym_ids`` / ``--eval.env_tasks`` per skill). A checkpoint that ``sr-train`` wrote carries its run's
    ``train_config.json``: its stream's skills and evaluation settings are then the defaults (flags override them)."""

    policy: PolicyPath = field(default_factory=PolicyPath)
    """The checkpoint to evaluate (--policy.path)."""
    skills: list[str] = field(default_factory=lambda: list(SURGICAI_SKILLS))
    """Skills to evaluate, in the policy's stream order (default: the checkpoint's stream, else the five needle
    skills)."""
    eval: EvalConfig = field(default_factory=EvalConfig)
    """Where and how each skill is evaluated (the same settings as sr-train's --eval.*; default: the checkpoint's
    run's)."""
    output_dir: Path = Path("outputs/eval")
    """Where eval.json and the videos are written."""
    overwrite: bool = False
    """Replace an earlier sr-eval's eval.json in output_dir and the videos it lists (refused otherwise, before
    evaluating)."""
    device: str = "cpu"
    """Torch device of the policy (cpu, cuda or mps)."""
    progress: bool = True
    """Console progress bars."""

    def __post_init__(self) -> None:
        if self.eval.env == "none":
            raise ValueError("eval.env: sr-eval evaluates in an environment; --eval.env=none leaves nothing to do")
        self.eval.check_skills(self.skills)


def checkpoint_defaults(args: list[str]) -> ConfigFile | None:
    """The settings for :class:`EvalCommandConfig` that the run which wrote the ``--policy.path`` checkpoint gives:
    its skills and ``eval`` settings (from its ``train_config.json``, checked against its seal), or None for a
    checkpoint without one (stock ``lerobot-train`` writes LeRobot's own, which has no stream). Settings this
    version does not know are left out."""
    _, given = take_flag(list(args), "--policy.path")
    stored = None if given is None else Path(given) / "train_config.json"
    config = _stored_run_config(stored)
    if config is None:
        return None
    stream, evaluation = config.get("stream"), config.get("eval")
    if not isinstance(stream, dict) or not isinstance(evaluation, dict) or "skills" not in stream:
        return None
    known = {f.name for f in dataclasses.fields(EvalConfig)}
    defaults = {"skills": list(stream["skills"]), "eval": {k: v for k, v in evaluation.items() if k in known}}
    logger.info("sr-eval: skills %s and evaluation settings (env %s) from %s; flags override them",
                defaults["skills"], defaults["eval"].get("env"), stored)
    return ConfigFile(stored, defaults, sealed=True)


def _stored_run_config(stored: Path | None) -> dict[str, Any] | None:
    """A checkpoint's ``train_config.json`` (checked against its seal), or None where there is none."""
    if stored is None or not stored.is_file():
        return None
    return read_config_json(stored)[0]


def checkpoint_stream(path: Path) -> list[str] | None:
    """The skill order of the run that wrote the checkpoint at ``path`` (its ``train_config.json``), or None."""
    stream = (_stored_run_config(Path(path) / "train_config.json") or {}).get("stream")
    return list(stream["skills"]) if isinstance(stream, dict) and "skills" in stream else None


def check_eval_output(cfg: EvalCommandConfig) -> set[Path]:
    """``FileExistsError`` naming ``output_dir/eval.json`` when an earlier evaluation is there and ``--overwrite`` is
    not given; with it, the videos that evaluation lists (:func:`replace_earlier_videos` removes those the new one
    does not write again, once it is written: a failed evaluation loses nothing)."""
    earlier = cfg.output_dir / "eval.json"
    if not earlier.exists():
        return set()
    if not cfg.overwrite:
        raise FileExistsError(f"{earlier}: an earlier evaluation is there; give another --output_dir, or "
                              "--overwrite=true to replace it")
    videos = (cfg.output_dir / "videos").resolve()
    listed = {Path(v) for r in read_checked_json(earlier)["results"].values() for v in r.get("videos", [])}
    return {v for v in listed if v.resolve().parent == videos}


def replace_earlier_videos(earlier: set[Path], record: dict[str, Any]) -> None:
    """Remove the earlier evaluation's videos that the new ``record`` does not list (nothing else in the folder)."""
    kept = {Path(v).resolve() for r in record.values() for v in r["videos"]}
    for video in earlier:
        if video.resolve() not in kept:
            video.unlink(missing_ok=True)


def eval_main(args: list[str] | None = None) -> None:
    """``sr-eval``: evaluate any ACT-SR (or ACT) checkpoint on a set of skills (needle skills by default, or the
    environments ``--eval.env`` names), with videos."""
    _setup_logging()
    config, rest = split_config(list(sys.argv[1:] if args is None else args))
    defaults = checkpoint_defaults(rest) if config is None else config
    cfg = parse_command(EvalCommandConfig, rest, prog="sr-eval", config_path=defaults, names=LEROBOT_EVAL_FLAGS)
    with hold_folder(cfg.output_dir, "sr-eval"):  # the only writer of output_dir, before it is looked at
        remove_leftovers(cfg.output_dir, Path(cfg.output_dir) / "videos", PARTIAL_VIDEO, "sr-eval")
        evaluate_checkpoint(cfg)


def evaluate_checkpoint(cfg: EvalCommandConfig) -> None:
    """``sr-eval``'s work once its command line is parsed and ``output_dir``'s lock is held: evaluate, write
    ``eval.json`` and the videos, print the success rates."""
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import get_policy_class, make_pre_post_processors

    path = Path(cfg.policy.path)
    if not (path / "config.json").is_file():
        raise FileNotFoundError(f"{path}: not a LeRobot pretrained_model directory (no config.json)")
    earlier_videos = check_eval_output(cfg)
    verify_checkpoint(path, "policy.path")  # an sr-train stage or sr-sleep checkpoint is sealed; else one warning
    policy_cfg = PreTrainedConfig.from_pretrained(path)
    policy_cfg.device = cfg.device
    policy = get_policy_class(policy_cfg.type).from_pretrained(path, config=policy_cfg)
    pre, post = make_pre_post_processors(policy_cfg, pretrained_path=str(path))
    images = list(policy_cfg.image_features)
    size = None
    if images:
        shape = policy_cfg.image_features[images[0]].shape
        size = (int(shape[1]), int(shape[2]))
    positions = episode_positions(cfg.skills, checkpoint_stream(path))  # the run's own episodes, in any order
    results = evaluate_skills(policy, pre, post, cfg.skills, positions, make_env_factory(cfg.eval, cfg.skills, size),
                              cfg.eval, cfg.output_dir / "videos", cfg.progress)
    record = {s: {"success": r.success, "success_per_seed": r.success_per_seed, "videos": r.videos}
              for s, r in results.items()}
    write_checked_json(cfg.output_dir / "eval.json", {"policy": str(path), "results": record})
    replace_earlier_videos(earlier_videos, record)
    print(json.dumps({s: round(r["success"], 4) for s, r in record.items()}, indent=2))  # eval.json: exact
    print(f"written: {cfg.output_dir / 'eval.json'}, videos in {cfg.output_dir / 'videos'}")


def sleep_main(args: list[str] | None = None) -> dict:
    """``sr-sleep``: consolidate a deployed ACT-SR policy offline from saved memory files
    (:mod:`sr_imitation.substrates.act.offline_sleep`); prints the before/after table and where it was written."""
    from sr_imitation.substrates.act.offline_sleep import (
        REPORT_FILE,
        OfflineSleepConfig,
        report_markdown,
        run_offline_sleep,
    )

    _setup_logging()
    config, rest = split_config(list(sys.argv[1:] if args is None else args))
    cfg = parse_command(OfflineSleepConfig, rest, prog="sr-sleep", config_path=config)
    with hold_folder(cfg.output_dir, "sr-sleep"):  # the only writer of output_dir, before it is looked at
        remove_staging_beside(cfg.output_dir, "sr-sleep")  # a killed earlier sr-sleep's .<output_dir>.XXXXXXXX
        record = run_offline_sleep(cfg)
    print(report_markdown(record), end="")
    print(f"written: {cfg.output_dir / 'pretrained_model'} (lerobot-eval --policy.path=...), "
          f"{cfg.output_dir / REPORT_FILE}, {cfg.output_dir / 'sleep.json'}")
    return record


def train_entry() -> None:
    """Console script ``sr-train``: :func:`train_main` with one-line user errors (``--debug`` for tracebacks)."""
    run_cli("sr-train", train_main)


def eval_entry() -> None:
    """Console script ``sr-eval``."""
    run_cli("sr-eval", eval_main)


def sleep_entry() -> None:
    """Console script ``sr-sleep`` (one-line user errors; ``--debug`` for tracebacks)."""
    run_cli("sr-sleep", sleep_main)


if __name__ == "__main__":
    train_entry()
