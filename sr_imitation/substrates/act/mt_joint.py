"""The MT-Joint oracle of the paper's SurgicAI table (appendix B): one ACT policy trained on the union of the five
skills' demonstrations, reported apart (it is not a continual-learning method).

    python -m sr_imitation.substrates.act.mt_joint --config_path=configs/needle_cpu.json --seed=0 \\
        --output_dir=outputs/needle_mt_joint

Flags are ``sr-train``'s. The union is built here (LeRobot 0.4.4 has no ``MultiLeRobotDataset``): each skill's
dataset is loaded and split by episode exactly as its stream wake loads it, and the training and validation frames
are the concatenation of all skills' (:func:`union_data`). The same ACT, normalization (the stream's fixed
statistics, from the first skill's dataset), optimizer and wake loop as the stream; the budget is the stream's whole
wake budget: an epoch is one pass over the union (or ``max_steps_per_epoch`` times the number of skills when the
preset caps epochs), up to ``wake.max_epochs`` epochs with the same early stopping and restore rule. Then every skill
is evaluated exactly as in the stream (same evaluation seeds and episodes). Results use the shared schema; there is
no sequence, so the success matrix repeats the final evaluation in every row and the after-wake row; BWT = 0 by
definition; SPI (subspace preservation across stages) is undefined (null).

Phases (``progress.json``; a run killed inside a phase redoes it with the same numbers): ``1.wake`` (checkpoint
``mt_joint/wake``; a training killed inside continues from ``wake_snapshot.safetensors``, written every few minutes,
:mod:`sr_imitation.substrates.act.wake_snapshot`), ``1.wake.eval`` (its evaluation, next to it). Settings are
fingerprinted and checked before anything is written, as for a stream.
"""

from __future__ import annotations

import dataclasses
import logging
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sr_imitation.infra.fingerprint import STACK_KEY, SettingsFingerprint, settings_fingerprint
from sr_imitation.infra.folder_lock import hold_folder
from sr_imitation.infra.provenance import log_code_version
from sr_imitation.reporting.results import build_results, write_results
from sr_imitation.stream.rundir import RunDirectory
from sr_imitation.substrates.act.cli import _setup_logging, parse_train_args
from sr_imitation.substrates.act.config import STACK_HINT, stack
from sr_imitation.substrates.act.data import SkillData, check_stream_datasets, load_metadata, load_skill_data
from sr_imitation.substrates.act.report import pair_list
from sr_imitation.substrates.act.substrate import WAKE_SNAPSHOT, ACTSubstrate
from sr_imitation.substrates.act.trainer import (
    RESUME_ALLOW_LIST,
    SETTINGS_ADDED,
    TrainStreamConfig,
    check_evaluation_envs,
    inputs_check,
    naming_misspelled_skills,
    stored_config_dict,
    stream_inputs,
)
from sr_imitation.substrates.act.wake import wake_train

logger = logging.getLogger(__name__)

JOINT = "mt_joint"


class JointSubstrate(ACTSubstrate):
    """The ACT substrate with one stage, ``mt_joint``, holding the jointly trained policy and its evaluation."""

    def stage_dir_name(self, index: int) -> str:
        return JOINT

    def stats_metas(self, first_meta: Any) -> list[Any]:
        """``--stream.stats=seen``: the joint policy has seen every skill before its first gradient, so its statistics
        are those of all the datasets (``union``); ``first`` and ``union`` as for a stream."""
        if self.cfg.stream.stats != "seen":
            return super().stats_metas(first_meta)
        stream = self.cfg.stream
        return [first_meta] + [load_metadata(stream.dataset_path(i), stream.repo_id(i))
                               for i in range(1, len(self.skills))]


def union_data(substrate: ACTSubstrate) -> SkillData:
    """Every skill's dataset, split by episode as its own wake splits it, behind one index space."""
    cfg = substrate.cfg
    parts = [load_skill_data(skill, cfg.stream.dataset_path(i), cfg.stream.repo_id(i), substrate.policy_cfg,
                             cfg.wake.val_fraction, substrate.phase_seed(i, "wake"), cfg.stream.video_backend)
             for i, skill in enumerate(substrate.skills)]
    offsets = np.cumsum([0] + [len(p.dataset) for p in parts[:-1]]).tolist()
    return SkillData(
        JOINT, Path(cfg.stream.dataset_root), torch.utils.data.ConcatDataset([p.dataset for p in parts]),
        [o + i for p, o in zip(parts, offsets, strict=True) for i in p.train_indices],
        [o + i for p, o in zip(parts, offsets, strict=True) for i in p.val_indices],
    )


def joint_wake(cfg: TrainStreamConfig) -> Any:
    """The stream's wake settings with an epoch cap covering every skill (the stream's whole wake budget)."""
    cap = cfg.wake.max_steps_per_epoch
    return dataclasses.replace(cfg.wake, max_steps_per_epoch=None if cap is None else cap * len(cfg.stream.skills))


def joint_stored_config(cfg: TrainStreamConfig) -> dict[str, Any]:
    """The oracle's ``train_config.json``: the stream's stored config marked ``mt_joint``."""
    return {**stored_config_dict(cfg), "mt_joint": True}


def joint_fingerprint(cfg: TrainStreamConfig, inputs: dict[str, str] | None = None) -> SettingsFingerprint:
    """The settings an oracle run is fingerprinted with (checked on resume and by the drivers' archive), with the
    datasets' content digests (``inputs.datasets.<skill>``, computed unless given)."""
    inputs = stream_inputs(cfg) if inputs is None else inputs
    return settings_fingerprint(joint_stored_config(cfg), RESUME_ALLOW_LIST,
                                {"inputs": {"datasets": inputs}, STACK_KEY: stack()}, added=SETTINGS_ADDED,
                                stack_hint=STACK_HINT)


