"""``sr-train --substrate=sac``: the stream engine with :class:`~sr_imitation.rl.substrate.SACSubstrate` and
``cfg.method``, and the measurements of a finished run for the shared results (:mod:`sr_imitation.stream.results`).

Output layout (every file written atomically; ``progress.json`` records each phase after its files)::

    <output_dir>/settings_fingerprint.json, config.json   (written once at the start, never on resume)
    <output_dir>/progress.json
    <output_dir>/stages/01_reach/{wake/agent.safetensors, memory.safetensors, trajectories.safetensors}
    <output_dir>/stages/02_door-open/{wake/, sleep/agent.safetensors, sleep/sleep_diagnostics.json, ...}
    <output_dir>/videos/stage_02_door-open/{reach,door-open}_episode0_<success|failure>.mp4
    <output_dir>/results.json, results.md, metrics.png, success_matrix.png

Every phase seeds its own generators (:meth:`SACSubstrate.begin_phase`), so ``--resume`` after a kill at any point
continues from the last completed phase and, on CPU, reproduces the uninterrupted run exactly.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from sr_imitation.core.io import load_checked_safetensors, read_checked_json
from sr_imitation.core.metrics import all_pairs, spi_at_stage
from sr_imitation.rl.config import RLTrainConfig
from sr_imitation.rl.envs import MT5_PAIRS, canonical_skill
from sr_imitation.rl.evaluate import SPI_FEATURES
from sr_imitation.rl.substrate import CHECKPOINT_FORMAT, CHECKPOINT_VERSION, SACSubstrate, stage_seed
from sr_imitation.stream import RunDirectory, StreamEngine, make_method
from sr_imitation.stream import results as shared_results
from sr_imitation.stream.results import RESULTS_VERSION, build_results
from sr_imitation.stream.substrate import PHASES

logger = logging.getLogger(__name__)

__all__ = ["CHECKPOINT_FORMAT", "CHECKPOINT_VERSION", "RESULTS_VERSION", "StreamTrainer", "prs_pairs", "stage_seed",
           "write_results"]


def prs_pairs(skills: list[str]) -> tuple[tuple[str, str], ...]:
    """MT5 (either order): the paper's six pairs; MT8: all 28 pairs; other lists: MT5 pairs present, else all."""
    names = [canonical_skill(s) for s in skills]
    if len(names) == 8:
        return all_pairs(names)
    present = tuple(p for p in MT5_PAIRS if p[0] in names and p[1] in names)
    return present or all_pairs(names)


def check_skill_names(skills: list[str]) -> None:
    """Every skill is a Meta-World v3 environment: ``ValueError`` naming ``stream.skills`` and the unknown names
    (before: a typo in the third skill surfaced after two stages had trained)."""
    import metaworld  # noqa: PLC0415 (only the SAC substrate needs Meta-World)

    unknown = [s for s in skills if s not in metaworld.MT1.ENV_NAMES]
    if unknown:
        raise ValueError(f"stream.skills: {unknown} are not Meta-World v3 environments (use '-v3' names, e.g. "
                         "'reach-v3')")


class StreamTrainer:
    """Runs (or resumes) one seed of the stream described by ``cfg`` on the stream engine.

    ``after_stage`` (tests) is called with the stage index after each completed stage; raising there simulates
    a killed run (``after_phase(k, phase)``: after each phase).
    """

    def __init__(self, cfg: RLTrainConfig, after_stage: Callable[[int], None] | None = None,
                 after_phase: Callable[[int, str], None] | None = None) -> None:
        self.cfg = cfg
        self.skills = cfg.stream_skills
        check_skill_names(self.skills)  # before the run directory is touched and the first gradient
        self.out = Path(cfg.output_dir)
        self.substrate = SACSubstrate(cfg)
        self.method = make_method(cfg.method, SACSubstrate.name, self.substrate.method_settings())
        # Runs from before the engine (one checkpoint per stage) cannot be resumed by it: no legacy settings.
        self.run_dir = RunDirectory(self.out, cfg.resume_fingerprint(), "config.json", cfg.stored_config(),
                                    cfg.resume, cfg.overwrite)
        self.engine = StreamEngine(self.substrate, self.method, self.run_dir, cfg.progress, self._after_phase,
                                   wandb=cfg.wandb, log_config=cfg.stored_config(), extend_from=cfg.stream.extend_from)
        self.after_stage, self.after_phase = after_stage, after_phase

    def _after_phase(self, k: int, phase: str) -> None:
        if self.after_phase is not None:
            self.after_phase(k, phase)
        if self.after_stage is not None and phase == self.engine.phases(k)[-1]:
            self.after_stage(k)

    def stage_dir(self, k: int) -> Path:
        return self.substrate.stage_dir(k)

    def run(self) -> dict[str, Any]:
        return self.engine.run()


