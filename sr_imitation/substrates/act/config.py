"""The configuration of ``sr-train`` on the imitation substrate, and what a run stores and fingerprints of it.

:class:`TrainStreamConfig` (with :class:`StreamConfig` and :class:`MemoryConfig`), what a resume may change
(:data:`RESUME_ALLOW_LIST`), the settings added since runs were first written (:data:`SETTINGS_ADDED`), the run's
fingerprint (:func:`resume_fingerprint`, datasets by content), its stored config (:func:`stored_config_dict`), and
an ``sr-main`` preset's config (:class:`MainJobConfig`: recording plus the stream). The
runner is :mod:`sr_imitation.substrates.act.trainer`; the substrate (:mod:`sr_imitation.substrates.act.substrate`) reads
this module, never the runner.
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
from sr_imitation.envs.needle.skills import SKILL_NAMES as SURGICAI_SKILLS
from sr_imitation.infra.fingerprint import (
    RUN_DIRECTORY,
    STACK_KEY,
    SettingsFingerprint,
    check_finite,
    settings_fingerprint,
    to_jsonable,
)
from sr_imitation.lerobot_compat import LEGACY_TAG, lerobot_version
from sr_imitation.recorders.needle import RecordConfig
from sr_imitation.stream import method_class, method_config
from sr_imitation.stream.config import (
    RunConfig,
    StreamSettings,
    StreamSleepConfig,
    check_shared_settings,
    fold_alias_settings,
)
from sr_imitation.substrates.act.data import STATS_SOURCES, cached_dataset_path
from sr_imitation.substrates.act.dataset_identity import check_inputs, dataset_inputs
from sr_imitation.substrates.act.evaluate import EvalConfig
from sr_imitation.substrates.act.report import PAIR_LISTS
from sr_imitation.substrates.act.wake import WakeConfig

logger = logging.getLogger(__name__)

SUBSTRATE = "act"
"""The substrate's registry name (``ACTSubstrate.name``; methods name it in ``ContinualMethod.substrates``)."""


@dataclass
class SurgicAISleepConfig(StreamSleepConfig):
    """The ACT substrate's sleep preset: :class:`~sr_imitation.stream.config.StreamSleepConfig` with the defaults of
    the paper's Table "Sleep-consolidation hyperparameters for SurgicAI" (Adam 1e-5, at most 1000 iterations, batch
    8, 5 Frank-Wolfe iterations for ``nash_fw``, window 50, anchor always on, also after the final skill). A class of
    its own, not a factory: draccus fills the fields a config file or flag leaves out from the class defaults, so
    ``--sleep.lr=1e-4`` must not bring back MT5's."""

    lr: float = 1e-5
    """Adam learning rate eta_sleep (SurgicAI table - 1e-5)."""
    max_iterations: int = 1000
    """N_sleep, iterations per sleep at most (SurgicAI table - 1000)."""
    batch_size: int = 8
    """Samples drawn from each memory per iteration (SurgicAI table - 8)."""
    fw_iterations: int = 5
    """Frank-Wolfe iterations per solve of nash_fw (SurgicAI table - 5); nash stops at its tolerance."""
    early_stop_window: int = 50
    """Window length in iterations of the plateau rule (SurgicAI table - 50)."""
    anchor_tau: float | None = None
    """tau of the anchor gate (Eq. 2); null - always on (the SurgicAI setting)."""
    anchor_after_final: bool = True
    """Apply the anchor in the sleep after the final skill (SurgicAI - yes)."""


