"""The ACT imitation substrate of the stream engine (:class:`~sr_imitation.stream.substrate.Substrate`).

Per stage k (files under the run directory; every file written atomically, checkpoints staged then renamed):

- ``wake``: behaviour cloning on skill k's LeRobot dataset (:func:`~sr_imitation.substrates.act.wake.wake_train`) with
  the method's distillation from earlier memories; checkpoint ``skill_k_<name>/wake/pretrained_model`` (LeRobot
  layout, loadable by ``lerobot-eval --policy.path``) and ``wake_history.json``; while the wake runs,
  ``skill_k_<name>/wake_snapshot.safetensors`` every few minutes (:mod:`sr_imitation.substrates.act.wake_snapshot`: a
  wake killed inside continues from it with identical results);
- ``memory``: the frozen actor memory M_k (``memories/skill_k_<name>.safetensors``);
- ``wake.eval`` / ``sleep.eval``: success on the learned skills (``eval.json``), SPI trajectories
  (``trajectories.safetensors``) and a few rollout videos (``videos/``), in the environment ``--eval.env`` names;
  with ``--eval.env=none`` instead (``eval.json``, no rollouts): each learned skill's memory loss (the distillation
  loss of its stored actor memory M_i under the current policy, over the whole buffer) and validation l1 (the wake's
  l1 on the skill's validation episodes, under the current policy);
- ``sleep``: checkpoint ``skill_k_<name>/sleep`` and ``sleep_diagnostics.json``.

Seeding: every phase seeds Python, NumPy and torch from ``seed * 1000 + 10 * stage + phase id``.
"""

from __future__ import annotations

import dataclasses
import logging
import random
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
from lerobot.policies.factory import make_policy, make_pre_post_processors
from lerobot.utils.constants import ACTION, OBS_STATE

from lerobot_policy_act_sr import ACTSRConfig, ACTSRPolicy
from lerobot_policy_act_sr.actor_memory import ActorMemory
from sr_imitation.core.memory import Memory, load_memory
from sr_imitation.core.sleep import SleepConfig
from sr_imitation.infra import distributed
from sr_imitation.infra.threads import set_torch_threads
from sr_imitation.io import (
    atomic_write_json,
    load_checkpoint_weights,
    read_checked_json,
    read_config_json,
    save_checked_safetensors,
    staged_directory,
    write_checked_json,
)
from sr_imitation.stream.methods.base import ContinualMethod, WakeHooks
from sr_imitation.stream.rundir import RUN_CONFIG_FILE
from sr_imitation.stream.substrate import MethodSettings, SleepProblem, phase_seed, seed_sequence
from sr_imitation.stream.substrate_base import SubstrateBase, load_weights
from sr_imitation.substrates.act.config import SUBSTRATE, TrainStreamConfig, stored_config_dict
from sr_imitation.substrates.act.data import (
    load_metadata,
    load_skill_data,
    load_stats,
    policy_features,
    sample_observation_buffer,
    save_stats,
    stream_stats,
)
from sr_imitation.substrates.act.evaluate import EnvFactory, evaluate_skills, make_env_factory
from sr_imitation.substrates.act.normalization import (
    far_outside,
    map_actions,
    reexpress_policy,
    reexpress_state_dict,
    retarget,
    same_stats,
)
from sr_imitation.substrates.act.report import TRAJECTORIES_FILE, no_pairs_warning, write_report
from sr_imitation.substrates.act.wake import validation_l1, wake_train

logger = logging.getLogger(__name__)

PER_SKILL_EVAL_KEYS = ("eval.gym_ids", "eval.env_tasks")
"""Evaluation settings with one entry per skill: an extended stream has more; its first entries must equal the run
it extends (:meth:`ACTSubstrate.source_skills`)."""
WAKE_SNAPSHOT = "wake_snapshot.safetensors"
"""A wake's snapshot in its stage folder, while the wake runs (:mod:`sr_imitation.substrates.act.wake_snapshot`)."""
STATS_FILE = "stream_stats.safetensors"
"""The stream's statistics: in the run directory (the first skill's, or those ``--stream.stats`` fixes), and under
``--stream.stats=seen`` in each later stage's folder (those of skills 1..k)."""
SEEN_METHODS = ("sr", "wake_only", "sequential_bc", "nash_mtl", "pcgrad")
"""Methods that ``--stream.stats=seen`` supports: their memories are the substrate's actor memories (raw
observations, targets it re-expresses) or none; the others store normalized frames, weights or Fisher information
that would stay in the earlier statistics."""
OFFLINE_BATCH = 64
"""Batch size of the memory losses and validation l1 of ``--eval.env=none`` (no randomness; any size gives the same
numbers up to float rounding)."""


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def stage_name(index: int, skill: str) -> str:
    return f"skill_{index + 1}_{skill}"