def _stage_records(sub: SACSubstrate, progress: dict[str, Any]) -> list[dict[str, Any]]:
    """Per stage: wake summary, memory size, the stage evaluation rows, the after-wake row, the sleep record."""
    done = progress["completed"]
    records = []
    for k, skill in enumerate(sub.skills):
        key = lambda phase, k=k: f"{k + 1}.{phase}"  # noqa: E731
        rec: dict[str, Any] = {"stage": k, "skill": skill, "wake": done[key("wake")]["wake"]}
        if key("memory") in done:
            rec["memory"] = {"states": done[key("memory")]["size"], "nbytes": done[key("memory")]["bytes"]}
        wake_rows = done[key("wake.eval")]["rows"]
        if key("sleep") in done:
            if wake_rows:
                rec["eval_after_wake"] = {**wake_rows[-1], "reused_stage_evaluation": False}
            sleep = dict(done[key("sleep")])
            diagnostics = read_checked_json(sub.stage_dir(k) / "sleep" / "sleep_diagnostics.json")
            objective = diagnostics.get("sleep_objective") or []
            sleep.update(anchor_distances=diagnostics.get("anchor_distances"),
                         sleep_objective_first_last=[objective[0], objective[-1]] if objective else None)
            if "frozen_critic_value_before" in sleep:  # SR's sleep (a method's distillation has no critics)
                before, after = sleep["frozen_critic_value_before"], sleep["frozen_critic_value_after"]
                sleep["frozen_critic_value_change"] = [a - b for a, b in zip(after, before, strict=True)]
            rec["sleep"] = sleep
            rec["eval"] = done[key("sleep.eval")]["rows"]
        else:  # no sleep: the after-wake policy is the stage policy (same configurations: the same numbers)
            rec["eval"] = wake_rows
            row = {name: value for name, value in wake_rows[-1].items() if name != "videos"}
            rec["eval_after_wake"] = {**row, "reused_stage_evaluation": True}
        rec["seconds"] = sum(float(done[key(p)].get("seconds", 0.0)) for p in
                             PHASES if key(p) in done)
        records.append(rec)
    return records


def write_results(sub: SACSubstrate, progress: dict[str, Any], memories: Any) -> dict[str, Any]:
    """Build the shared results (:mod:`sr_imitation.stream.results`: ``results.json``, ``results.md`` and, with
    ``cfg.plots``, ``metrics.png`` / ``success_matrix.png``) of a finished run from its phases. One evaluation unit:
    every stage evaluates a skill on the same fixed configurations."""
    cfg = sub.cfg
    records = _stage_records(sub, progress)
    n = len(sub.skills)
    matrix = np.full((n, n), np.nan)
    for k, rec in enumerate(records):
        for i, row in enumerate(rec["eval"]):
            matrix[k, i] = row["success_rate"]
    trajectories = []
    for k in range(n):
        tensors, _ = load_checked_safetensors(sub.stage_dir(k) / "trajectories.safetensors")
        trajectories.append({name.removeprefix("traj."): t.numpy() for name, t in tensors.items()})
    names = [canonical_skill(s) for s in sub.skills]
    reference = {names[i]: trajectories[i][names[i]] for i in range(n)}
    spi = [spi_at_stage(reference, trajectories[k], names[:k]) for k in range(n)]
    after_wake = [rec["eval_after_wake"]["success_rate"] if "eval_after_wake" in rec else np.nan for rec in records]
    per_skill, per_kind = shared_results.memory_budget(memories)
    results = build_results(
        substrate=SACSubstrate.name, method=cfg.method, sleep_enabled=cfg.sleep.enabled, seed=cfg.seed,
        skills=names, pairs=prs_pairs(sub.skills), success=matrix[None], after_wake=np.array([after_wake]),
        spi=np.array([spi]), spi_features=SPI_FEATURES, memory_bytes=per_skill, memory_kinds=per_kind,
        stages=records, config=cfg.stored_config())
    shared_results.write_results(sub.out, results, plots=cfg.plots)
    return results
