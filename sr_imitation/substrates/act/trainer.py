"""``sr-train`` on the imitation substrate: the stream's configuration and its runner.

The algorithm is the stream engine's (:mod:`sr_imitation.stream.engine`, Algorithm 1 written once); the ACT
substrate (:mod:`sr_imitation.substrates.act.substrate`) says what each phase does and which files it writes; the
method (``--method``: :mod:`sr_imitation.stream.methods`) what is distilled, stored and whether it sleeps. This
module holds :class:`ACTTrainer`, which checks every dataset of the stream, prepares the run directory and runs
the engine; the configuration (:class:`TrainStreamConfig`, what a resume must keep) is
:mod:`sr_imitation.substrates.act.config`'s, re-exported here.

Every phase is recorded in ``progress.json`` only after its outputs are completely and atomically written, and
every phase seeds its own random generators from (run seed, skill, phase). A run killed at any point and
restarted with ``--resume=true`` therefore redoes at most the interrupted phase and, on CPU, reaches the same
numbers as an uninterrupted run. Results (``results.json``, plots, a markdown table) are rebuilt from the
recorded phases at the end.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import logging
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from sr_imitation.envs.needle.skills import SKILL_NAMES as SURGICAI_SKILLS
from sr_imitation.infra import distributed
from sr_imitation.infra.folder_lock import hold_folder
from sr_imitation.stream.methods import check_method
from sr_imitation.stream.run import StreamRun
from sr_imitation.stream.rundir import point_last
from sr_imitation.substrates.act.config import (
    RESUME_ALLOW_LIST,
    SETTINGS_ADDED,
    MemoryConfig,
    StreamConfig,
    TrainStreamConfig,
    inputs_check,
    resume_fingerprint,
    stored_config_dict,
    stream_inputs,
)
from sr_imitation.substrates.act.data import DatasetMismatchError, check_stream_datasets
from sr_imitation.substrates.act.evaluate import (
    EnvFactory,
    check_env_features,
    check_env_renders,
    make_env_factory,
    resolve_eval_env,
)
from sr_imitation.substrates.act.hub import check_push, push_policy
from sr_imitation.substrates.act.substrate import ACTSubstrate, seed_everything, stage_name

__all__ = ["RESUME_ALLOW_LIST", "SETTINGS_ADDED", "MemoryConfig", "StreamConfig", "ACTTrainer",
           "TrainStreamConfig", "check_evaluation_envs", "check_skill_names", "inputs_check",
           "naming_misspelled_skills", "resume_fingerprint", "seed_everything", "stage_name", "stored_config_dict",
           "stream_inputs", "train_stream"]

logger = logging.getLogger(__name__)


class ACTTrainer(StreamRun):
    """Runs (or resumes) one stream: the engine (:class:`~sr_imitation.stream.StreamEngine`) with the ACT substrate
    and ``cfg.method`` (:class:`~sr_imitation.stream.run.StreamRun`). Before the first phase every dataset and
    evaluation environment is checked and ``--policy.push_to_hub`` tried; after each stage's final phase
    ``<output_dir>/last`` points at its consolidated policy; at the end the policy is pushed if asked.
    ``after_phase(k, phase)`` (tests) is called after each newly completed phase."""

    def __init__(self, cfg: TrainStreamConfig, make_env: EnvFactory | None = None,
                 after_phase: Callable[[int, str], None] | None = None) -> None:
        substrate = ACTSubstrate(cfg, make_env)
        check_method(cfg.method, substrate)  # before the datasets are read for their digests
        with naming_misspelled_skills(cfg, make_env is not None):
            inputs = stream_inputs(cfg)
        stored = stored_config_dict(cfg)
        super().__init__(cfg, substrate, fingerprint=resume_fingerprint(cfg, inputs), stored_config=stored,
                         check_inputs=inputs_check(cfg, inputs), after_phase=after_phase,
                         inputs=[cfg.stream.dataset_path(i) for i in range(len(cfg.stream.skills))])
        self.cfg: TrainStreamConfig = cfg
        self.substrate: ACTSubstrate = substrate
        substrate.train_config = stored

    @property
    def policy(self) -> Any:
        return self.substrate.policy

    def preflight(self) -> None:
        """Before anything is trained or written: the datasets, the evaluation environments, the hub."""
        _, inputs, outputs = check_stream_datasets(self.cfg.stream, self.substrate.policy_cfg.use_images)
        check_evaluation_envs(self.cfg, inputs, outputs, custom_env=self.substrate._make_env is not None)
        check_push(self.cfg.policy)  # --policy.push_to_hub: reachable, or one line now rather than after training

    def run(self, stop_after: int | None = None, report: bool = True) -> dict[str, Any]:
        """Run every pending phase; with ``stop_after=k`` stop after stage k (1-based), or with ``report=False``,
        return ``progress`` instead of the final report (partial runs, e.g. the sleep replays of
        ``experiments.sleep_replay``). A process other than the main one of a several-process run
        (:mod:`sr_imitation.infra.distributed`) always returns its progress: the main process evaluates and
        reports."""
        if not distributed.current().is_main:
            return super().run(stop_after, report=False)
        results = super().run(stop_after, report)
        self._point_last()  # also when a resume found every phase done (killed between a phase and its pointer)
        if stop_after is None and report and self.cfg.policy.push_to_hub:
            last = len(self.cfg.stream.skills) - 1
            pretrained = self.substrate.checkpoint_dir(last, self.final_phase(last)) / "pretrained_model"
            push_policy(self.substrate.policy, pretrained,
                        [self.cfg.stream.repo_id(i) for i in range(len(self.cfg.stream.skills))])
        return results

    def on_phase(self, k: int, phase: str) -> None:
        if phase == self.final_phase(k):
            self._point_last()

    def _point_last(self) -> None:
        """``<output_dir>/last`` -> the newest stage's consolidated checkpoint (its final phase) recorded so far."""
        done = [k for k in range(len(self.cfg.stream.skills)) if self.run_dir.done(k, self.final_phase(k))]
        if done:
            point_last(self.out, self.substrate.checkpoint_dir(done[-1], self.final_phase(done[-1])))


