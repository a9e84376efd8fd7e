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
from sr_imitation.imitation.data import STATS_SOURCES, cached_dataset_path, check_stream_datasets
from sr_imitation.imitation.dataset_identity import check_inputs, dataset_inputs
from sr_imitation.imitation.evaluate import (
    EnvFactory,
    EvalConfig,
    check_env_features,
    check_env_renders,
    make_env_factory,
    resolve_eval_env,
)
from sr_imitation.imitation.hub import check_push, push_policy
from sr_imitation.imitation.substrate import TRAIN_CONFIG_FILE, ACTSubstrate, seed_everything, stage_name
from sr_imitation.imitation.wake import WakeConfig
from sr_imitation.stream import RunDirectory, StreamEngine, make_method, method_config, methods_for
from sr_imitation.stream.config import check_shared_settings, fold_alias_settings
from sr_imitation.stream.rundir import point_last

__all__ = ["RESUME_ALLOW_LIST", "SETTINGS_ADDED", "StreamConfig", "StreamTrainer", "TrainStreamConfig",
           "check_evaluation_envs", "resume_fingerprint", "seed_everything", "stage_name", "stored_config_dict",
           "train_stream"]

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
        LeRobot cache (:class:`~sr_imitation.imitation.data.DatasetMismatchError` naming the repo_id and the path
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
        if self.policy.use_amp:  # LeRobot itself refuses it on CPU at parse time; on a GPU it would be ignored
            raise ValueError("policy.use_amp: mixed precision is not implemented in sr-train's wake and sleep yet "
                             "(it would be silently ignored); run without it")
        self.eval.check_skills(self.stream.skills)  # one gym id / LeRobot task per skill
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


SETTINGS_ADDED: dict[str, Any] = {
    "eval.env": "needle",
    "eval.gym_ids": None,
    "eval.env_type": None,
    "eval.env_tasks": None,
    "eval.env_options": {},
}
"""Fingerprinted settings added after runs were first fingerprinted, with the value every run that predates them had
(the needle environment, issue 27): a stored fingerprint without one of them resumes with that value and is refused
with another (:attr:`~sr_imitation.core.fingerprint.SettingsFingerprint.added`)."""


def stream_inputs(cfg: TrainStreamConfig) -> dict[str, str]:
    """The content digest of every skill's dataset (:mod:`sr_imitation.imitation.dataset_identity`)."""
    return dataset_inputs(cfg.stream.skills, [cfg.stream.dataset_path(i) for i in range(len(cfg.stream.skills))])


def inputs_check(cfg: TrainStreamConfig, inputs: dict[str, str]) -> Callable[[Path, Any], None]:
    """The resume check of ``cfg``'s datasets against a stored fingerprint (``RunDirectory``'s ``check_inputs``)."""
    paths = {s: cfg.stream.dataset_path(i) for i, s in enumerate(cfg.stream.skills)}
    return lambda path, stored: check_inputs(path, stored, inputs, paths, cfg.allow_unhashed_inputs)


def resume_fingerprint(cfg: TrainStreamConfig, inputs: dict[str, str] | None = None) -> SettingsFingerprint:
    """The settings of ``cfg`` that a resume must keep (everything but :data:`RESUME_ALLOW_LIST`), plus the method's
    own settings with their defaults (``method_config``, :func:`~sr_imitation.stream.methods.method_config`) and the
    datasets' content digests (``inputs.datasets.<skill>``; computed from ``cfg`` unless given)."""
    inputs = stream_inputs(cfg) if inputs is None else inputs
    return settings_fingerprint(_config_dict(cfg), RESUME_ALLOW_LIST,
                                {"method_config": method_config(cfg.method, cfg.method_options),
                                 "inputs": {"datasets": inputs}}, added=SETTINGS_ADDED)


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
        stored = stored_config_dict(cfg)
        self.run_dir = RunDirectory(self.out, resume_fingerprint(cfg, inputs), TRAIN_CONFIG_FILE, stored,
                                    cfg.resume, cfg.overwrite, check_inputs=inputs_check(cfg, inputs))
        self.substrate.train_config = stored
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
        # before anything is written
        _, inputs, outputs = check_stream_datasets(self.cfg.stream, self.substrate.policy_cfg.use_images)
        check_evaluation_envs(self.cfg, inputs, outputs, custom_env=self.substrate._make_env is not None)
        check_push(self.cfg.policy)  # --policy.push_to_hub: reachable, or one line now rather than after training
        engine = StreamEngine(self.substrate, self.method, self.run_dir, self.cfg.progress, self._after_phase,
                              wandb=self.cfg.wandb, log_config=stored_config_dict(self.cfg),
                              extend_from=self.cfg.stream.extend_from)
        self._final_phase = engine.final_phase
        results = engine.run(stop_after)
        self._point_last()  # also when a resume found every phase done (killed between a phase and its pointer)
        if stop_after is None and self.cfg.policy.push_to_hub:
            last = len(self.cfg.stream.skills) - 1
            pretrained = self.substrate.checkpoint_dir(last, engine.final_phase(last)) / "pretrained_model"
            push_policy(self.substrate.policy, pretrained,
                        [self.cfg.stream.repo_id(i) for i in range(len(self.cfg.stream.skills))])
        return results


    def _after_phase(self, k: int, phase: str) -> None:
        if phase == self._final_phase(k):
            self._point_last()
        if self.after_phase is not None:
            self.after_phase(k, phase)

    def _point_last(self) -> None:
        """``<output_dir>/last`` -> the newest stage's consolidated checkpoint (its final phase) recorded so far."""
        done = [k for k in range(len(self.cfg.stream.skills)) if self.run_dir.done(k, self._final_phase(k))]
        if done:
            point_last(self.out, self.substrate.checkpoint_dir(done[-1], self._final_phase(done[-1])))


def check_evaluation_envs(cfg: TrainStreamConfig, input_features: dict[str, Any], output_features: dict[str, Any],
                          custom_env: bool = False) -> None:
    """Every skill resolves to its evaluation environment before the first gradient (``--eval.env``).

    ``needle``: every skill must be a needle skill (``ValueError`` naming ``stream.skills`` and the valid names).
    ``gym`` / ``lerobot``: every gym id must be registered (its namespace module imported if needed), the LeRobot
    env type known and its config valid for each task; then each environment is built once, its action space and a
    reset observation must fit the policy's features (``input_features``, ``output_features``: those of the
    datasets) and, with videos, its recording twin must render ``rgb_array`` frames. ``ValueError`` naming the key
    (``eval.gym_ids[i]``, ``eval.env_type``, ``eval.env_tasks[i]``). ``none``: nothing to check. A factory given
    to :class:`StreamTrainer` (``custom_env``, tests) replaces the environment ``--eval.env`` names."""
    mode, skills = cfg.eval.env, list(cfg.stream.skills)
    if mode == "none" or custom_env:
        return
    if mode == "needle":
        unknown = [s for s in skills if s not in SURGICAI_SKILLS]
        if unknown:
            raise ValueError(f"stream.skills: {unknown} have no evaluation environment (the needle environment has "
                             f"{list(SURGICAI_SKILLS)}); every skill needs a dataset and an environment: evaluate "
                             "them with --eval.env=gym|lerobot or switch evaluation off with --eval.env=none")
        return
    make_env = make_env_factory(cfg.eval, skills, None)  # only the needle env takes the image size
    if make_env is None:
        return
    for index, skill in enumerate(skills):
        where = resolve_eval_env(cfg.eval, skills, index)
        for with_video in (False, True) if cfg.eval.videos_per_skill > 0 else (False,):
            try:
                env = make_env(skill, with_video)
            except ValueError as exc:
                raise ValueError(f"{where}: {exc}") from None
            except Exception as exc:  # noqa: BLE001 - whatever the environment's constructor raises
                first = str(exc).splitlines()[0] if str(exc) else ""
                raise ValueError(f"{where}: cannot build it ({type(exc).__name__}: {first})") from exc
            try:
                if with_video:
                    check_env_renders(env, where)
                else:
                    check_env_features(env, input_features, output_features, where)
            finally:
                env.close()


def train_stream(cfg: TrainStreamConfig, make_env: EnvFactory | None = None) -> dict[str, Any]:
    """Run or resume the stream described by ``cfg``; returns the results dictionary."""
    return StreamTrainer(cfg, make_env).run()
