"""The shared results of a finished SAC run (:mod:`sr_imitation.reporting.results`), from its recorded phases.

``results.json``, ``results.md`` and, with ``cfg.plots``, ``metrics.png`` / ``success_matrix.png``: the success
matrix, the after-wake evaluation, SPI against each skill's own trajectories, memory bytes by kind and one record per
stage. Reads the run through :class:`RunFiles` (what :class:`~sr_imitation.substrates.sac.substrate.SACSubstrate`
provides), so the substrate calls it without this module importing the substrate.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Protocol

import numpy as np

from sr_imitation.core.memory import Memory
from sr_imitation.core.metrics import all_pairs, spi_at_stage
from sr_imitation.envs.metaworld.tasks import MT5_PAIRS, canonical_skill
from sr_imitation.io import load_checked_safetensors, read_checked_json
from sr_imitation.reporting import results as shared_results
from sr_imitation.reporting.results import build_results
from sr_imitation.stream.substrate import PHASES
from sr_imitation.substrates.sac.config import RLTrainConfig
from sr_imitation.substrates.sac.evaluate import SPI_FEATURES

SUBSTRATE = "sac"
"""The substrate's registry name (``SACSubstrate.name``)."""


class RunFiles(Protocol):
    """A SAC run's configuration and where its stages are."""

    cfg: RLTrainConfig
    skills: list[str]
    out: Path

    def stage_dir(self, k: int) -> Path:
        """The folder of stage ``k``'s files."""


def prs_pairs(skills: list[str]) -> tuple[tuple[str, str], ...]:
    """MT5 (either order): the paper's six pairs; MT8: all 28 pairs; other lists: MT5 pairs present, else all."""
    names = [canonical_skill(s) for s in skills]
    if len(names) == 8:
        return all_pairs(names)
    present = tuple(p for p in MT5_PAIRS if p[0] in names and p[1] in names)
    return present or all_pairs(names)



def _stage_records(sub: RunFiles, progress: dict[str, Any]) -> list[dict[str, Any]]:
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


def write_results(sub: RunFiles, progress: dict[str, Any], memories: list[Memory]) -> dict[str, Any]:
    """Build the shared results (:mod:`sr_imitation.reporting.results`: ``results.json``, ``results.md`` and, with
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
        substrate=SUBSTRATE, method=cfg.method, sleep_enabled=cfg.sleep.enabled, seed=cfg.seed,
        skills=names, pairs=prs_pairs(sub.skills), success=matrix[None], after_wake=np.array([after_wake]),
        spi=np.array([spi]), spi_features=SPI_FEATURES, memory_bytes=per_skill, memory_kinds=per_kind,
        stages=records, config=cfg.stored_config())
    shared_results.write_results(sub.out, results, plots=cfg.plots)
    return results