def check_recorded_tasks(cfg: TrainStreamConfig) -> None:
    """``--eval.env=metaworld``: a dataset that ``sr-record --env=metaworld`` recorded (its ``meta/sr_record.json``)
    must hold the Meta-World task its skill is evaluated on; ``ValueError`` naming the file and both tasks. Datasets
    of other origin carry no such record and are not checked here."""
    from sr_imitation.io import read_checked_json

    skills = list(cfg.stream.skills)
    for index, task in enumerate(cfg.eval.tasks(skills)):
        record = Path(cfg.stream.dataset_path(index)) / "meta" / "sr_record.json"
        if not record.is_file():
            continue
        recorded = read_checked_json(record)
        if recorded.get("env") == "metaworld" and recorded.get("skill") != task:
            raise ValueError(f"{record}: the dataset of skill {skills[index]!r} was recorded on Meta-World task "
                             f"{recorded.get('skill')!r}, but it is evaluated on {task!r}; check the order of "
                             "stream.skills, the datasets and eval.env_tasks")


def check_skill_names(cfg: TrainStreamConfig, custom_env: bool = False) -> None:
    """Every skill names an environment ``--eval.env`` has, checked on names alone: ``needle``, a needle skill;
    ``metaworld``, a Meta-World v3 task (``eval.env_tasks`` where given). ``ValueError`` naming the key."""
    if custom_env:
        return
    mode, skills = cfg.eval.env, list(cfg.stream.skills)
    if mode == "needle":
        unknown = [s for s in skills if s not in SURGICAI_SKILLS]
        if unknown:
            raise ValueError(f"stream.skills: {unknown} have no evaluation environment (the needle environment has "
                             f"{list(SURGICAI_SKILLS)}); every skill needs a dataset and an environment: evaluate "
                             "them with --eval.env=gym|lerobot or switch evaluation off with --eval.env=none")
    if mode == "metaworld":
        for index in range(len(skills)):
            resolve_eval_env(cfg.eval, skills, index)  # one line naming the key and a close task name


@contextlib.contextmanager
def naming_misspelled_skills(cfg: TrainStreamConfig, custom_env: bool = False) -> Iterator[None]:
    """Around reading the datasets: one that cannot be read for a skill that names no environment of ``--eval.env``
    (a misspelling: ``dor-open-v3``) is reported as that, the key with a close name suggested
    (:func:`check_skill_names`), not as a missing dataset folder. Only then: a resume with a changed setting is still
    refused by the settings check first. A dataset folder that does not exist at all under ``--stream.dataset_root``,
    for a skill the needle or Meta-World recorder can record, gets the ``sr-record`` command that records it."""
    try:
        yield
    except DatasetMismatchError as exc:
        check_skill_names(cfg, custom_env)
        hint = record_hint(cfg, custom_env)
        if hint is None:
            raise
        raise DatasetMismatchError(f"{exc}; {hint}") from None  # the one line shown is the innermost error