def run_mt_joint(cfg: TrainStreamConfig, make_env: Any = None) -> dict[str, Any]:
    """Train (or resume) the oracle in ``cfg.output_dir``, as its only writer (its lock held throughout); returns the
    results dictionary."""
    with hold_folder(cfg.output_dir):
        return _run_mt_joint(cfg, make_env)


def _run_mt_joint(cfg: TrainStreamConfig, make_env: Any) -> dict[str, Any]:
    """:func:`run_mt_joint` once ``cfg.output_dir``'s lock is held."""
    with naming_misspelled_skills(cfg, make_env is not None):
        _, input_features, output_features = check_stream_datasets(cfg.stream, cfg.policy.use_images)  # before writing
    check_evaluation_envs(cfg, input_features, output_features, custom_env=make_env is not None)
    stored = joint_stored_config(cfg)
    inputs = stream_inputs(cfg)
    run = RunDirectory(cfg.output_dir, joint_fingerprint(cfg, inputs), "train_config.json", stored, cfg.resume,
                       cfg.overwrite, check_inputs=inputs_check(cfg, inputs),
                       inputs=[cfg.stream.dataset_path(i) for i in range(len(cfg.stream.skills))])
    run.prepare()
    log_code_version(logger)
    substrate = JointSubstrate(cfg, make_env)
    with run.undo_on_error():  # a run --overwrite replaced comes back if the start fails
        substrate.setup()
        skills = substrate.skills
        if not run.done(0, "wake"):
            substrate.begin_phase(0, "wake", substrate.phase_seed(0, "wake"))
            t0 = time.perf_counter()
            result = wake_train(substrate.policy, substrate.preprocessor, union_data(substrate), joint_wake(cfg),
                                substrate.phase_seed(0, "wake"), cfg.progress,
                                snapshot=cfg.output_dir / WAKE_SNAPSHOT)
            substrate.save_policy(0, "wake", {"wake_history.json": result.history_record()})
            run.mark(0, "wake", {"seconds": time.perf_counter() - t0 + result.seconds_before_resume,
                                  "epochs": result.epochs, "best_epoch": result.best_epoch,
                                  "best_val_l1": result.best_val_l1, "steps": result.steps})
        else:
            substrate.load_policy(0, "wake")
    if not run.done(0, "wake.eval"):
        substrate.begin_phase(0, "wake.eval", substrate.phase_seed(0, "wake.eval"))
        run.mark(0, "wake.eval", substrate.evaluate(0, "wake.eval", list(range(len(skills)))))
    evals = substrate.read_eval(0, "wake")
    n = len(skills)
    common = {"substrate": "act", "method": JOINT, "sleep_enabled": False, "seed": cfg.seed, "skills": skills,
              "pairs": pair_list(cfg.stream.pairs, skills), "spi_features": [], "memory_bytes": {},
              "stages": [{"stage": 0, "skill": JOINT, "wake": run.record(0, "wake"),
                          "wake.eval": run.record(0, "wake.eval")}],
              "config": stored, "extra": {"oracle": "all skills trained jointly; rows repeat the final evaluation",
                                          "episodes_per_skill_per_unit": cfg.eval.episodes}}
    if cfg.eval.env == "none":  # no success to report: each skill's validation l1 under the joint policy
        results = build_results(**common, success=None, after_wake=None, spi=None, evaluation="none",
                                losses=_offline_losses([evals[s]["validation_l1"] for s in skills]))
        write_results(cfg.output_dir, results, plots=False)
        return results
    per_seed = np.array([evals[s]["success_per_seed"] for s in skills]).T  # (evaluation seeds, skills)
    matrix = np.repeat(per_seed[:, None, :], n, axis=1)
    matrix[:, np.triu_indices(n, 1)[0], np.triu_indices(n, 1)[1]] = np.nan
    results = build_results(**common, success=matrix, after_wake=per_seed, spi=np.full((per_seed.shape[0], n), np.nan),
                            evaluation=None if cfg.eval.env == "needle" else cfg.eval.env)
    write_results(cfg.output_dir, results)
    return results


def _offline_losses(validation_l1: list[float]) -> dict[str, Any]:
    """``losses`` of the oracle without an evaluation environment, in the stream's layout
    (:func:`~sr_imitation.substrates.act.report.loss_matrices`): every row the joint policy's validation l1 on each
    skill's validation episodes (the episodes the stream's wakes hold out: the union is split as each wake splits), null
    above the diagonal; no memories, and one joint wake instead of one per skill."""
    n = len(validation_l1)
    rows = np.tile(np.asarray(validation_l1, dtype=float), (n, 1))
    rows[np.triu_indices(n, 1)] = np.nan
    nothing = np.full((n, n), np.nan)
    return {"validation_l1": rows.tolist(), "validation_l1_after_wake": rows.tolist(),
            "memory_loss": nothing.tolist(), "memory_loss_after_wake": nothing.tolist(), "wake_best_val_l1": [None] * n}


def main(args: list[str] | None = None) -> None:
    from sr_imitation.infra.cli_errors import run_cli

    def _main(argv: list[str]) -> None:
        _setup_logging()
        cfg = parse_train_args(argv)
        results = run_mt_joint(cfg)
        final = dict(zip(results["skills"], results["success_matrix"][-1], strict=True))
        logger.info("MT-Joint: final success %s, AFSR %.3f", final, results["metrics"]["afsr"]["final"])

    run_cli("mt-joint", _main, list(sys.argv[1:] if args is None else args))


if __name__ == "__main__":
    main()
