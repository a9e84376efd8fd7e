"""The wake-sleep stream trainer for ACT-SR (Algorithm 1 on the imitation substrate).

For each skill k of the stream:

1. ``wake``: behaviour cloning on skill k's dataset only, plus the method's distillation from earlier memories;
   checkpoint ``skill_k_<name>/wake`` (LeRobot layout, loadable by ``lerobot-eval --policy.path``);
2. ``memory``: the frozen actor memory M_k (``memories/skill_k_<name>.safetensors``);
3. ``wake.eval``: success on every skill learned so far, trajectories for SPI, a few rollout videos;
4. ``sleep`` (k >= 2, if the method sleeps): Nash-bargained consolidation over M_1..M_k with the anchor toward
   the previous consolidated checkpoint; checkpoint ``skill_k_<name>/sleep`` and its diagnostics;
5. ``sleep.eval``.

Every step is recorded in ``progress.json`` only after its outputs are completely and atomically written, and
every step seeds its own random generators from (run seed, skill, step). A run killed at any point and
restarted with ``--resume=true`` therefore redoes at most the interrupted step and, on CPU, reaches the same
numbers as an uninterrupted run. Results (``results.json``, plots, a markdown table) are rebuilt from the
recorded steps at the end.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import random
import shutil
import tempfile
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from lerobot.configs.policies import PreTrainedConfig
from lerobot.policies.factory import make_policy, make_pre_post_processors
from safetensors.torch import load_file

from lerobot_policy_act_sr import ACTSRConfig, ACTSRPolicy
from sr_imitation.core.fingerprint import (
    FINGERPRINT_FILE,
    RUN_DIRECTORY,
    SettingsFingerprint,
    check_settings,
    read_fingerprint,
    settings_fingerprint,
    settings_from_config,
    to_jsonable,
    write_fingerprint,
)
from sr_imitation.core.io import CorruptFileError, atomic_write_json, read_json
from sr_imitation.core.memory import Memory, load_memory
from sr_imitation.core.metrics import SURGICAI_SKILLS
from sr_imitation.core.sleep import sleep_consolidate
from sr_imitation.imitation.actor_memory import ActorMemory
from sr_imitation.imitation.data import (
    check_stream_datasets,
    load_metadata,
    load_skill_data,
    load_stats,
    policy_features,
    sample_observation_buffer,
    save_stats,
    stream_stats,
)
from sr_imitation.imitation.evaluate import EnvFactory, EvalConfig, evaluate_skills, needle_env_factory
from sr_imitation.imitation.methods import make_method
from sr_imitation.imitation.report import write_report
from sr_imitation.imitation.wake import WakeConfig, wake_train

logger = logging.getLogger(__name__)

PROGRESS_VERSION = 1
PHASE_IDS = {"wake": 0, "memory": 1, "wake.eval": 2, "sleep": 3, "sleep.eval": 4}


@dataclass
class StreamConfig:
    """The skill stream: an ordered list of skills, one LeRobot dataset each.

    Attributes:
        skills: stream order (default: approach, place, insert, regrasp, pullout).
        dataset_root: datasets live at ``<dataset_root>/<skill>`` (as ``sr-record`` writes them) ...
        dataset_paths: ... unless listed explicitly here, one path per skill.
        repo_id_prefix: LeRobot ``repo_id`` label ``<prefix>_<skill>`` (local datasets; nothing is downloaded).
        video_backend: decoder for video datasets (``pyav``: torchcodec does not load here).
        pairs: PRS pair list, ``surgicai`` (the paper's seven), ``all`` or ``adjacent``.
        stats_min_std: floor on the fixed stream statistics' standard deviations.
    """

    skills: list[str] = field(default_factory=lambda: list(SURGICAI_SKILLS))
    dataset_root: Path = Path("datasets/needle")
    dataset_paths: list[Path] | None = None
    repo_id_prefix: str = "local/sr_needle"
    video_backend: str = "pyav"
    pairs: str = "surgicai"
    stats_min_std: float = 1e-2

    def __post_init__(self) -> None:
        if not self.skills:
            raise ValueError("the stream needs at least one skill")
        if len(set(self.skills)) != len(self.skills):
            raise ValueError(f"skills must be distinct, got {self.skills}")
        if self.dataset_paths is not None and len(self.dataset_paths) != len(self.skills):
            raise ValueError(f"{len(self.dataset_paths)} dataset_paths for {len(self.skills)} skills")

    def dataset_path(self, index: int) -> Path:
        if self.dataset_paths is not None:
            return Path(self.dataset_paths[index])
        return Path(self.dataset_root) / self.skills[index]

    def repo_id(self, index: int) -> str:
        return f"{self.repo_id_prefix}_{self.skills[index]}"


@dataclass
class TrainStreamConfig:
    """``sr-train`` configuration (draccus: ``--policy.type=act_sr --policy.sleep=true --stream.skills=[...]``)."""

    policy: PreTrainedConfig | None = None
    stream: StreamConfig = field(default_factory=StreamConfig)
    wake: WakeConfig = field(default_factory=WakeConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    method: str = "sr"
    output_dir: Path = Path("outputs/needle_stream")
    seed: int = 1000
    resume: bool = False
    overwrite: bool = False
    progress: bool = True

    def __post_init__(self) -> None:
        if self.policy is None:
            self.policy = ACTSRConfig()
        if not isinstance(self.policy, ACTSRConfig):
            raise ValueError(f"sr-train trains ACT-SR policies (--policy.type=act_sr), got {self.policy.type!r}")
        if self.resume and self.overwrite:
            raise ValueError("--resume and --overwrite exclude each other")
        self.output_dir = Path(self.output_dir)


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def stage_name(index: int, skill: str) -> str:
    return f"skill_{index + 1}_{skill}"


def _config_dict(cfg: TrainStreamConfig) -> dict[str, Any]:
    """The whole configuration as JSON data (what ``train_config.json`` holds; draccus reads it back)."""
    out = to_jsonable(cfg)
    out["policy"]["type"] = cfg.policy.type  # draccus' choice key (not a dataclass field)
    return out


RESUME_ALLOW_LIST: dict[str, str] = {
    "output_dir": "where the run is, not what it computes: a copied run directory resumes where it is",
    "resume": "the per-invocation flag that asks for this check",
    "overwrite": "per invocation (it excludes --resume, and a fresh run has nothing to compare with)",
    "progress": "console progress bars only",
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
}
"""Settings of ``sr-train`` that may differ on ``--resume`` (fnmatch patterns, each covering the keys below it),
with the reason each cannot change results. Every other setting of :class:`TrainStreamConfig`, the whole
``--policy.*`` included, is fingerprinted at the run's start (``settings_fingerprint.json``) and must be equal on
resume; the check runs before anything is written (:meth:`StreamTrainer._prepare_output_dir`)."""


def resume_fingerprint(cfg: TrainStreamConfig) -> SettingsFingerprint:
    """The settings of ``cfg`` that a resume must keep (everything but :data:`RESUME_ALLOW_LIST`)."""
    return settings_fingerprint(_config_dict(cfg), RESUME_ALLOW_LIST)


def stored_config_dict(cfg: TrainStreamConfig) -> dict[str, Any]:
    """``train_config.json``: the whole config without the per-invocation flags and with ``output_dir`` "."
    (the directory holding the file), so the file never names the run's absolute location."""
    out = {k: v for k, v in _config_dict(cfg).items() if k not in ("resume", "overwrite")}
    out["output_dir"] = RUN_DIRECTORY
    return out


class StreamTrainer:
    """Runs (or resumes) one stream; see the module docstring for the steps and files."""

    def __init__(self, cfg: TrainStreamConfig, make_env: EnvFactory | None = None) -> None:
        self.cfg = cfg
        self.out = cfg.output_dir
        self.policy_cfg: ACTSRConfig = cfg.policy  # type: ignore[assignment]
        self.method = make_method(cfg.method, self.policy_cfg)
        self.skills = list(cfg.stream.skills)
        self._make_env = make_env
        self.progress: dict[str, Any] = {"version": PROGRESS_VERSION, "completed": {}}
        self.memories: list[Memory] = []

    # -- set-up --------------------------------------------------------------------------------------
    def _prepare_output_dir(self) -> None:
        """Fresh run: create the directory, then write the settings fingerprint and ``train_config.json`` (once).
        Resume: check the requested settings against the stored fingerprint and read ``progress.json``, writing
        nothing (a refused resume leaves the directory byte-identical; the stored config is never rewritten)."""
        fingerprint = resume_fingerprint(self.cfg)
        exists = self.out.exists() and any(self.out.iterdir())
        if exists and self.cfg.overwrite:
            logger.warning("--overwrite: removing %s", self.out)
            shutil.rmtree(self.out)
            exists = False
        elif exists and not self.cfg.resume:
            raise FileExistsError(
                f"{self.out} already exists; pass --resume=true to continue it or --overwrite=true to replace it"
            )
        elif not exists and self.cfg.resume:
            raise FileNotFoundError(f"--resume=true but {self.out} holds no run to resume")
        if exists:
            legacy = self._check_resume_settings(fingerprint)
            progress_path = self.out / "progress.json"
            if progress_path.exists():
                try:
                    self.progress = json.loads(progress_path.read_text())
                except json.JSONDecodeError as exc:
                    raise CorruptFileError(progress_path, f"cannot resume: {exc}") from exc
            if legacy:  # a run from before fingerprints (or a sleep replay): store the checked settings once
                write_fingerprint(self.out / FINGERPRINT_FILE, fingerprint)
            return
        self.out.mkdir(parents=True, exist_ok=True)
        write_fingerprint(self.out / FINGERPRINT_FILE, fingerprint)
        atomic_write_json(self.out / "train_config.json", stored_config_dict(self.cfg))

    def _check_resume_settings(self, fingerprint: SettingsFingerprint) -> bool:
        """Compare with the stored fingerprint (or, for a run without one, its ``train_config.json``); raise
        :class:`SettingsMismatchError` naming every differing key. Returns whether the run had no fingerprint."""
        path = self.out / FINGERPRINT_FILE
        if path.is_file():
            check_settings(path, read_fingerprint(path), fingerprint)
            return False
        path = self.out / "train_config.json"
        if not path.is_file():
            raise FileNotFoundError(f"--resume=true but {self.out} holds no run to resume (no {FINGERPRINT_FILE} "
                                    "or train_config.json)")
        saved = read_json(path)
        check_settings(path, settings_from_config(saved), fingerprint)
        return True

    def _setup_policy(self) -> None:
        first_meta = load_metadata(self.cfg.stream.dataset_path(0), self.cfg.stream.repo_id(0))
        inputs, outputs = policy_features(first_meta, self.policy_cfg.use_images)
        self.policy_cfg.input_features, self.policy_cfg.output_features = inputs, outputs
        stats_path = self.out / "stream_stats.safetensors"
        if stats_path.exists():
            self.stats = load_stats(stats_path)
        else:
            self.stats = stream_stats(first_meta, inputs, self.cfg.stream.stats_min_std)
            save_stats(stats_path, self.stats)
        seed_everything(self.cfg.seed)
        self.policy: ACTSRPolicy = make_policy(self.policy_cfg, ds_meta=first_meta)  # type: ignore[assignment]
        self.preprocessor, self.postprocessor = make_pre_post_processors(self.policy_cfg, dataset_stats=self.stats)
        self.policy.set_observation_normalizer(self._normalize_raw)
        image_keys = list(self.policy_cfg.image_features)
        self.buffer_keys = [*image_keys, "observation.state"]
        size = None
        if image_keys:
            shape = self.policy_cfg.image_features[image_keys[0]].shape
            size = (int(shape[1]), int(shape[2]))
        self.make_env = self._make_env or needle_env_factory(size, self.cfg.eval)

    def _normalize_raw(self, raw: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        obs = {k: (v.float() / 255.0 if v.dtype == torch.uint8 else v) for k, v in raw.items()}
        return self.preprocessor(obs)

    # -- progress ------------------------------------------------------------------------------------
    def _key(self, index: int, phase: str) -> str:
        return f"{index + 1}.{phase}"

    def _done(self, index: int, phase: str) -> bool:
        return self._key(index, phase) in self.progress["completed"]

    def _mark(self, index: int, phase: str, record: dict[str, Any]) -> None:
        self.progress["completed"][self._key(index, phase)] = record
        atomic_write_json(self.out / "progress.json", self.progress)

    def _phase_seed(self, index: int, phase: str) -> int:
        return self.cfg.seed * 1000 + 10 * (index + 1) + PHASE_IDS[phase]

    # -- files -----------------------------------------------------------------------------------------
    def _checkpoint_dir(self, index: int, phase: str) -> Path:
        return self.out / stage_name(index, self.skills[index]) / phase

    def _memory_path(self, index: int) -> Path:
        return self.out / "memories" / f"{stage_name(index, self.skills[index])}.safetensors"

    def _save_checkpoint(self, index: int, phase: str, extra: dict[str, Any]) -> Path:
        """Write ``pretrained_model/`` (LeRobot layout) and ``extra`` JSON files to a temp dir, then rename."""
        final = self._checkpoint_dir(index, phase)
        final.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{phase}.", dir=final.parent))
        try:
            pretrained = tmp / "pretrained_model"
            self.policy.save_pretrained(pretrained)
            self.preprocessor.save_pretrained(pretrained)
            self.postprocessor.save_pretrained(pretrained)
            for name, obj in extra.items():
                atomic_write_json(tmp / name, obj)
            if final.exists():  # left by a run killed after the rename but before progress.json was written
                shutil.rmtree(final)
            os.replace(tmp, final)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        return final

    def _load_weights(self, checkpoint: Path) -> None:
        path = checkpoint / "pretrained_model" / "model.safetensors"
        if not path.is_file():
            raise FileNotFoundError(f"{path}: checkpoint recorded in progress.json is missing")
        state = load_file(str(path))
        missing, unexpected = self.policy.load_state_dict(state, strict=False)
        if missing or unexpected:
            raise CorruptFileError(path, f"weights do not match the policy (missing {missing[:5]}, "
                                         f"unexpected {unexpected[:5]})")

    def _weights_of(self, checkpoint: Path) -> list[torch.Tensor]:
        state = load_file(str(checkpoint / "pretrained_model" / "model.safetensors"))
        names = [n for n, p in self.policy.named_parameters() if p.requires_grad]
        return [state[n] for n in names]

    def _stage_final_checkpoint(self, index: int) -> Path:
        sleep = self._checkpoint_dir(index, "sleep")
        return sleep if self._done(index, "sleep") else self._checkpoint_dir(index, "wake")

    # -- phases ----------------------------------------------------------------------------------------
    def _wake(self, index: int) -> dict[str, Any]:
        skill = self.skills[index]
        data = load_skill_data(skill, self.cfg.stream.dataset_path(index), self.cfg.stream.repo_id(index),
                               self.policy_cfg, self.cfg.wake.val_fraction, self._phase_seed(index, "wake"),
                               self.cfg.stream.video_backend)
        memories, weight = self.method.wake_memories(index + 1, self.memories)
        self.policy.set_wake_memories(memories, weight, seed=self._phase_seed(index, "wake"))
        t0 = time.perf_counter()
        result = wake_train(self.policy, self.preprocessor, data, self.cfg.wake, self._phase_seed(index, "wake"),
                            self.cfg.progress)
        self.policy.set_wake_memories([], 0.0)
        history = dataclasses.asdict(result) | {"distill_weight": weight, "n_memories": len(memories)}
        self._save_checkpoint(index, "wake", {"wake_history.json": history})
        self._data = data
        return {"seconds": time.perf_counter() - t0, "epochs": result.epochs, "best_epoch": result.best_epoch,
                "best_val_l1": result.best_val_l1, "steps": result.steps}

    def _store_memory(self, index: int) -> dict[str, Any]:
        skill = self.skills[index]
        data = getattr(self, "_data", None)
        if data is None or data.skill != skill:
            data = load_skill_data(skill, self.cfg.stream.dataset_path(index), self.cfg.stream.repo_id(index),
                                   self.policy_cfg, self.cfg.wake.val_fraction, self._phase_seed(index, "wake"),
                                   self.cfg.stream.video_backend)
        buffer = sample_observation_buffer(data, self.policy_cfg.memory_buffer_size, self.buffer_keys,
                                           self._phase_seed(index, "memory"))
        snapshot = str(self._checkpoint_dir(index, "wake").relative_to(self.out))
        memory = ActorMemory.from_observations(skill, self.policy.memory_chunk, buffer, snapshot=snapshot,
                                               reduction=self.policy_cfg.distill_reduction)
        memory.save(self._memory_path(index))
        self.memories.append(memory)
        return {"bytes": memory.nbytes(), "size": memory.size}

    def _evaluate(self, index: int, phase: str) -> dict[str, Any]:
        learned = self.skills[: index + 1]
        video_dir = self.out / "videos" / stage_name(index, self.skills[index]) / phase.split(".")[0]
        t0 = time.perf_counter()
        evals = evaluate_skills(self.policy, self.preprocessor, self.postprocessor, learned,
                                list(range(index + 1)), self.make_env, self.cfg.eval,
                                video_dir if self.cfg.eval.videos_per_skill else None, self.cfg.progress)
        record = {
            skill: {"success": e.success, "success_per_seed": e.success_per_seed,
                    "episode_lengths": e.episode_lengths, "videos": [str(Path(v).relative_to(self.out))
                                                                      for v in e.videos]}
            for skill, e in evals.items()
        }
        phase_dir = self._checkpoint_dir(index, phase.split(".")[0])
        trajectories = {f"{skill}/{i}": t for skill, e in evals.items() for i, t in enumerate(e.trajectories)}
        tmp = phase_dir / ".trajectories.tmp.npz"
        np.savez_compressed(tmp, **{k.replace("/", "__"): v for k, v in trajectories.items()})
        os.replace(tmp, phase_dir / "trajectories.npz")
        atomic_write_json(phase_dir / "eval.json", record)
        logger.info("stage %d %s: %s", index + 1, phase, {s: round(r["success"], 3) for s, r in record.items()})
        return {"seconds": time.perf_counter() - t0, "success": {s: r["success"] for s, r in record.items()}}

    def _sleep(self, index: int) -> dict[str, Any]:
        previous = self._stage_final_checkpoint(index - 1)
        anchor = self._weights_of(previous)
        wake_snapshots = [self._weights_of(self._checkpoint_dir(i, "wake")) for i in range(index)]
        params = [p for p in self.policy.parameters() if p.requires_grad]
        config = self.policy_cfg.sleep_config(seed=self._phase_seed(index, "sleep"))
        t0 = time.perf_counter()
        result = sleep_consolidate(
            params, self.policy.memory_chunk, self.memories[: index + 1], config, anchor_params=anchor,
            wake_snapshots=wake_snapshots, is_final_skill=index == len(self.skills) - 1, progress=self.cfg.progress,
        )
        self._save_checkpoint(index, "sleep", {"sleep_diagnostics.json": result.to_dict()})
        return {"seconds": time.perf_counter() - t0, **result.summary()}

    # -- driver ----------------------------------------------------------------------------------------
    def run(self, stop_after: int | None = None) -> dict[str, Any]:
        """Run every pending phase; with ``stop_after=k`` stop after stage k (1-based) and return ``progress``
        instead of the final report (partial runs, e.g. the sleep replays of ``experiments.sleep_replay``)."""
        last = len(self.skills) if stop_after is None else stop_after
        if not 1 <= last <= len(self.skills):
            raise ValueError(f"stop_after must be in 1..{len(self.skills)}, got {stop_after}")
        check_stream_datasets(self.cfg.stream, self.policy_cfg.use_images)  # before anything is written
        self._prepare_output_dir()
        self._setup_policy()
        pending_load: Path | None = None
        for index in range(last):
            number = index + 1
            phases: list[tuple[str, Callable[[int], dict[str, Any]]]] = [("wake", self._wake)]
            if self.method.stores_memories:
                phases.append(("memory", self._store_memory))
            phases.append(("wake.eval", lambda i: self._evaluate(i, "wake.eval")))
            if self.method.sleeps_after(number):
                phases += [("sleep", self._sleep), ("sleep.eval", lambda i: self._evaluate(i, "sleep.eval"))]
            for phase, run_phase in phases:
                if self._done(index, phase):
                    if phase in ("wake", "sleep"):
                        pending_load = self._checkpoint_dir(index, phase)
                    elif phase == "memory":
                        self.memories.append(load_memory(self._memory_path(index), skill=self.skills[index]))
                    continue
                if pending_load is not None:
                    logger.info("resuming from %s", pending_load)
                    self._load_weights(pending_load)
                    pending_load = None
                seed_everything(self._phase_seed(index, phase))
                logger.info("stage %d (%s): %s", number, self.skills[index], phase)
                record = run_phase(index)
                self._mark(index, phase, record)
        if last < len(self.skills):
            return dict(self.progress)
        return write_report(self.out, self.skills, self.cfg.stream.pairs, self.progress, _config_dict(self.cfg),
                            [self._stage_final_checkpoint(i) for i in range(len(self.skills))],
                            [self._checkpoint_dir(i, "wake") for i in range(len(self.skills))],
                            self.memories)


def train_stream(cfg: TrainStreamConfig, make_env: EnvFactory | None = None) -> dict[str, Any]:
    """Run or resume the stream described by ``cfg``; returns the results dictionary."""
    return StreamTrainer(cfg, make_env).run()