def record_hint(cfg: TrainStreamConfig, custom_env: bool = False) -> str | None:
    """``to record them: sr-record ...`` for the skills whose ``<dataset_root>/<skill>`` folder does not exist,
    when ``--eval.env`` is ``needle`` or ``metaworld`` (the recorders' own environments; our choice: datasets given
    by path or repo_id, or evaluated elsewhere, get no guess)."""
    stream = cfg.stream
    if custom_env or cfg.eval.env not in ("needle", "metaworld") or stream.dataset_paths or stream.repo_ids:
        return None
    missing = [s for i, s in enumerate(stream.skills) if not stream.dataset_path(i).exists()]
    if not missing:
        return None
    env = " --env=metaworld" if cfg.eval.env == "metaworld" else ""
    return (f"to record them: sr-record{env} --root={stream.dataset_root} --skills=[{','.join(missing)}] "
            f"(sr-record{env} --help: episodes, images)")


def check_evaluation_envs(cfg: TrainStreamConfig, input_features: dict[str, Any], output_features: dict[str, Any],
                          custom_env: bool = False) -> None:
    """Every skill resolves to its evaluation environment before the first gradient (``--eval.env``).

    ``needle``: every skill must be a needle skill (``ValueError`` naming ``stream.skills`` and the valid names).
    ``metaworld`` / ``gym`` / ``lerobot``: every task must be a Meta-World v3 task, every gym id registered (its
    namespace module imported if needed), the LeRobot env type known and its config valid for each task; then each
    environment is built once, its action space and a reset observation must fit the policy's features
    (``input_features``, ``output_features``: those of the datasets) and, with videos, its recording twin must
    render ``rgb_array`` frames. ``ValueError`` naming the key (``eval.gym_ids[i]``, ``eval.env_type``,
    ``eval.env_tasks[i]``). ``none``: nothing to check. A factory given to :class:`ACTTrainer` (``custom_env``,
    tests) replaces the environment ``--eval.env`` names."""
    mode, skills = cfg.eval.env, list(cfg.stream.skills)
    if mode == "none" or custom_env:
        return
    check_skill_names(cfg)
    if mode == "needle":
        return
    if mode == "metaworld":
        check_recorded_tasks(cfg)
    images = [tuple(f.shape[:2]) if f.shape[-1] == 3 else tuple(f.shape[1:]) for key, f in input_features.items()
              if key.startswith("observation.images.")]
    size = images[0] if images and mode == "metaworld" else None  # the needle's own check is above; gym: their size
    make_env = make_env_factory(cfg.eval, skills, size)
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
    """Run or resume the stream described by ``cfg``; returns the results dictionary.

    Launched as several processes (``torchrun --nproc_per_node=N sr-train ...``), the processes join
    (:func:`sr_imitation.infra.distributed.start`), the wake's updates are data-parallel and the main process alone
    writes ``cfg.output_dir``; the others run in a private scratch copy, removed at the end, and return their
    progress (the main process returns the results)."""
    processes = distributed.start(cpu=cfg.policy.device == "cpu")
    # the one writer of cfg.output_dir holds its lock from before the run is built to the end (its `last` link, a push)
    with hold_folder(cfg.output_dir) if processes.is_main else contextlib.nullcontext():
        return _train(cfg, make_env, processes)


def _train(cfg: TrainStreamConfig, make_env: EnvFactory | None, processes: distributed.Processes) -> dict[str, Any]:
    """:func:`train_stream` once ``processes`` (:func:`sr_imitation.infra.distributed.start`) have joined."""
    if not processes.distributed:
        return ACTTrainer(cfg, make_env).run()
    if cfg.wake.batch_size < processes.world_size:
        raise ValueError(f"wake.batch_size: {cfg.wake.batch_size} rows cannot be split over {processes.world_size} "
                         "processes (each takes a slice of every batch); use at least one row per process")
    own = copy.copy(cfg)
    if not processes.is_main:
        own.output_dir = distributed.scratch_output(cfg.output_dir, cfg.resume, processes)
        own.progress, own.wandb = False, dataclasses.replace(cfg.wandb, enable=False)
        logging.getLogger().setLevel(logging.WARNING)  # the main process logs the run
    distributed.barrier()  # every copy is taken before the main process touches the run directory
    try:
        results = ACTTrainer(own, make_env).run()
        distributed.barrier()
    finally:
        distributed.remove_scratch(own.output_dir, processes)
    return results
