"""Sleep vs wake-only vs sequential BC on the needle stream, several training seeds, one table.

    python -m sr_imitation.experiments.needle_compare --preset=configs/needle_cpu.json \\
        --seeds=[0,1,2] --variants=[sr,wake_only,sequential_bc] --output_root=outputs/needle_compare

Variants: ``sr``, ``wake_only``, ``sequential_bc`` (the default three) and the sleep ablations ``sr_no_anchor``
(anchor strength 0) and ``sr_mean_grad`` (mean of normalized gradients instead of Nash). Every (variant, seed) is an
ordinary ``sr-train`` run in ``<output_root>/<variant>_seed<seed>`` on the same
recorded datasets (recorded once, as by ``sr-main``); an interrupted comparison resumes each run where it stopped.
The summary (``summary.json``, ``summary.md``, ``summary.png``) reports the final AFSR, PRS, BWT (reference: after
stage i), BWT_wake (reference: right after skill i's own wake) and SPI, the final success per skill and the success
right after each skill's own wake as mean +- standard error over training seeds (each seed's value is itself the
mean over its evaluation seeds), and every metric's paired difference to ``wake_only`` over the training seeds
both have.
"""

from __future__ import annotations

import copy
import json
import logging
import math
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import draccus
import numpy as np

from sr_imitation.core.io import atomic_write_bytes, atomic_write_json
from sr_imitation.core.metrics import bwt_curve, mean_sem
from sr_imitation.imitation.cli import parse_config
from sr_imitation.imitation.stream import train_stream
from sr_imitation.main_job import MainJobConfig
from sr_imitation.offscreen import setup_offscreen_rendering
from sr_imitation.record import RecordConfig, record

logger = logging.getLogger(__name__)

# variant -> (continual method, policy settings that differ from the preset)
VARIANTS: dict[str, tuple[str, dict[str, Any]]] = {
    "sr": ("sr", {"sleep": True}),
    "wake_only": ("sr", {"sleep": False}),
    "sequential_bc": ("sequential_bc", {"sleep": False}),
    "sr_no_anchor": ("sr", {"sleep": True, "anchor_strength": 0.0}),
    "sr_mean_grad": ("sr", {"sleep": True, "aggregator": "mean_grad"}),  # the paper's Mean-grad (raw gradients)
    "sr_mean_normalized": ("sr", {"sleep": True, "aggregator": "mean_normalized"}),
    "sr_nash_fw": ("sr", {"sleep": True, "aggregator": "nash_fw"}),  # the paper's Frank-Wolfe, 5 iterations
}
METRICS = ("afsr", "prs", "bwt", "bwt_wake", "spi")
LABELS = {"afsr": "AFSR", "prs": "PRS", "bwt": "BWT", "bwt_wake": "BWT_wake", "spi": "SPI"}
PAIRED_BASELINE = "wake_only"


@dataclass
class CompareConfig:
    """``preset``: the sr-main config every run starts from (its record section gives the datasets)."""

    preset: Path = Path("configs/needle_cpu.json")
    seeds: list[int] = field(default_factory=lambda: [0, 1, 2])
    variants: list[str] = field(default_factory=lambda: ["sr", "wake_only", "sequential_bc"])
    output_root: Path = Path("outputs/needle_compare")

    def __post_init__(self) -> None:
        unknown = [v for v in self.variants if v not in VARIANTS]
        if unknown:
            raise ValueError(f"unknown variants {unknown}; choose from {sorted(VARIANTS)}")


