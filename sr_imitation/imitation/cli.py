"""Command-line entry points ``sr-train`` and ``sr-eval`` (draccus, LeRobot's flag style).

    sr-train --config_path=configs/needle_cpu.json
    sr-train --policy.type=act_sr --policy.sleep=true --stream.skills=[approach,place,insert] \\
             --stream.dataset_root=datasets/needle --output_dir=outputs/run1
    sr-train --config_path=outputs/run1/train_config.json --resume=true   # resumes outputs/run1, wherever it is
    sr-eval --policy.path=outputs/run1/skill_5_pullout/sleep/pretrained_model --skills=[approach,pullout]
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

import draccus
from lerobot.configs.policies import PreTrainedConfig

import lerobot_policy_act_sr  # noqa: F401  (registers act_sr with LeRobot's config registry)
from sr_imitation.core.cli_errors import run_cli, split_config_path
from sr_imitation.core.fingerprint import output_dir_for
from sr_imitation.core.io import write_checked_json
from sr_imitation.envs.needle.skills import SKILL_NAMES as SURGICAI_SKILLS
from sr_imitation.imitation.evaluate import EvalConfig, evaluate_skills, needle_env_factory
from sr_imitation.imitation.stream import TrainStreamConfig, train_stream
from sr_imitation.offscreen import setup_offscreen_rendering
from sr_imitation.stream.config import fold_alias_flags


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


def parse_config(cls: type[T], config_path: str | os.PathLike[str] | None, args: list[str]) -> T:
    """``draccus.parse`` of a config holding an ACT-SR policy (see :func:`act_sr_choices_only`)."""
    with act_sr_choices_only():
        return draccus.parse(cls, config_path=None if config_path is None else str(config_path), args=args)


def _setup_logging() -> None:
    setup_offscreen_rendering()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")


def parse_train_config(config_path: str | None, args: list[str]) -> TrainStreamConfig:
    """The ``sr-train`` config of a command line. ``--config_path`` may name a run's ``train_config.json`` (its
    ``output_dir`` "." is the run directory, wherever it was copied) or an ``sr-main`` preset such as
    ``configs/needle_cpu.json``, whose ``train`` section is used with the datasets at ``record.root`` (flags then
    address that section as usual: ``--seed=1``). The ACT-SR policy's names of shared settings
    (``--policy.sleep`` for ``--sleep.enabled``, ``--policy.sleep_memory_size`` for ``--memory.buffer_size``) are
    folded into them (:func:`~sr_imitation.stream.config.fold_alias_flags`)."""
    data = {} if config_path is None else _read_json(config_path)
    preset = _is_main_job_preset(data)
    args = fold_alias_flags(args, data.get("train") if preset else data, str(config_path))
    if preset:
        from sr_imitation.main_job import MainJobConfig  # noqa: PLC0415 (main_job imports this module)

        prefixed = [f"--train.{a[2:]}" if a.startswith("--") else a for a in args]
        cfg = parse_config(MainJobConfig, config_path, prefixed).train
        cfg.output_dir = Path(cfg.output_dir)
        return cfg
    cfg = parse_config(TrainStreamConfig, config_path, args)
    cfg.output_dir = output_dir_for(config_path, args, cfg.output_dir)
    return cfg


def parse_train_args(args: list[str]) -> TrainStreamConfig:
    """:func:`parse_train_config` of a whole command line (``--config_path`` included)."""
    config_path, rest = split_config_path(list(args))
    return parse_train_config(config_path, rest)


def _read_json(config_path: str) -> dict:
    """A config file's JSON object; ``{}`` if it is unreadable or not an object (draccus reports it)."""
    try:
        data = json.loads(Path(config_path).read_text())
    except (OSError, json.JSONDecodeError):
        return {}
    return data if isinstance(data, dict) else {}


def _is_main_job_preset(data: dict) -> bool:
    """Whether a config file's JSON is an ``sr-main`` preset (``record`` and ``train`` sections)."""
    return "train" in data and "record" in data


def train_main(args: list[str] | None = None) -> None:
    """``sr-train``: run (or resume) a wake-sleep stream."""
    _setup_logging()
    cfg = parse_train_args(list(sys.argv[1:] if args is None else args))
    results = train_stream(cfg)
    m = results["metrics"]
    print(f"results: {cfg.output_dir / 'results.json'} (plots: metrics.png, success_matrix.png; videos: videos/)")
    names = ("afsr", "prs", "bwt", "bwt_wake", "spi")
    print("final " + ", ".join(f"{k.upper()}={m[k]['final']:.3f}" for k in names
                               if k in m and m[k]["final"] is not None)
          + " (BWT: reference after stage i; BWT_WAKE: reference right after skill i's own wake)")


@dataclass
class PolicyPath:
    path: Path = Path("")


@dataclass
class EvalCommandConfig:
    """``sr-eval`` configuration."""

    policy: PolicyPath = field(default_factory=PolicyPath)
    skills: list[str] = field(default_factory=lambda: list(SURGICAI_SKILLS))
    eval: EvalConfig = field(default_factory=EvalConfig)
    output_dir: Path = Path("outputs/eval")
    device: str = "cpu"
    progress: bool = True


def eval_main(args: list[str] | None = None) -> None:
    """``sr-eval``: evaluate any ACT-SR (or ACT) checkpoint on a set of needle skills, with videos."""
    _setup_logging()
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import get_policy_class, make_pre_post_processors

    config_path, rest = split_config_path(list(sys.argv[1:] if args is None else args))
    cfg = draccus.parse(EvalCommandConfig, config_path=config_path, args=rest)
    path = Path(cfg.policy.path)
    if not (path / "config.json").is_file():
        raise FileNotFoundError(f"{path}: not a LeRobot pretrained_model directory (no config.json)")
    policy_cfg = PreTrainedConfig.from_pretrained(path)
    policy_cfg.device = cfg.device
    policy = get_policy_class(policy_cfg.type).from_pretrained(path, config=policy_cfg)
    pre, post = make_pre_post_processors(policy_cfg, pretrained_path=str(path))
    images = list(policy_cfg.image_features)
    size = None
    if images:
        shape = policy_cfg.image_features[images[0]].shape
        size = (int(shape[1]), int(shape[2]))
    results = evaluate_skills(policy, pre, post, cfg.skills, [SURGICAI_SKILLS.index(s) if s in SURGICAI_SKILLS
                                                              else i for i, s in enumerate(cfg.skills)],
                              needle_env_factory(size, cfg.eval), cfg.eval, cfg.output_dir / "videos",
                              cfg.progress)
    record = {s: {"success": r.success, "success_per_seed": r.success_per_seed, "videos": r.videos}
              for s, r in results.items()}
    write_checked_json(cfg.output_dir / "eval.json", {"policy": str(path), "results": record})
    print(json.dumps({s: r["success"] for s, r in record.items()}, indent=2))
    print(f"written: {cfg.output_dir / 'eval.json'}, videos in {cfg.output_dir / 'videos'}")


def train_entry() -> None:
    """Console script ``sr-train``: :func:`train_main` with one-line user errors (``--debug`` for tracebacks)."""
    run_cli("sr-train", train_main)


def eval_entry() -> None:
    """Console script ``sr-eval``."""
    run_cli("sr-eval", eval_main)


if __name__ == "__main__":
    train_entry()