@dataclass
class StreamConfig(StreamSettings):
    """The skill stream: an ordered list of skills, one LeRobot dataset each.

    Each field is documented below (``--help`` shows it).
    """

    skills: list[str] = field(default_factory=lambda: list(SURGICAI_SKILLS))
    """Stream order (default - approach, place, insert, regrasp, pullout)."""
    dataset_root: Path = Path("datasets/needle")
    """Datasets live at <dataset_root>/<skill>, as sr-record writes them ..."""
    dataset_paths: list[Path] | None = None
    """... unless listed here, one path per skill ..."""
    repo_ids: list[str] | None = None
    """... or here, one LeRobot repo_id per skill (e.g. [user/pick,user/place]), each found where LeRobotDataset
    keeps it: $HF_LEROBOT_HOME/<repo_id> (default ~/.cache/huggingface/lerobot/<repo_id>). Offline: nothing is
    downloaded, a repo_id not in the cache is refused. Excludes dataset_paths."""
    repo_id_prefix: str = "local/sr_needle"
    """LeRobot repo_id label <prefix>_<skill> of datasets given by path (local datasets; nothing is downloaded)."""
    video_backend: str = "pyav"
    """Decoder for video datasets (pyav - torchcodec does not load here)."""
    pairs: str = "surgicai"
    """PRS pair list - surgicai (the paper's seven needle pairs), mt5 (the paper's six MT5 pairs, for Meta-World
    skills), all or adjacent."""
    stats: str = "seen"
    """Normalization statistics - seen (default - the skills seen so far, updated at each wake; the policy and the
    memories' targets are re-expressed when they change; what a continual learner may use), first (the first skill's
    dataset for the whole stream; later skills may lie far outside it) or union (all the stream's datasets, read
    before the first wake - future skills' data, which a continual learner may not read; measured better than seen
    on the needle stream, docs/RESULTS.md: use it when every skill's dataset is at hand from the start); see
    sr_imitation.substrates.act.data."""
    stats_min_std: float = 1e-2
    """Floor on every standard deviation of the stream's statistics (a constant dimension stays constant)."""
    reexpress_inputs: bool = True
    """Under stats=seen, when the statistics change: true (default) re-expresses the policy's input layers with its
    action head, exactly (the same actions; the input weights grow as the statistics widen); false re-expresses the
    action head only, so earlier skills' inputs read differently until the memories bring them back (exploratory,
    docs/RESULTS.md, 'The normalization default measured')."""

    def __post_init__(self) -> None:
        if not self.skills:
            raise ValueError("stream.skills: the stream needs at least one skill")
        if len(set(self.skills)) != len(self.skills):
            repeated = sorted({s for s in self.skills if self.skills.count(s) > 1})
            raise ValueError(f"stream.skills must be distinct, got {self.skills} ({repeated} more than once)")
        if self.pairs not in PAIR_LISTS:
            raise ValueError(f"stream.pairs must be one of {PAIR_LISTS}, got {self.pairs!r}")
        if self.stats not in STATS_SOURCES:
            raise ValueError(f"stream.stats must be one of {STATS_SOURCES}, got {self.stats!r}")
        if not self.reexpress_inputs and self.stats != "seen":
            raise ValueError(f"stream.reexpress_inputs=false acts only when the statistics change "
                             f"(--stream.stats=seen), got --stream.stats={self.stats}")
        if self.dataset_paths is not None and len(self.dataset_paths) != len(self.skills):
            raise ValueError(f"{len(self.dataset_paths)} dataset_paths for {len(self.skills)} skills")
        if self.repo_ids is not None:
            if self.dataset_paths is not None:
                raise ValueError("stream.repo_ids and stream.dataset_paths both name the datasets; give one of them")
            if len(self.repo_ids) != len(self.skills):
                raise ValueError(f"stream.repo_ids: {len(self.repo_ids)} repo_ids for {len(self.skills)} skills "
                                 f"{self.skills}; give one per skill, in stream order")
            for i, repo_id in enumerate(self.repo_ids):
                parts = str(repo_id).split("/")
                if not str(repo_id).strip() or str(repo_id).startswith("/") or ".." in parts or "" in parts:
                    raise ValueError(f"stream.repo_ids[{i}]: {repo_id!r} is not a repo_id (<user>/<name>, a path "
                                     "below $HF_LEROBOT_HOME; local paths go to stream.dataset_paths)")

    def dataset_path(self, index: int) -> Path:
        """Skill ``index``'s dataset directory: listed in ``dataset_paths``, resolved from ``repo_ids`` in the local
        LeRobot cache (:class:`~sr_imitation.substrates.act.data.DatasetMismatchError` naming the repo_id and the path
        looked at when it is not there), or ``<dataset_root>/<skill>``."""
        if self.dataset_paths is not None:
            return Path(self.dataset_paths[index])
        if self.repo_ids is not None:
            return cached_dataset_path(self.repo_ids[index], f"stream.repo_ids[{index}]")
        return Path(self.dataset_root) / self.skills[index]

    def repo_id(self, index: int) -> str:
        """The LeRobot repo_id of skill ``index``'s dataset (``repo_ids``, or the label ``<prefix>_<skill>``)."""
        if self.repo_ids is not None and self.dataset_paths is None:
            return self.repo_ids[index]
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
class TrainStreamConfig(RunConfig):
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
    output_dir: Path = Path("outputs/needle_stream")
    """Run directory (refused if it exists, unless --resume or --overwrite)."""
    seed: int = 1000
    """Training seed - every phase seeds its generators from it."""
    allow_unhashed_inputs: bool = False
    """Resume a run started before datasets were fingerprinted by content, without checking its data (you vouch
    that the datasets are unchanged; a run that has the fingerprints always checks them)."""
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
        check_shared_settings(self, SUBSTRATE)
        fold_alias_settings(self)  # policy.sleep is sleep.enabled, policy.sleep_memory_size memory.buffer_size
        self.output_dir = Path(self.output_dir)
        check_finite(self)  # every numeric setting (policy, wake, eval), before anything is written
        check_policy_ranges(self.policy)
        if self.policy.use_amp and str(self.policy.device).startswith("cuda") and not torch.cuda.is_bf16_supported():
            raise ValueError("policy.use_amp: sr-train's mixed precision is bfloat16 autocast (no fp16 loss scaling) "
                             "and this GPU has no bfloat16; run without it")
        self.eval.check_skills(self.stream.skills)  # one gym id / LeRobot task per skill
        method_class(self.method, SUBSTRATE)  # what the method asks of the substrate: checked when the run is built


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
    "stream.repo_ids": "as stream.dataset_root: a repo_id only says where in the local LeRobot cache the dataset is "
                       "($HF_LEROBOT_HOME/<repo_id>, nothing is downloaded) and is LeRobot's label of it, used in no "
                       "computation; the dataset is identified by its content digest, so the same data under another "
                       "repo_id, cache or path resumes and other data under the same repo_id is refused",
    "progress": "console progress bars only",
    "wandb": "experiment tracking only (the run log mirrored to Weights & Biases)",
    "eval.videos_per_skill": "which evaluation episodes are also rendered to mp4: the recording env is another "
                             "instance reset with the same seed and rendering only reads the scene (outcomes, "
                             "agent_pos and image observations are identical, checked on the needle env with "
                             "64x64 images and 240x320 / 720x1280 videos)",
    "eval.video_height": "video frame size only (see eval.videos_per_skill)",
    "eval.video_width": "video frame size only (see eval.videos_per_skill)",
    "wake.snapshot_every_s": "when a wake writes its snapshot: writing one reads the state and draws nothing, and a "
                             "resumed wake continues bit for bit (tests/substrates/act/test_wake_snapshot.py)",
    "wake.num_workers": "DataLoader worker processes: sampling and its seed draw stay in the main process (torch "
                        "draws the worker base seed with or without workers) and the in-memory dataset has no "
                        "randomness, so the batches are the same (tests/substrates/act/test_resume_settings.py resumes "
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
resume; the check runs before anything is written (``RunDirectory.prepare``)."""


SETTINGS_ADDED: dict[str, Any] = {
    "eval.env": "needle",
    "eval.gym_ids": None,
    "eval.env_type": None,
    "eval.env_tasks": None,
    "eval.env_options": {},
    "stream.stats": "first",
    "stream.reexpress_inputs": True,
    "sleep.early_stop_scale": "window",  # added 2026-11-29
    "sleep.newest_guard": False,  # added 2026-12-07 (the final-sleep screening's C3)
    "stack.lerobot": "0.4.4",  # added 2026-12-07: every run before then was made with LeRobot 0.4.4
}
"""Fingerprinted settings added after runs were first fingerprinted, with the value every run that predates them had
(the needle environment): a stored fingerprint without one of them resumes with that value and is refused
with another (:attr:`~sr_imitation.infra.fingerprint.SettingsFingerprint.added`)."""


LEGACY_DEFAULTS: dict[str, Any] = {"stream.stats": "first"}
"""Settings whose default changed after runs stored their configs without them (``stream.stats``: runs before the
setting normalized with the first skill's statistics; the default is now ``seen``): a run's own config file
(``train_config.json``) that lacks one is read with this value, so it resumes and repeats as it ran."""


def stream_inputs(cfg: TrainStreamConfig) -> dict[str, str]:
    """The content digest of every skill's dataset (:mod:`sr_imitation.substrates.act.dataset_identity`)."""
    return dataset_inputs(cfg.stream.skills, [cfg.stream.dataset_path(i) for i in range(len(cfg.stream.skills))])


def inputs_check(cfg: TrainStreamConfig, inputs: dict[str, str]) -> Callable[[Path, Any], None]:
    """The resume check of ``cfg``'s datasets against a stored fingerprint (``RunDirectory``'s ``check_inputs``)."""
    paths = {s: cfg.stream.dataset_path(i) for i, s in enumerate(cfg.stream.skills)}
    return lambda path, stored: check_inputs(path, stored, inputs, paths, cfg.allow_unhashed_inputs)


def stack() -> dict[str, str]:
    """The library versions a run's numbers depend on (``stack`` in its fingerprint): LeRobot's (0.6 changed ACT's
    loss and the recorded image statistics)."""
    return {"lerobot": lerobot_version()}


STACK_HINT = (f"a run made with LeRobot 0.4.4 continues at git tag {LEGACY_TAG} (Python 3.11, its "
              ".ci/constraints.txt; its checkpoints and datasets load here), any other in an environment with the "
              "LeRobot it names; or start a new run in another output_dir")
"""What :class:`~sr_imitation.infra.fingerprint.StackMismatchError` tells a user to do."""


def resume_fingerprint(cfg: TrainStreamConfig, inputs: dict[str, str] | None = None) -> SettingsFingerprint:
    """The settings of ``cfg`` that a resume must keep (everything but :data:`RESUME_ALLOW_LIST`), plus the method's
    own settings with their defaults (``method_config``, :func:`~sr_imitation.stream.methods.method_config`) and the
    datasets' content digests (``inputs.datasets.<skill>``; computed from ``cfg`` unless given)."""
    inputs = stream_inputs(cfg) if inputs is None else inputs
    return settings_fingerprint(_config_dict(cfg), RESUME_ALLOW_LIST,
                                {"method_config": method_config(cfg.method, cfg.method_options),
                                 "inputs": {"datasets": inputs}, STACK_KEY: stack()}, added=SETTINGS_ADDED,
                                stack_hint=STACK_HINT)


def stored_config_dict(cfg: TrainStreamConfig) -> dict[str, Any]:
    """``train_config.json``: the whole config without the per-invocation flags and with ``output_dir`` "."
    (the directory holding the file), so the file never names the run's absolute location."""
    out = {k: v for k, v in _config_dict(cfg).items() if k not in ("resume", "overwrite")}
    out["output_dir"] = RUN_DIRECTORY
    return out


@dataclass
class MainJobConfig:
    """Recording settings and the stream's settings; ``record.root`` is where the stream reads its datasets."""

    record: RecordConfig = field(default_factory=RecordConfig)
    """Recording of the scripted-expert demonstrations (sr-record's flags under --record.)."""
    train: TrainStreamConfig = field(default_factory=TrainStreamConfig)
    """The wake-sleep stream (sr-train's flags under --train.)."""
    expert_video: bool = True
    """Also write a full-suture video of the scripted expert (expert_suture.mp4) to train.output_dir."""

    def __post_init__(self) -> None:
        given = Path(self.train.stream.dataset_root)
        if given not in (Path(StreamConfig.dataset_root), Path(self.record.root)):
            raise ValueError(f"train.stream.dataset_root: {str(given)!r}, but this job reads its datasets where it "
                             f"records them (record.root: {str(self.record.root)!r}); give the folder as --record.root")
        self.train.stream.dataset_root = self.record.root
        self.record.skills = list(self.train.stream.skills)