def run_compare(cfg: CompareConfig) -> dict:
    base = parse_config(MainJobConfig, cfg.preset, [])
    rec = base.record
    missing = [s for s in rec.skills if not rec.target(s).exists()]
    if missing:
        record(RecordConfig(**{**vars(rec), "skills": missing}))
    runs: dict[str, dict[str, Path]] = {v: {} for v in cfg.variants}
    for variant in cfg.variants:
        for seed in cfg.seeds:
            train = copy.deepcopy(base.train)
            train.method, policy_settings = VARIANTS[variant]
            for name, value in policy_settings.items():
                setattr(train.policy, name, value)
            train.seed = seed
            train.output_dir = cfg.output_root / f"{variant}_seed{seed}"
            train.resume = (train.output_dir / "progress.json").exists()
            logger.info("=== %s seed %d -> %s", variant, seed, train.output_dir)
            train_stream(train)
            runs[variant][str(seed)] = train.output_dir / "results.json"
    return summarize(runs, cfg.output_root)


def _mean_sem_dict(values: list[float | None]) -> dict[str, Any]:
    present = [float(x) for x in values if x is not None and math.isfinite(x)]
    mean, sem = mean_sem(present) if present else (float("nan"), float("nan"))
    return {"mean": mean, "sem": sem, "per_seed": values}


def _final(results: dict[str, Any], metric: str) -> float | None:
    """A run's final metric (mean over its evaluation seeds). Runs written before ``bwt_wake`` existed: computed
    from ``success_matrix`` and the diagonal of ``success_matrix_after_wake`` (linear in S, so equal to the mean of
    the per-evaluation-seed values)."""
    if metric in results["metrics"]:
        return results["metrics"][metric]["final_mean"]
    if metric != "bwt_wake":
        raise KeyError(f"results.json has no metric {metric!r}")
    s = np.array(results["success_matrix"], dtype=float)
    wake = np.diag(np.array(results["success_matrix_after_wake"], dtype=float))
    return float(bwt_curve(s, wake)[-1])


def _paired(summary: dict[str, Any], finals: dict[str, dict[str, dict[str, float | None]]]) -> dict[str, Any]:
    """Per variant: the difference to ``PAIRED_BASELINE`` of each metric, per training seed both have, mean +- SE."""
    if PAIRED_BASELINE not in finals:
        return {}
    base = finals[PAIRED_BASELINE]
    out: dict[str, Any] = {}
    for variant, per_metric in finals.items():
        seeds = [s for s in summary[variant]["seeds"] if s in summary[PAIRED_BASELINE]["seeds"]]
        if variant == PAIRED_BASELINE or not seeds:
            continue
        out[variant] = {"seeds": seeds}
        for m in METRICS:
            diffs = [None if per_metric[m][s] is None or base[m][s] is None else per_metric[m][s] - base[m][s]
                     for s in seeds]
            out[variant][m] = _mean_sem_dict(diffs)
    return out


