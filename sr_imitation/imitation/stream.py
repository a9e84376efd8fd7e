"""``sr-train`` on the imitation substrate: the stream's configuration and its runner.

The algorithm is the stream engine's (:mod:`sr_imitation.stream.engine`, Algorithm 1 written once); the ACT
substrate (:mod:`sr_imitation.imitation.substrate`) says what each phase does and which files it writes; the
method (``--method``: :mod:`sr_imitation.stream.methods`) what is distilled, stored and whether it sleeps. This
module holds :class:`TrainStreamConfig`, what a resume must keep (:data:`RESUME_ALLOW_LIST`), and
:class:`StreamTrainer`, which checks every dataset of the stream, prepares the run directory and runs the engine.

Every phase is recorded in ``progress.json`` only after its outputs are completely and atomically written, and
every phase seeds its own random generators from (run seed, skill, phase). A run killed at any point and
restarted with ``--resume=true`` therefore redoes at most the interrupted phase and, on CPU, reaches the same
numbers as an uninterrupted run. Results (``results.json``, plots, a markdown table) are rebuilt from the
recorded phases at the end.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from lerobot.configs.policies import PreTrainedConfig

from lerobot_policy_act_sr import ACTSRConfig
from sr_imitation.core.fingerprint import (
    RUN_DIRECTORY,
    SettingsFingerprint,
    check_finite,
    settings_fingerprint,
    to_jsonable,
)
from sr_imitation.core.runlog import WandbConfig
from sr_imitation.core.sleep import SurgicAISleepConfig
from sr_imitation.envs.needle.skills import SKILL_NAMES as SURGICAI_SKILLS
from sr_imitation.imitation.data import STATS_SOURCES, check_stream_datasets
from sr_imitation.imitation.dataset_identity import check_inputs, dataset_inputs
from sr_imitation.imitation.evaluate import EnvFactory, EvalConfig
from sr_imitation.imitation.substrate import ACTSubstrate, seed_everything, stage_name
from sr_imitation.imitation.wake import WakeConfig
from sr_imitation.stream import RunDirectory, StreamEngine, make_method, method_config, methods_for
from sr_imitation.stream.config import check_shared_settings, fold_alias_settings

__all__ = ["RESUME_ALLOW_LIST", "StreamConfig", "StreamTrainer", "TrainStreamConfig", "resume_fingerprint",
           "seed_everything", "stage_name", "stored_config_dict", "train_stream"]

logger = logging.getLogger(__name__)



@dataclass
class StreamConfig:
    """The skill stream: an ordered list of skills, one LeRobot dataset each.

    Each field is documented below (``--help`` shows it).
    """

    skills: list[str] = field(default_factory=lambda: list(SURGICAI_SKILLS))
    """Stream order (default - approach, place, insert, regrasp, pullout)."""
    dataset_root: Path = Path("datasets/needle")
    """Datasets live at <dataset_root>/<skill>, as sr-record writes them ..."""
    dataset_paths: list[Path] | None = None
    """... unless listed here, one path per skill."""
    repo_id_prefix: str = "local/sr_needle"
    """LeRobot repo_id label <prefix>_<skill> (local datasets; nothing is downloaded)."""
    video_backend: str = "pyav"
    """Decoder for video datasets (pyav - torchcodec does not load here)."""
    pairs: str = "surgicai"
    """PRS pair list - surgicai (the paper's seven), all or adjacent."""
    stats: str = "first"
    """Normalization statistics fixed for the whole stream - first (the first skill's dataset) or union (all the
    stream's datasets, known before the first skill); see sr_imitation.imitation.data."""
    stats_min_std: float = 1e-2
    """Floor on the fixed stream statistics' standard deviations."""
    extend_from: Path | None = None
    """A finished sr-train run with these settings whose skills are this stream's first ones - its stages are
    copied and the stream continues with the next skill."""

    def __post_init__(self) -> None:
        if not self.skills:
            raise ValueError("the stream needs at least one skill")
        if len(set(self.skills)) != len(self.skills):
            raise ValueError(f"skills must be distinct, got {self.skills}")
        if self.stats not in STATS_SOURCES:
            raise ValueError(f"stream.stats must be one of {STATS_SOURCES}, got {self.stats!r}")
        if self.dataset_paths is not None and len(self.dataset_paths) != len(self.skills):
            raise ValueError(f"{len(self.dataset_paths)} dataset_paths for {len(self.skills)} skills")

    def dataset_path(self, index: int) -> Path:
        if self.dataset_paths is not None:
            return Path(self.dataset_paths[index])
        return Path(self.dataset_root) / self.skills[index]

    def repo_id(self, index: int) -> str:
        return f"{self.repo_id_prefix}_{self.skills[index]}"


@dataclass
class MemoryConfig:
    """The frozen actor memory M_k stored after each skill's wake (paper Table "Sleep-consolidation
    hyperparameters for SurgicAI": 1024 buffered observations per skill)."""

    buffer_size: int = 1024
    """|B_k| - observations sampled from the skill's demonstrations into its memory."""

    def __post_init__(self) -> None:
        if self.buffer_size < 1:
            raise ValueError(f"memory.buffer_size must be >= 1, got {self.buffer_size}")


@dataclass
class TrainStreamConfig:
    """``sr-train`` on the imitation substrate (ACT-SR on the needle stream), e.g.
    ``sr-train --policy.type=act_sr --stream.skills=[approach,place] --sleep.enabled=true``.
    ``sr-train --substrate=sac --help`` shows the Meta-World SAC substrate's flags instead."""

    substrate: str = "act"
    """The substrate sr-train runs - act (this one) or sac (Meta-World SAC, see --substrate=sac --help)."""
    policy: PreTrainedConfig | None = None
    """The ACT-SR policy (--policy.type=act_sr): architecture, wake optimizer, wake distillation weights."""
    stream: StreamConfig = field(default_factory=StreamConfig)
    """The skills and their datasets."""
    wake: WakeConfig = field(default_factory=WakeConfig)
    """Wake budget and early stopping."""
    memory: MemoryConfig = field(default_factory=MemoryConfig)
    """The skill memories."""
    sleep: SurgicAISleepConfig = field(default_factory=SurgicAISleepConfig)
    """Sleep consolidation (defaults - the paper's SurgicAI table; --sleep.enabled=false is SR wake-only)."""
    eval: EvalConfig = field(default_factory=EvalConfig)
    """Evaluation after every wake and sleep."""
    method: str = "sr"
    """Continual method - sr, wake_only, sequential_bc, lwf, m2distill or ewc (sr_imitation/stream/methods)."""
    method_options: dict[str, float] = field(default_factory=dict)
    """Values for the method's own settings, e.g. --method_options='{lam: 100}' for EWC's lambda (each method's
    file lists them)."""
    wandb: WandbConfig = field(default_factory=WandbConfig)
    """Mirror the run log (log.jsonl) to Weights & Biases (offline by default)."""
    output_dir: Path = Path("outputs/needle_stream")
    """Run directory (refused if it exists, unless --resume or --overwrite)."""
    seed: int = 1000
    """Training seed - every phase seeds its generators from it."""
    resume: bool = False
    """Continue the run in output_dir (settings must equal its settings_fingerprint.json)."""
    overwrite: bool = False
    """Delete output_dir first."""
    allow_unhashed_inputs: bool = False
    """Resume a run started before datasets were fingerprinted by content, without checking its data (you vouch
    that the datasets are unchanged; a run that has the fingerprints always checks them)."""
    progress: bool = True
    """Console progress bars."""
    torch_threads: int | None = None
    """torch's intra-op threads (null - this process's default, e.g. OMP_NUM_THREADS). Fingerprinted as the number
    in effect: CPU reductions split over another number of threads round differently, so a resume must use the same
    number (as the SAC substrate's torch_threads)."""

    def __post_init__(self) -> None:
        if self.torch_threads is not None and self.torch_threads < 1:
            raise ValueError(f"torch_threads must be >= 1, got {self.torch_threads}")
        if self.policy is None:
            self.policy = ACTSRConfig()
        if not isinstance(self.policy, ACTSRConfig):
            raise ValueError(f"sr-train trains ACT-SR policies (--policy.type=act_sr), got {self.policy.type!r}")
        check_shared_settings(self, ACTSubstrate.name)
        fold_alias_settings(self)  # policy.sleep is sleep.enabled, policy.sleep_memory_size memory.buffer_size
        self.output_dir = Path(self.output_dir)
        check_finite(self)  # every numeric setting (policy, wake, eval), before anything is written
        check_policy_ranges(self.policy)
        methods = methods_for(ACTSubstrate.name)
        if self.method not in methods:
            raise ValueError(f"method: unknown method {self.method!r}; choose from {methods}")


POLICY_RANGES: dict[str, tuple[str, Callable[[Any], bool]]] = {
    "optimizer_lr": ("> 0", lambda v: v > 0),
    "optimizer_lr_backbone": ("> 0", lambda v: v > 0),
    "optimizer_weight_decay": (">= 0", lambda v: v >= 0),
    "kl_weight": (">= 0", lambda v: v >= 0),
    "dropout": ("in [0, 1)", lambda v: 0 <= v < 1),
    "dim_model": (">= 1", lambda v: v >= 1),
    "n_heads": (">= 1", lambda v: v >= 1),
    "dim_feedforward": (">= 1", lambda v: v >= 1),
    "n_encoder_layers": (">= 1", lambda v: v >= 1),
    "n_decoder_layers": (">= 1", lambda v: v >= 1),
    "n_vae_encoder_layers": (">= 1", lambda v: v >= 1),
    "latent_dim": (">= 1", lambda v: v >= 1),
    "chunk_size": (">= 1", lambda v: v >= 1),
    "n_action_steps": (">= 1", lambda v: v >= 1),
}
"""Ranges of ACT's numeric settings that LeRobot checks only when the optimizer or the model is built (after a
run has written its first files): checked at parse time instead, named with their ``policy.`` prefix."""


def check_policy_ranges(policy: Any) -> None:
    """``ValueError`` naming every ``policy.<key>`` outside :data:`POLICY_RANGES` (one line)."""
    bad = [f"policy.{key} must be {rule}, got {getattr(policy, key)!r}" for key, (rule, ok) in POLICY_RANGES.items()
           if not ok(getattr(policy, key))]
    if bad:
        raise ValueError("; ".join(bad))


def _config_dict(cfg: TrainStreamConfig) -> dict[str, Any]:
    """The whole configuration as JSON data (what ``train_config.json`` holds; draccus reads it back)."""
    out = to_jsonable(cfg)
    out["policy"]["type"] = cfg.policy.type  # draccus' choice key (not a dataclass field)
    out["torch_threads"] = resolved_torch_threads(cfg)  # the number in effect, stored and fingerprinted
    return out


def resolved_torch_threads(cfg: TrainStreamConfig) -> int:
    """``cfg.torch_threads``, or torch's current intra-op thread count when it is not set."""
    return int(cfg.torch_threads) if cfg.torch_threads is not None else torch.get_num_threads()


RESUME_ALLOW_LIST: dict[str, str] = {
    "output_dir": "where the run is, not what it computes: a copied run directory resumes where it is",
    "resume": "the per-invocation flag that asks for this check",
    "overwrite": "per invocation (it excludes --resume, and a fresh run has nothing to compare with)",
    "allow_unhashed_inputs": "per invocation: whether an old run without dataset fingerprints may resume",
    "stream.dataset_root": "where the datasets are, not what they hold: each dataset is identified by the content "
                           "digest of its files (inputs.datasets.<skill>), so a moved dataset, or the same one given "
                           "as an absolute path, resumes, and other data under the same path is refused",
    "stream.dataset_paths": "as stream.dataset_root",
    "progress": "console progress bars only",
    "wandb": "experiment tracking only (the run log mirrored to Weights & Biases)",
    "eval.videos_per_skill": "which evaluation episodes are also rendered to mp4: the recording env is another "
                             "instance reset with the same seed and rendering only reads the scene (outcomes, "
                             "agent_pos and image observations are identical, checked on the needle env with "
                             "64x64 images and 240x320 / 720x1280 videos)",
    "eval.video_height": "video frame size only (see eval.videos_per_skill)",
    "eval.video_width": "video frame size only (see eval.videos_per_skill)",
    "wake.num_workers": "DataLoader worker processes: sampling and its seed draw stay in the main process (torch "
                        "draws the worker base seed with or without workers) and the in-memory dataset has no "
                        "randomness, so the batches are the same (tests/imitation/test_resume_settings.py resumes "
                        "with workers and gets bit-identical weights)",
    "policy.input_features": "derived from the stream's first dataset at set-up (any given value is overwritten); "
                             "the datasets are inputs, not settings",
    "policy.output_features": "as policy.input_features",
    "policy.sleep": "another name of sleep.enabled, which is fingerprinted: folded into it at parse time and always "
                    "null in a parsed config (stream.config.POLICY_ALIASES)",
    "policy.sleep_memory_size": "another name of memory.buffer_size, as policy.sleep",
}
"""Settings of ``sr-train`` that may differ on ``--resume`` (fnmatch patterns, each covering the keys below it),
with the reason each cannot change results. Every other setting of :class:`TrainStreamConfig`, the whole
``--policy.*`` included, is fingerprinted at the run's start (``settings_fingerprint.json``) and must be equal on
resume; the check runs before anything is written (:meth:`StreamTrainer._prepare_output_dir`)."""


def stream_inputs(cfg: TrainStreamConfig) -> dict[str, str]:
    """The content digest of every skill's dataset (:mod:`sr_imitation.imitation.dataset_identity`)."""
    return dataset_inputs(cfg.stream.skills, [cfg.stream.dataset_path(i) for i in range(len(cfg.stream.skills))])


def resume_fingerprint(cfg: TrainStreamConfig, inputs: dict[str, str] | None = None) -> SettingsFingerprint:
    """The settings of ``cfg`` that a resume must keep (everything but :data:`RESUME_ALLOW_LIST`), plus the method's
    own settings with their defaults (``method_config``, :func:`~sr_imitation.stream.methods.method_config`) and the
    datasets' content digests (``inputs.datasets.<skill>``; computed from ``cfg`` unless given)."""
    inputs = stream_inputs(cfg) if inputs is None else inputs
    return settings_fingerprint(_config_dict(cfg), RESUME_ALLOW_LIST,
                                {"method_config": method_config(cfg.method, cfg.method_options),
                                 "inputs": {"datasets": inputs}})


def stored_config_dict(cfg: TrainStreamConfig) -> dict[str, Any]:
    """``train_config.json``: the whole config without the per-invocation flags and with ``output_dir`` "."
    (the directory holding the file), so the file never names the run's absolute location."""
    out = {k: v for k, v in _config_dict(cfg).items() if k not in ("resume", "overwrite")}
    out["output_dir"] = RUN_DIRECTORY
    return out


class StreamTrainer:
    """Runs (or resumes) one stream: the engine (:class:`~sr_imitation.stream.StreamEngine`) with the ACT substrate
    and ``cfg.method``. ``after_phase(k, phase)`` (tests) is called after each newly completed phase."""

    def __init__(self, cfg: TrainStreamConfig, make_env: EnvFactory | None = None,
                 after_phase: Callable[[int, str], None] | None = None) -> None:
        self.cfg = cfg
        self.out = cfg.output_dir
        self.substrate = ACTSubstrate(cfg, make_env)
        self.method = make_method(cfg.method, ACTSubstrate.name, self.substrate.method_settings())
        inputs = stream_inputs(cfg)
        paths = {s: cfg.stream.dataset_path(i) for i, s in enumerate(cfg.stream.skills)}
        self.run_dir = RunDirectory(
            self.out, resume_fingerprint(cfg, inputs), "train_config.json", stored_config_dict(cfg), cfg.resume,
            cfg.overwrite,
            check_inputs=lambda path, stored: check_inputs(path, stored, inputs, paths, cfg.allow_unhashed_inputs))
        self.after_phase = after_phase

    @property
    def policy(self) -> Any:
        return self.substrate.policy

    def _prepare_output_dir(self) -> None:
        self.run_dir.prepare()

    def _check_resume_settings(self, fingerprint: SettingsFingerprint) -> bool:
        """Compare ``fingerprint`` with the run's stored settings (see :class:`RunDirectory`)."""
        self.run_dir.fingerprint = fingerprint
        return self.run_dir._check_settings()

    def run(self, stop_after: int | None = None) -> dict[str, Any]:
        """Run every pending phase; with ``stop_after=k`` stop after stage k (1-based) and return ``progress``
        instead of the final report (partial runs, e.g. the sleep replays of ``experiments.sleep_replay``)."""
        check_stream_datasets(self.cfg.stream, self.substrate.policy_cfg.use_images)  # before anything is written
        check_evaluation_envs(self.cfg.stream.skills, custom_env=self.substrate._make_env is not None)
        engine = StreamEngine(self.substrate, self.method, self.run_dir, self.cfg.progress, self.after_phase,
                              wandb=self.cfg.wandb, log_config=stored_config_dict(self.cfg),
                              extend_from=self.cfg.stream.extend_from)
        return engine.run(stop_after)


def check_evaluation_envs(skills: list[str], custom_env: bool) -> None:
    """Every skill resolves to its evaluation environment before the first gradient: with the needle environment
    (the default), every skill must be a needle skill. ``ValueError`` naming ``stream.skills`` and the valid names."""
    unknown = [s for s in skills if s not in SURGICAI_SKILLS]
    if unknown and not custom_env:
        raise ValueError(f"stream.skills: {unknown} have no evaluation environment (the needle environment has "
                         f"{list(SURGICAI_SKILLS)}); every skill needs a dataset and an environment")


def train_stream(cfg: TrainStreamConfig, make_env: EnvFactory | None = None) -> dict[str, Any]:
    """Run or resume the stream described by ``cfg``; returns the results dictionary."""
    return StreamTrainer(cfg, make_env).run()