def normalize_raw_observations(preprocessor: Any, raw: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The policy's normalized inputs for raw buffered observations (uint8 images become floats in [0, 1], as
    LeRobot's datasets hold them, then the policy's preprocessor): what memories evaluate the policy on."""
    obs = {k: (v.float() / 255.0 if v.dtype == torch.uint8 else v) for k, v in raw.items()}
    return preprocessor(obs)


def deployed_parameters(policy: ACTSRPolicy, state: Mapping[str, torch.Tensor]) -> list[torch.Tensor]:
    """The deployed parameters (:meth:`ACTSRPolicy.deployed_named_parameters` order) of a saved ``state``."""
    return [state[n] for n, _ in policy.deployed_named_parameters()]


def act_sleep_problem(policy: ACTSRPolicy, config: SleepConfig) -> SleepProblem:
    """The sleep of an ACT-SR policy: theta is the deployed policy's parameters (ACT's training-only VAE encoder
    excluded, our choice: :meth:`ACTSRPolicy.deployed_named_parameters` says why) and each memory evaluates the
    deployed action chunk of its raw observations (:meth:`ACTSRPolicy.memory_chunk`). The stream's sleep and
    ``sr-sleep`` both use it."""
    return SleepProblem([p for _, p in policy.deployed_named_parameters()], policy.memory_chunk, config)


def save_pretrained_model(directory: Path, policy: ACTSRPolicy, preprocessor: Any, postprocessor: Any) -> None:
    """A LeRobot ``pretrained_model/`` directory: the policy (config and weights) and its pre/post-processors, what
    ``lerobot-eval --policy.path`` loads."""
    policy.save_pretrained(directory)
    preprocessor.save_pretrained(directory)
    postprocessor.save_pretrained(directory)


TRAIN_CONFIG_FILE = RUN_CONFIG_FILE
"""The run's stored config: in the run directory, and beside each checkpoint in ``pretrained_model/`` (LeRobot's
layout), where ``--config_path=<run>/last/pretrained_model/train_config.json --resume=true`` resumes the run."""


class ACTSubstrate(SubstrateBase):
    """ACT-SR on the needle stream (LeRobot datasets, MuJoCo needle environment); the memories' files and the run it
    extends as :class:`SubstrateBase` does them, the checkpoints in LeRobot's layout."""

    name: ClassVar[str] = SUBSTRATE
    seed_scheme: ClassVar[str] = "decimal"
    wake_hooks: ClassVar[frozenset[str]] = frozenset({"wake_batch", "wake_loss", "adjust_gradients"})  # hooked_update
    extension_keys: ClassVar[tuple[str, ...]] = ("stream.skills", "stream.dataset_paths", "stream.repo_ids",
                                                 "stream.extend_from", *PER_SKILL_EVAL_KEYS)
    checkpoint_file: ClassVar[str] = "pretrained_model/model.safetensors"
    memory_files: ClassVar[str] = "memories/skill_{n}_{skill}{suffix}.safetensors"
    run_files: ClassVar[tuple[str, ...]] = (STATS_FILE,)  # the stream's fixed statistics (the shared first skill's)

    def __init__(self, cfg: TrainStreamConfig, make_env: EnvFactory | None = None) -> None:
        self.cfg = cfg
        self.out = Path(cfg.output_dir)
        self.policy_cfg: ACTSRConfig = cfg.policy  # type: ignore[assignment]
        self.skills = list(cfg.stream.skills)
        self._make_env = make_env
        self._data: Any = None
        self.train_config: dict[str, Any] | None = None
        """The run's stored config, written beside each checkpoint as LeRobot does (set by ``ACTTrainer``)."""
        if cfg.stream.stats == "seen" and cfg.method not in SEEN_METHODS:
            raise ValueError(f"stream.stats=seen (the default) re-expresses actor memories when the statistics "
                             f"change; method {cfg.method!r} keeps normalized data of earlier skills: give "
                             f"--stream.stats=first or --stream.stats=union (seen supports {list(SEEN_METHODS)})")
        self._stage_stats: dict[int, dict] = {}
        self._stats_stage = 0  # the stage whose statistics the processors hold
        self._policy_stage = 0  # the stage whose statistics the policy's weights are expressed in
        self._memory_origin: dict[int, tuple[Any, int, torch.Tensor]] = {}  # id -> (memory, stage, its targets)

    def method_settings(self) -> MethodSettings:
        return MethodSettings(sleep=self.cfg.sleep.enabled, distill_weight=self.policy_cfg.distill_weight,
                              extra={"aggregator": self.cfg.sleep.aggregator})

    # -- set-up ------------------------------------------------------------------------------------------
    def setup(self) -> None:
        set_torch_threads(self.cfg.torch_threads, logger)
        if (why := no_pairs_warning(self.cfg.stream.pairs, self.skills)) is not None:
            logger.warning(why)
        first_meta = load_metadata(self.cfg.stream.dataset_path(0), self.cfg.stream.repo_id(0))
        inputs, outputs = policy_features(first_meta, self.policy_cfg.use_images)
        self.policy_cfg.input_features, self.policy_cfg.output_features = inputs, outputs
        stats_path = self.out / STATS_FILE
        if stats_path.exists():
            self.stats = load_stats(stats_path)
        else:
            self.stats = stream_stats(self.stats_metas(first_meta), inputs, self.cfg.stream.stats_min_std)
            save_stats(stats_path, self.stats)
        self._stage_stats = {0: self.stats}
        self._stats_stage = self._policy_stage = 0
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
        self.make_env = self._make_env or make_env_factory(self.cfg.eval, self.skills, size)

    def stats_metas(self, first_meta: Any) -> list[Any]:
        """The datasets whose statistics normalize the stream from its start (``--stream.stats``: the first - also
        for ``seen``, until the second skill's wake - or all)."""
        stream = self.cfg.stream
        if stream.stats in ("first", "seen"):
            return [first_meta]
        return [first_meta] + [load_metadata(stream.dataset_path(i), stream.repo_id(i))
                               for i in range(1, len(self.skills))]

    def _normalize_raw(self, raw: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        return normalize_raw_observations(self.preprocessor, raw)

    # -- --stream.stats=seen: the statistics of skills 1..k at stage k ----------------------------------------------
    def stage_stats(self, k: int) -> dict:
        """The statistics that normalize stage ``k``: the stream's fixed ones, or under ``seen`` those of skills
        1..k (computed at the stage's first phase from datasets 1..k only, saved in its folder, read back on
        resume)."""
        if self.cfg.stream.stats != "seen" or k == 0:
            return self._stage_stats[0]
        if k not in self._stage_stats:
            path = self.out / self.stage_dir_name(k) / STATS_FILE
            if path.exists():
                self._stage_stats[k] = load_stats(path)
            else:
                stream = self.cfg.stream
                metas = [load_metadata(stream.dataset_path(i), stream.repo_id(i)) for i in range(k + 1)]
                stats = stream_stats(metas, self.policy_cfg.input_features, stream.stats_min_std)
                path.parent.mkdir(parents=True, exist_ok=True)
                save_stats(path, stats)
                self._stage_stats[k] = stats
        return self._stage_stats[k]

    def _use_stage(self, k: int) -> None:
        """Under ``seen``: the processors normalize with stage ``k``'s statistics, the policy's weights are
        re-expressed into them (the same actions, :func:`~sr_imitation.substrates.act.normalization.reexpress_policy`)
        and every memory's targets are its stored targets mapped into them. Each is computed from what was stored
        (the checkpoint's weights, the memory file's targets), so a resumed run computes the same numbers."""
        if self.cfg.stream.stats != "seen":
            return
        new = self.stage_stats(k)
        floor = self.cfg.stream.stats_min_std
        if self._policy_stage != k:
            old = self.stage_stats(self._policy_stage)
            if not same_stats(old, new, list(new)):
                reexpress_policy(self.policy, old, new, floor, self.cfg.stream.reexpress_inputs)
            self._policy_stage = k
        if self._stats_stage != k:
            self.stats, self._stats_stage = new, k
            self.preprocessor, self.postprocessor = make_pre_post_processors(self.policy_cfg, dataset_stats=new)
            logger.info("stage %d: normalization statistics of skills %s (--stream.stats=seen)", k + 1,
                        self.skills[: k + 1])
        for memory, stage, targets in self._memory_origin.values():
            source = self.stage_stats(stage)[ACTION]
            retarget(memory, targets if stage == k else map_actions(targets, source, new[ACTION]))

    def _remember(self, memory: Memory, k: int) -> Memory:
        """Keep an actor memory of stage ``k`` (its targets in stage ``k``'s statistics) for :meth:`_use_stage`."""
        if self.cfg.stream.stats == "seen" and isinstance(memory, ActorMemory):
            self._memory_origin[id(memory)] = (memory, k, memory.tensors["target"])
            if k != self._stats_stage:
                retarget(memory, map_actions(memory.tensors["target"], self.stage_stats(k)[ACTION],
                                             self.stats[ACTION]))
        return memory

    def warn_far_outside(self, k: int) -> None:
        """One warning line, before skill ``k``'s first gradient, when its dataset's mean lies more than
        :data:`~sr_imitation.substrates.act.normalization.FAR_OUTSIDE` standard deviations of the statistics in use
        from their mean in some state or action dimension. Under ``seen`` the statistics in use already hold skill
        ``k``; there the line says how far it lies outside those of the skills before it, which widen to take it
        in (the policy, re-expressed exactly, meets it as that far an outlier; docs/RESULTS.md measures what
        ``seen`` costs against ``union`` on the needle stream, where such jumps occur)."""
        stream = self.cfg.stream
        meta = load_metadata(stream.dataset_path(k), stream.repo_id(k))
        if stream.stats == "seen":
            found = None if k == 0 else far_outside(meta.stats, self.stage_stats(k - 1), [OBS_STATE, ACTION])
            if found is not None:
                key, dim, z = found
                logger.warning("skill %s: its %s[%d] lies %.0f standard deviations outside the statistics of the "
                               "skills before it (--stream.stats=seen widens them to take it in); on the needle "
                               "stream seen ended below union (docs/RESULTS.md, 'The normalization default "
                               "measured'): --stream.stats=union if every skill's dataset is at hand from the start",
                               self.skills[k], key, dim, z)
            return
        found = far_outside(meta.stats, self.stats, [OBS_STATE, ACTION])
        if found is not None:
            key, dim, z = found
            logger.warning("skill %s: its %s[%d] lies %.0f standard deviations from the mean of the statistics in "
                           "use (--stream.stats=%s); it may not be learned: use --stream.stats=seen", self.skills[k],
                           key, dim, z, stream.stats)

    @property
    def run_seed(self) -> int:
        return self.cfg.seed

    def phase_seed(self, index: int, phase: str) -> int:
        """The seed the engine hands ``phase`` of stage ``index`` (the generators of this substrate that belong to
        another phase, e.g. the wake's data split during an evaluation, use that phase's)."""
        return phase_seed(self.seed_scheme, self.cfg.seed, index, phase)

    def begin_phase(self, k: int, phase: str, seed: int) -> None:
        seed_everything(seed)
        self._use_stage(k)

    # -- files -------------------------------------------------------------------------------------------
    def stage_dir_name(self, index: int) -> str:
        """The folder of stage ``index`` (its checkpoints, evaluations and videos)."""
        return stage_name(index, self.skills[index])

    def stage_dir(self, k: int) -> Path:
        return self.out / self.stage_dir_name(k)

    def checkpoint_dir(self, index: int, phase: str) -> Path:
        return self.stage_dir(index) / phase

    def checkpoint_module(self) -> torch.nn.Module:
        return self.policy

    def save_policy(self, k: int, phase: str, files: dict[str, Any]) -> None:
        """Write ``pretrained_model/`` (LeRobot layout) and ``files`` (JSON) to a staging dir, then rename."""
        # an existing final directory was left by a run killed after the rename but before progress.json was written
        with staged_directory(self.checkpoint_dir(k, phase)) as tmp:
            save_pretrained_model(tmp / "pretrained_model", self.policy, self.preprocessor, self.postprocessor)
            if self.train_config is not None:
                write_checked_json(tmp / "pretrained_model" / TRAIN_CONFIG_FILE, self.train_config)
            for name, obj in files.items():
                atomic_write_json(tmp / name, obj)

    def checkpoint_state(self, k: int, phase: str) -> dict[str, torch.Tensor]:
        """The checkpoint's weights after checking every file of it against its ``checksums.json``."""
        path = self.checkpoint_path(k, phase)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: checkpoint recorded in progress.json is missing")
        return load_checkpoint_weights(self.checkpoint_dir(k, phase))

    def _state_in_use(self, k: int, phase: str) -> dict[str, torch.Tensor]:
        """:meth:`checkpoint_state`, under ``--stream.stats=seen`` re-expressed into the statistics in use."""
        state = self.checkpoint_state(k, phase)
        if self.cfg.stream.stats == "seen" and k != self._stats_stage:
            state = reexpress_state_dict(state, self.stage_stats(k), self.stats, self.cfg.stream.stats_min_std,
                                         self.cfg.stream.reexpress_inputs)
        return state

    def load_policy(self, k: int, phase: str) -> None:
        super().load_policy(k, phase)
        self._policy_stage = k  # its weights are in stage k's statistics (seen)

    def parameters_at(self, k: int, phase: str) -> list[torch.Tensor]:
        state = self._state_in_use(k, phase)  # in the statistics in use
        return [state[n] for n in self.parameter_names()]

    def reset_networks(self, k: int) -> None:
        """A freshly initialized policy (every weight, the training-only VAE encoder too) for skill k (Reset &
        Distill's network per skill), built as :meth:`setup` builds it but seeded from (run seed, k); the statistics
        and processors are kept, and the global random state is left as it was. The wake then builds its own
        optimizer, as every wake does."""
        saved = torch.random.get_rng_state()
        torch.manual_seed(seed_sequence(self.cfg.seed, k, 20) % (2**63))
        fresh = type(self.policy)(self.policy.config)
        torch.random.set_rng_state(saved)
        self.policy.load_state_dict(fresh.state_dict())
        self._policy_stage = self._stats_stage  # fresh weights: in the statistics in use (seen)

    def load_actor(self, k: int, phase: str) -> None:
        """Only the policy's weights of the checkpoint after ``phase`` of stage k (Reset & Distill's shared policy),
        checked against its checksums; under ``--stream.stats=seen`` re-expressed into the statistics in use (as
        :meth:`parameters_at` does), so the processors and memories of the current stage stay as they are."""
        load_weights(self.policy, self._state_in_use(k, phase), self.checkpoint_path(k, phase))
        self._policy_stage = self._stats_stage

    # -- what continual methods ask of the policy -------------------------------------------------------------
    def chunk_policy(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """The deployed action chunk on a preprocessed (normalized) training batch (LwF's output)."""
        return self.policy.action_chunk(batch)

    def chunk_and_features(self, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """:meth:`chunk_policy` with the encoder's intermediate features (M2Distill's targets)."""
        return self.policy.action_chunk_and_features(batch)

    def policy_weights(self) -> dict[str, torch.Tensor]:
        """Every tensor of the policy's state (what a frozen copy of it holds)."""
        return dict(self.policy.state_dict())

    def frozen_policy(self) -> Any:
        """A frozen copy of the current policy (LwF's and M2Distill's previous policy); its ``action_chunk`` and
        ``action_chunk_and_features`` are :meth:`chunk_policy` and :meth:`chunk_and_features` as they are now."""
        saved = torch.random.get_rng_state()  # building the copy must not move the wake's random stream
        frozen = type(self.policy)(self.policy.config)
        torch.random.set_rng_state(saved)
        frozen.load_state_dict(self.policy.state_dict())
        return frozen.to(next(self.policy.parameters()).device).eval().requires_grad_(False)

    def policy_parameters(self) -> list[torch.nn.Parameter]:
        return self.trainable()

    def state_sample(self, k: int, n: int | None = None) -> list[dict[str, torch.Tensor]]:
        """``n`` (default 2000) preprocessed single-frame batches of skill k's demonstrations, drawn uniformly
        (seeded per stage; EWC's Fisher samples)."""
        n = 2000 if n is None else n
        data = self._skill_data(k)
        rng = np.random.default_rng(self.phase_seed(k, "memory") + 7)
        pool = data.train_indices + data.val_indices
        picks = rng.choice(pool, size=n, replace=len(pool) < n)
        return [self.preprocessor({key: v.unsqueeze(0) if isinstance(v, torch.Tensor) else [v]
                                   for key, v in data.dataset[int(i)].items()}) for i in picks]

    def demonstration_frames(self, k: int, n: int | None = None) -> dict[str, torch.Tensor]:
        """``n`` (default ``--memory.buffer_size``) demonstration frames of skill k as a wake batch holds them
        (preprocessed: the normalized policy inputs, the normalized action chunk and its ``action_is_pad`` mask),
        stacked on the CPU: the frames SR's memory M_k buffers (:func:`~sr_imitation.substrates.act.data.
        sample_observation_buffer`'s draw with the same seed: uniform over all the skill's demonstration frames,
        without replacement unless it has fewer than ``n``). Experience replay's buffer."""
        n = self.cfg.memory.buffer_size if n is None else n
        data = self._skill_data(k)
        pool = data.train_indices + data.val_indices
        picks = np.random.default_rng(self.phase_seed(k, "memory")).choice(pool, size=n, replace=len(pool) < n)
        parts, keys = [], None
        for start in range(0, n, 256):  # preprocessing is per frame; chunks bound the float images' memory
            items = [data.dataset[int(i)] for i in picks[start : start + 256]]
            if keys is None:  # the dataset's policy inputs (ACT derives its environment state from the state)
                keys = [*(k for k in self.policy_cfg.input_features if k in items[0]), "action", "action_is_pad"]
            raw = {key: torch.stack([item[key] for item in items]) for key in keys}
            parts.append({key: v.detach().cpu() for key, v in self.preprocessor(raw).items() if key in keys})
        return {key: torch.cat([p[key] for p in parts]) for key in keys or []}

    def log_likelihood(self, batch: dict[str, torch.Tensor], generator: torch.Generator) -> torch.Tensor:
        """Minus the L1 behaviour-cloning loss of the deployed action chunk (zero latent, no dropout: what acts at
        inference) on one preprocessed batch, padded steps masked: its squared gradient is the empirical Fisher (EWC
        on ACT; the training-only VAE encoder is not a deployed parameter)."""
        pred = self.policy.action_chunk(batch)
        mask = ~batch["action_is_pad"].unsqueeze(-1) if "action_is_pad" in batch else torch.ones_like(pred, dtype=bool)
        return -((pred - batch["action"]).abs() * mask).mean()

    def trainable(self) -> list[torch.nn.Parameter]:
        """theta of the sleep: the deployed policy's parameters (ACT's training-only VAE encoder excluded)."""
        return [p for _, p in self.policy.deployed_named_parameters()]

    # -- phases --------------------------------------------------------------------------------------------
    def _skill_data(self, index: int) -> Any:
        skill = self.skills[index]
        if self._data is None or self._data.skill != skill:
            self._data = load_skill_data(skill, self.cfg.stream.dataset_path(index), self.cfg.stream.repo_id(index),
                                         self.policy_cfg, self.cfg.wake.val_fraction,
                                         self.phase_seed(index, "wake"), self.cfg.stream.video_backend)
        return self._data

    def wake(self, k: int, memories: Sequence[Memory], distill_weight: float, method: ContinualMethod | None = None
             ) -> tuple[dict[str, Any], dict[str, Any]]:
        self._data = None
        data = self._skill_data(k)
        self.warn_far_outside(k)
        self.policy.set_wake_memories(list(memories), distill_weight, seed=self.phase_seed(k, "wake"))
        t0 = time.perf_counter()
        log = self.run_log

        def on_epoch(epoch: int, values: dict[str, float]) -> None:
            if log is not None:
                log.log("wake", stage=k + 1, step=epoch, **values)

        hooks = None
        if method is not None and method.has_wake_hooks:
            hooks = WakeHooks(method, k, self.trainable(), self.chunk_policy, self.phase_seed(k, "wake"))
        result = wake_train(self.policy, self.preprocessor, data, self.cfg.wake, self.phase_seed(k, "wake"),
                            self.cfg.progress, on_epoch=on_epoch, hooks=hooks,
                            snapshot=self.out / self.stage_dir_name(k) / WAKE_SNAPSHOT)
        self.policy.set_wake_memories([], 0.0)
        history = result.history_record() | {"distill_weight": distill_weight, "n_memories": len(memories)}
        record = {"seconds": time.perf_counter() - t0 + result.seconds_before_resume, "epochs": result.epochs,
                  "best_epoch": result.best_epoch, "best_val_l1": result.best_val_l1, "steps": result.steps}
        return record, {"wake_history.json": history}

    def make_memory(self, k: int) -> Memory:
        return self.actor_memory(k)

    def actor_memory(self, k: int) -> Memory:
        """M_k: ``--memory.buffer_size`` raw frames of skill k (:func:`~sr_imitation.substrates.act.data.
        sample_observation_buffer`, seeded per stage) and the current policy's deployed action chunks on them, frozen
        now (:class:`ActorMemory`), saved as the stage's memory. SR's memory after its wake; Reset & Distill's expert
        memory (:class:`~sr_imitation.stream.capabilities.ActorSnapshotMemory`)."""
        data = self._skill_data(k)
        buffer = sample_observation_buffer(data, self.cfg.memory.buffer_size, self.buffer_keys,
                                           self.phase_seed(k, "memory"))
        snapshot = str(self.checkpoint_dir(k, "wake").relative_to(self.out))
        memory = ActorMemory.from_observations(self.skills[k], self.policy.memory_chunk, buffer, snapshot=snapshot,
                                               reduction=self.policy_cfg.distill_reduction)
        memory.save(self.memory_path(k))
        return self._remember(memory, k)

    def load_memory(self, k: int, name: str = "memory") -> Memory:
        return self._remember(super().load_memory(k, name), k)

    def wake_eval_skills(self, k: int, sleeps: bool) -> list[int]:
        return list(range(k + 1))  # every learned skill: the after-wake success matrix is reported too

    def evaluate(self, k: int, phase: str, skills: Sequence[int]) -> dict[str, Any]:
        if not distributed.current().is_main:  # several processes: the main one evaluates (infra.distributed)
            return {"seconds": 0.0, "skipped": "evaluated by the main process"}
        if self.make_env is None:  # --eval.env=none
            return self._evaluate_offline(k, phase, skills)
        names = [self.skills[i] for i in skills]
        step = phase.split(".")[0]
        video_dir = self.out / "videos" / self.stage_dir_name(k) / step
        t0 = time.perf_counter()
        evals = evaluate_skills(self.policy, self.preprocessor, self.postprocessor, names, list(skills),
                                self.make_env, self.cfg.eval, video_dir if self.cfg.eval.videos_per_skill else None,
                                self.cfg.progress)
        record = {
            skill: {"success": e.success, "success_per_seed": e.success_per_seed,
                    "episode_lengths": e.episode_lengths, "videos": [str(Path(v).relative_to(self.out))
                                                                      for v in e.videos]}
            for skill, e in evals.items()
        }
        phase_dir = self.checkpoint_dir(k, step)
        trajectories = {f"{skill}__{i}": torch.from_numpy(np.ascontiguousarray(t))
                        for skill, e in evals.items() for i, t in enumerate(e.trajectories)}
        save_checked_safetensors(phase_dir / TRAJECTORIES_FILE, trajectories,
                                 {"format": "sr_imitation.act.trajectories", "stage": k + 1, "phase": phase})
        write_checked_json(phase_dir / "eval.json", record)
        logger.info("stage %d %s: %s", k + 1, phase, {s: round(r["success"], 3) for s, r in record.items()})
        return {"seconds": time.perf_counter() - t0, "success": {s: r["success"] for s, r in record.items()}}

    def _evaluate_offline(self, k: int, phase: str, skills: Sequence[int]) -> dict[str, Any]:
        """``--eval.env=none``: what can be computed without an environment, for every learned skill i - the loss of
        its stored actor memory M_i under the current policy (the sleep's objective L_i over the whole buffer; null
        when the method stores no actor memory) and the wake's validation l1 on its validation episodes (on its
        training episodes for a one-episode dataset, as the wake does). Written to ``eval.json``."""
        t0 = time.perf_counter()
        record: dict[str, dict[str, float | None]] = {}
        for i in skills:
            record[self.skills[i]] = {"memory_loss": self._memory_loss(i),
                                      "validation_l1": self._validation_l1(i)}
        write_checked_json(self.checkpoint_dir(k, phase.split(".")[0]) / "eval.json", record)
        logger.info("stage %d %s (no evaluation environment): %s", k + 1, phase, record)
        return {"seconds": time.perf_counter() - t0,
                "memory_loss": {s: r["memory_loss"] for s, r in record.items()},
                "validation_l1": {s: r["validation_l1"] for s, r in record.items()}}

    def _memory_loss(self, i: int) -> float | None:
        """L_i(theta) of skill i's stored actor memory over its whole buffer (``None`` if there is none)."""
        path = self.memory_path(i)
        if not path.is_file():
            return None
        memory = load_memory(path, skill=self.skills[i])
        if not isinstance(memory, ActorMemory):
            return None
        buffers = {key: memory.tensors[key] for key in memory.buffer_keys}
        if self.cfg.stream.stats == "seen" and i != self._stats_stage:  # stored in stage i's statistics
            buffers["target"] = map_actions(buffers["target"], self.stage_stats(i)[ACTION], self.stats[ACTION])
        total = 0.0
        with torch.no_grad():
            for start in range(0, memory.size, OFFLINE_BATCH):
                batch = {key: v[start : start + OFFLINE_BATCH] for key, v in buffers.items()}
                n = len(batch["target"])
                total += float(memory.loss(self.policy.memory_chunk, batch)) * n
        return total / memory.size

    def _validation_l1(self, i: int) -> float:
        """The wake's validation l1 (:func:`~sr_imitation.substrates.act.wake.validation_l1`) on skill i's validation
        episodes under the current policy."""
        data = self._skill_data(i)
        indices = data.val_indices or data.train_indices
        loader = torch.utils.data.DataLoader(torch.utils.data.Subset(data.dataset, indices), batch_size=OFFLINE_BATCH,
                                             shuffle=False)
        return validation_l1(self.policy, self.preprocessor, loader)

    def read_eval(self, k: int, phase: str) -> dict[str, Any]:
        """The evaluation record :meth:`evaluate` wrote after stage ``k``'s ``phase`` (checked)."""
        return read_checked_json(self.checkpoint_dir(k, phase.split(".")[0]) / "eval.json")

    def sleep_problem(self, k: int, memories: Sequence[Memory]) -> SleepProblem:
        return act_sleep_problem(self.policy, dataclasses.replace(self.cfg.sleep, seed=self.phase_seed(k, "sleep")))

    def source_skills(self, settings: dict[str, Any]) -> list[str]:
        """The skills of the run being extended; its per-skill evaluation entries (:data:`PER_SKILL_EVAL_KEYS`) must be
        this stream's first ones (``ValueError`` naming the key otherwise)."""
        skills = list(settings["stream.skills"])
        n = len(skills)
        for key in PER_SKILL_EVAL_KEYS:
            mine = getattr(self.cfg.eval, key.split(".")[1])
            stored, current = settings.get(key), None if mine is None else list(mine)[:n]
            if key == "eval.env_tasks":  # null: each skill's name is its task
                stored = skills if stored is None else stored
                current = list(self.skills[:n]) if current is None else current
            if stored != current:
                raise ValueError(f"{key}: the run being extended evaluated its skills with {stored}, this stream's "
                                 f"first {n} entries are {current}")
        return skills

    def report(self, progress: dict[str, Any], memories: Sequence[Memory], final_phases: Sequence[str]
               ) -> dict[str, Any]:
        n = len(self.skills)  # the stored config: no absolute run location in results.json
        # the configuration the run started with (train_config.json, written once at its start), not this
        # invocation's: a resume may change allow-listed settings only, and results say what held from the start
        stored = self.out / TRAIN_CONFIG_FILE
        config = read_config_json(stored)[0] if stored.is_file() else stored_config_dict(self.cfg)  # (older runs)
        return write_report(self.out, self.skills, self.cfg.stream.pairs, progress, config,
                            [self.checkpoint_dir(i, final_phases[i]) for i in range(n)],
                            [self.checkpoint_dir(i, "wake") for i in range(n)], memories,
                            evaluation=self.cfg.eval.env)