def summarize(runs: dict[str, dict[str, Path]], output_root: Path) -> dict[str, Any]:
    """Mean +- SE over training seeds of the final metrics, the final success per skill and the success right
    after each skill's own wake, and paired differences to ``wake_only``; writes ``summary.json``, ``summary.md``
    and ``summary.png``."""
    summary: dict[str, Any] = {}
    skills: list[str] = []
    finals_by_seed: dict[str, dict[str, dict[str, float | None]]] = {}
    for variant, per_seed in runs.items():
        results = {seed: json.loads(Path(path).read_text()) for seed, path in per_seed.items()}
        skills = next(iter(results.values()))["skills"]
        finals_by_seed[variant] = {m: {seed: _final(r, m) for seed, r in results.items()} for m in METRICS}
        finals = {m: list(finals_by_seed[variant][m].values()) for m in METRICS}
        final_success = np.array([r["success_matrix"][-1] for r in results.values()], dtype=float)
        after_wake = np.array([np.diag(np.array(r["success_matrix_after_wake"], dtype=float))
                               for r in results.values()])
        summary[variant] = {
            "seeds": list(per_seed),
            "runs": {seed: str(path) for seed, path in per_seed.items()},
            **{m: _mean_sem_dict(finals[m]) for m in METRICS},
            "final_success": {s: _mean_sem_dict(final_success[:, i].tolist()) for i, s in enumerate(skills)},
            "success_after_own_wake": {s: _mean_sem_dict(after_wake[:, i].tolist())
                                       for i, s in enumerate(skills)},
        }
    paired = _paired(summary, finals_by_seed)
    atomic_write_json(output_root / "summary.json", {"skills": skills, "summary": summary,
                                                     f"paired_minus_{PAIRED_BASELINE}": paired})
    fmt = lambda d: f"{d['mean']:.3f} +- {d['sem']:.3f}"  # noqa: E731
    header = "| variant | seeds | " + " | ".join(LABELS[m] for m in METRICS) + " |"
    rule = "|---" * (len(METRICS) + 2) + "|"
    lines = ["Final metrics after the full stream, mean +- SE over training seeds. BWT: reference = success on skill "
             "i after stage i (after its sleep); BWT_wake: reference = success on skill i right after its own wake.",
             "", header, rule]
    for v, row in summary.items():
        lines.append(f"| {v} | {','.join(row['seeds'])} | " + " | ".join(fmt(row[m]) for m in METRICS) + " |")
    if paired:
        lines += ["", f"Paired difference variant - {PAIRED_BASELINE} (same training seed), mean +- SE:", "",
                  header, rule]
        for v, row in paired.items():
            lines.append(f"| {v} | {','.join(row['seeds'])} | " + " | ".join(fmt(row[m]) for m in METRICS) + " |")
    for key, title in (("final_success", "Final success per skill (after the last stage)"),
                       ("success_after_own_wake", "Success right after each skill's own wake phase")):
        lines += ["", f"{title}, mean +- SE over training seeds:", "",
                  "| variant | " + " | ".join(skills) + " |", "|---" * (len(skills) + 1) + "|"]
        for v, row in summary.items():
            lines.append(f"| {v} | " + " | ".join(fmt(row[key][s]) for s in skills) + " |")
    atomic_write_bytes(output_root / "summary.md", ("\n".join(lines) + "\n").encode())
    _plot(summary, skills, output_root / "summary.png")
    return summary


def _plot(summary: dict[str, Any], skills: list[str], path: Path) -> None:
    """Bars: mean over training seeds with +- SE; dots: the individual seeds."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    variants = list(summary)
    panels = [(LABELS[m], [summary[v][m] for v in variants]) for m in METRICS]
    fig, axes = plt.subplots(1, len(panels) + 1, figsize=(4 * (len(panels) + 1), 3.6))
    x = np.arange(len(variants))
    for ax, (title, cells) in zip(axes, panels, strict=False):
        ax.bar(x, [c["mean"] for c in cells], yerr=[c["sem"] for c in cells], capsize=4, color="#8fb3d9")
        for i, c in enumerate(cells):
            ys = [y for y in c["per_seed"] if y is not None]
            ax.scatter([i] * len(ys), ys, color="k", s=10, zorder=3)
        ax.set_xticks(x, variants, rotation=20)
        ax.set_title(title)
        ax.axhline(0.0, color="grey", lw=0.5)
    ax = axes[-1]
    width = 0.8 / max(len(variants), 1)
    for j, v in enumerate(variants):
        cells = [summary[v]["final_success"][s] for s in skills]
        ax.bar(np.arange(len(skills)) + j * width, [c["mean"] for c in cells], width,
               yerr=[c["sem"] for c in cells], capsize=2, label=v)
    ax.set_xticks(np.arange(len(skills)) + 0.4 - width / 2, skills, rotation=20)
    ax.set_ylim(0, 1.05)
    ax.set_title("final success per skill")
    ax.legend(fontsize=7)
    fig.tight_layout()
    tmp = path.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    os.replace(tmp, path)


def main(args: list[str] | None = None) -> None:
    setup_offscreen_rendering()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    cfg = draccus.parse(CompareConfig, args=list(sys.argv[1:] if args is None else args))
    summary = run_compare(cfg)
    print(json.dumps({v: {m: row[m]["mean"] for m in METRICS} for v, row in summary.items()}, indent=2))  # noqa: T201
    print(f"written {cfg.output_root / 'summary.md'}")  # noqa: T201


if __name__ == "__main__":
    main()
