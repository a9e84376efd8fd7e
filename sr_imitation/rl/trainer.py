"""``sr-rl-train`` on the SAC substrate: the stream engine with :class:`~sr_imitation.rl.substrate.SACSubstrate`
and ``cfg.method``, and the results of a finished run (success matrix, AFSR/PRS/BWT after-stage and
after-own-wake/SPI, ``results.json``, ``report.md``, plots).

Output layout (every file written atomically; ``progress.json`` records each phase after its files)::

    <output_dir>/settings_fingerprint.json, config.json   (written once at the start, never on resume)
    <output_dir>/progress.json
    <output_dir>/stages/01_reach/{wake/agent.safetensors, memory.safetensors, trajectories.safetensors}
    <output_dir>/stages/02_door-open/{wake/, sleep/agent.safetensors, sleep/sleep_diagnostics.json, ...}
    <output_dir>/videos/stage_02_door-open/{reach,door-open}_episode0_<success|failure>.mp4
    <output_dir>/results.json, report.md, plots/*.png

Every phase seeds its own generators (:meth:`SACSubstrate.begin_phase`), so ``--resume`` after a kill at any point
continues from the last completed phase and, on CPU, reproduces the uninterrupted run exactly.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from sr_imitation.core.io import atomic_write_bytes, atomic_write_json, load_checked_safetensors
from sr_imitation.core.metrics import (
    MT5_PAIRS,
    all_pairs,
    canonical_skill,
    spi_at_stage,
    stream_metrics,
)
from sr_imitation.rl.config import RLTrainConfig
from sr_imitation.rl.evaluate import SPI_FEATURES
from sr_imitation.rl.substrate import CHECKPOINT_FORMAT, CHECKPOINT_VERSION, SACSubstrate, stage_seed
from sr_imitation.stream import RunDirectory, StreamEngine, make_method

logger = logging.getLogger(__name__)

__all__ = ["CHECKPOINT_FORMAT", "CHECKPOINT_VERSION", "RESULTS_VERSION", "StreamTrainer", "prs_pairs",
           "render_report", "stage_seed", "write_plots", "write_results"]

RESULTS_VERSION = 3
"""results.json schema: 3 adds ``method_name`` and records stages from the engine's phases (2 adds
``success_after_own_wake``, ``metrics.bwt_wake``, ``spi_features``)."""


def prs_pairs(skills: list[str]) -> tuple[tuple[str, str], ...]:
    """MT5 (either order): the paper's six pairs; MT8: all 28 pairs; other lists: MT5 pairs present, else all."""
    names = [canonical_skill(s) for s in skills]
    if len(names) == 8:
        return all_pairs(names)
    present = tuple(p for p in MT5_PAIRS if p[0] in names and p[1] in names)
    return present or all_pairs(names)


class StreamTrainer:
    """Runs (or resumes) one seed of the stream described by ``cfg`` on the stream engine.

    ``after_stage`` (tests) is called with the stage index after each completed stage; raising there simulates
    a killed run (``after_phase(k, phase)``: after each phase).
    """

    def __init__(self, cfg: RLTrainConfig, after_stage: Callable[[int], None] | None = None,
                 after_phase: Callable[[int, str], None] | None = None) -> None:
        self.cfg = cfg
        self.skills = cfg.stream_skills
        self.out = Path(cfg.output_dir)
        self.substrate = SACSubstrate(cfg)
        self.method = make_method(cfg.method, SACSubstrate.name, self.substrate.method_settings())
        # Runs from before the engine (one checkpoint per stage) cannot be resumed by it: no legacy settings.
        self.run_dir = RunDirectory(self.out, cfg.resume_fingerprint(), "config.json", cfg.stored_config(),
                                    cfg.resume, cfg.overwrite)
        self.engine = StreamEngine(self.substrate, self.method, self.run_dir, cfg.progress, self._after_phase,
                                   wandb=cfg.wandb, log_config=cfg.stored_config(), extend_from=cfg.extend_from)
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
            diagnostics = json.loads((sub.stage_dir(k) / "sleep" / "sleep_diagnostics.json").read_text())
            before, after = sleep["frozen_critic_value_before"], sleep["frozen_critic_value_after"]
            objective = diagnostics.get("sleep_objective") or []
            sleep.update(frozen_critic_value_change=[a - b for a, b in zip(after, before, strict=True)],
                         anchor_distances=diagnostics.get("anchor_distances"),
                         sleep_objective_first_last=[objective[0], objective[-1]] if objective else None)
            rec["sleep"] = sleep
            rec["eval"] = done[key("sleep.eval")]["rows"]
        else:  # no sleep: the after-wake policy is the stage policy (same configurations: the same numbers)
            rec["eval"] = wake_rows
            row = {name: value for name, value in wake_rows[-1].items() if name != "videos"}
            rec["eval_after_wake"] = {**row, "reused_stage_evaluation": True}
        rec["seconds"] = sum(float(done[key(p)].get("seconds", 0.0)) for p in
                             ("wake", "memory", "wake.eval", "sleep", "sleep.eval") if key(p) in done)
        records.append(rec)
    return records


def write_results(sub: SACSubstrate, progress: dict[str, Any], memories: Any) -> dict[str, Any]:
    """Build ``results.json``, ``report.md`` and (``cfg.plots``) the plots of a finished run from its phases."""
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
    pairs = prs_pairs(sub.skills)
    after_wake = [rec["eval_after_wake"]["success_rate"] if "eval_after_wake" in rec else None for rec in records]
    complete = all(x is not None for x in after_wake[:-1])
    metrics = stream_metrics(matrix, names, pairs, spi=spi,
                             wake_diagonal=[np.nan if x is None else x for x in after_wake] if complete else None)
    if not complete:  # eval.after_wake was off: the after-own-wake reference was not measured
        metrics["bwt_wake"], metrics["bwt_wake_curve"] = float("nan"), [float("nan")] * n
    method = cfg.method
    label = {"sr": "sleeping_robots" if cfg.sleep_enabled else "wake_only"}.get(method, method)
    results = {
        "results_version": RESULTS_VERSION,
        "seed": cfg.seed,
        "skills": names,
        "method": label,
        "method_name": method,
        "pairs": [list(p) for p in pairs],
        "success_matrix": [[None if np.isnan(x) else float(x) for x in row] for row in matrix],
        "success_after_own_wake": after_wake,
        "metrics": _nan_to_none(metrics),
        "spi_features": list(SPI_FEATURES),
        "memory_nbytes_total": int(sum(m.nbytes() for m in memories)),
        "stages": records,
        "config": cfg.stored_config(),
    }
    atomic_write_json(sub.out / "results.json", results)
    atomic_write_bytes(sub.out / "report.md", render_report(results).encode())
    if cfg.plots:
        write_plots(results, sub.out / "plots")
    return results


def _nan_to_none(obj: Any) -> Any:
    """Strict JSON: NaN (undefined metric, e.g. PRS at k = 1) becomes null."""
    if isinstance(obj, dict):
        return {k: _nan_to_none(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_nan_to_none(v) for v in obj]
    if isinstance(obj, float) and np.isnan(obj):
        return None
    return obj


REPORT_METRICS = ("afsr", "prs", "bwt", "bwt_wake", "spi")
METRIC_LABELS = {"afsr": "AFSR", "prs": "PRS", "bwt": "BWT (ref. after stage i)",
                 "bwt_wake": "BWT_wake (ref. after own wake)", "spi": "SPI"}


def render_report(results: dict[str, Any]) -> str:
    """A short markdown report: success matrix, success right after each skill's own wake, final metrics."""
    names = results["skills"]
    lines = [f"# SAC stream report ({results['method']}, seed {results['seed']})", "",
             "Success S[k, i] after stage k (rows) on skill i (columns):", "",
             "| after \\ skill | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
    for k, row in enumerate(results["success_matrix"]):
        cells = ["" if x is None else f"{x:.2f}" for x in row]
        lines.append(f"| {k + 1}. {names[k]} | " + " | ".join(cells) + " |")
    wake = results.get("success_after_own_wake")
    if wake is not None:
        lines.append("| right after own wake | " + " | ".join("-" if x is None else f"{x:.2f}" for x in wake) + " |")
    m = results["metrics"]
    lines += ["", "| metric | final | per stage |", "|---|---|---|"]
    for key in REPORT_METRICS:
        if key in m:
            curve = ", ".join("-" if x is None else f"{x:.3f}" for x in m[f"{key}_curve"])
            final = "-" if m[key] is None else f"{m[key]:.3f}"
            lines.append(f"| {METRIC_LABELS[key]} | {final} | {curve} |")
    lines += ["", f"Memory stored: {results['memory_nbytes_total'] / 1e6:.2f} MB", ""]
    return "\n".join(lines)


def write_plots(results: dict[str, Any], plot_dir: Path) -> None:
    """Success-matrix heatmap and metric curves (PNG, written atomically)."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = results["skills"]
    matrix = np.array([[np.nan if x is None else x for x in row] for row in results["success_matrix"]])
    fig, ax = plt.subplots(figsize=(1.2 * len(names) + 2, 1.0 * len(names) + 1.5))
    im = ax.imshow(matrix, vmin=0, vmax=1, cmap="viridis")
    ax.set_xticks(range(len(names)), names, rotation=45, ha="right")
    ax.set_yticks(range(len(names)), [f"after {n}" for n in names])
    for (k, i), v in np.ndenumerate(matrix):
        if not np.isnan(v):
            ax.text(i, k, f"{v:.2f}", ha="center", va="center", color="w" if v < 0.5 else "k", fontsize=8)
    fig.colorbar(im, ax=ax, label="success")
    ax.set_title(f"{results['method']} seed {results['seed']}")
    _save_fig(fig, plot_dir / "success_matrix.png", io, plt)

    m = results["metrics"]
    fig, axes = plt.subplots(1, 4, figsize=(14, 3))
    for ax, keys in zip(axes, (("afsr",), ("prs",), ("bwt", "bwt_wake"), ("spi",)), strict=True):
        for key in keys:
            curve = [np.nan if x is None else x for x in m.get(f"{key}_curve", [])]
            ax.plot(range(1, len(curve) + 1), curve, marker="o", label=METRIC_LABELS[key])
        ax.set_title(" / ".join(key.upper() for key in keys))
        if len(keys) > 1:
            ax.legend(fontsize=7)
        ax.set_xlabel("stage k")
        ax.grid(alpha=0.3)
    _save_fig(fig, plot_dir / "metrics.png", io, plt)


def _save_fig(fig, path: Path, io, plt) -> None:
    buf = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())
