"""The memory-budget curve: final AFSR and BWT_wake against stored frames per skill.

    python -m experiments.memory_budget \\
        --points=[8=docs/results/needle_cpu_m8_compare,16=docs/results/needle_cpu_m16_compare,...] \\
        --variants=[sr,wake_only,replay] --output=docs/results/memory_budget

Each point is an archive of finished runs (``<variant>_seed<S>/``) of the same preset with
``memory.buffer_size`` = the point's budget (checked against each run's stored config). Per budget and variant: the
mean +- SE over training seeds of the final AFSR and BWT_wake, and the paired SR - other difference over the seeds
both have. Written: ``memory_budget.md`` / ``.json`` / ``.png`` (two panels, log-scale budget axis).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sr_imitation.experiments.hypotheses import archived_runs
from sr_imitation.infra.cli_errors import run_cli, setup_logging
from sr_imitation.infra.cli_parsing import parse_command
from sr_imitation.io import atomic_write_bytes, write_checked_json
from sr_imitation.reporting.summary import mean_sem_dict

logger = logging.getLogger(__name__)
PROG = "python -m experiments.memory_budget"
"""The command as a user types it (usage errors and ``--help`` name it)."""

PANELS = (("afsr", "final AFSR"), ("bwt_wake", "final BWT_wake"))


@dataclass
class BudgetConfig:
    points: list[str] = field(default_factory=list)
    """``<frames per skill>=<archive folder>`` per budget."""
    variants: list[str] = field(default_factory=lambda: ["sr", "wake_only", "replay"])
    """Variants drawn (the first is the paired reference)."""
    seeds: list[int] | None = None
    """Training seeds drawn at every point (e.g. [0,1,2], so that every budget averages the same seeds); null: every
    archived seed of each point."""
    output: Path | None = None
    """Where memory_budget.md / .json / .png go (none: print only)."""

    def __post_init__(self) -> None:
        for point in self.points:
            budget, _, folder = point.partition("=")
            if not budget.isdigit() or not folder:
                raise ValueError(f"points: {point!r} is not <frames per skill>=<archive folder>")


def _runs(archive: Path, variant: str, budget: int) -> dict[int, dict[str, Any]]:
    runs = archived_runs(archive, variant)
    for seed, results in runs.items():
        stored = ((results.get("config") or {}).get("memory") or {}).get("buffer_size")
        if stored is not None and int(stored) != budget:
            raise ValueError(f"{archive / f'{variant}_seed{seed}'}: memory.buffer_size {stored}, but its point says "
                             f"{budget}")
    return runs


def collect(cfg: BudgetConfig) -> dict[str, Any]:
    reference = cfg.variants[0]
    table: dict[str, Any] = {}
    for point in cfg.points:
        budget_text, _, folder = point.partition("=")
        budget = int(budget_text)
        runs = {v: {s: r for s, r in _runs(Path(folder), v, budget).items() if cfg.seeds is None or s in cfg.seeds}
                for v in cfg.variants}
        row: dict[str, Any] = {"archive": folder}
        for v in cfg.variants:
            row[v] = {m: mean_sem_dict([r["metrics"][m]["final"] for r in runs[v].values()]) for m, _ in PANELS}
            row[v]["seeds"] = sorted(runs[v])
            if v != reference:
                seeds = sorted(set(runs[v]) & set(runs[reference]))
                row[v]["paired_to_" + reference] = {
                    m: mean_sem_dict([runs[reference][s]["metrics"][m]["final"] - runs[v][s]["metrics"][m]["final"]
                                      for s in seeds]) for m, _ in PANELS} | {"seeds": seeds}
        table[str(budget)] = row
    return {"variants": list(cfg.variants), "reference": reference, "budgets": table}


def render(summary: dict[str, Any]) -> str:
    ref = summary["reference"]
    others = [v for v in summary["variants"] if v != ref]
    head = ["frames/skill"] + [f"{v} {m}" for v in summary["variants"] for m, _ in PANELS]
    head += [f"{ref} - {v} AFSR (paired)" for v in others]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]

    def fmt(d: dict[str, Any], n: list[int] | None = None) -> str:
        if not np.isfinite(d["mean"]):
            return "-"
        sem = "" if not np.isfinite(d["sem"]) else f" +- {d['sem']:.3f}"
        return f"{d['mean']:+.3f}{sem}" + (f" (n={len(n)})" if n is not None else "")

    for budget, row in sorted(summary["budgets"].items(), key=lambda kv: int(kv[0])):
        cells = [budget] + [fmt(row[v][m], row[v]["seeds"]) for v in summary["variants"] for m, _ in PANELS]
        cells += [fmt(row[v]["paired_to_" + ref]["afsr"], row[v]["paired_to_" + ref]["seeds"]) for v in others]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def plot(summary: dict[str, Any], path: Path) -> None:
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    budgets = sorted(summary["budgets"], key=int)
    fig, axes = plt.subplots(1, len(PANELS), figsize=(5 * len(PANELS), 3.6))
    for ax, (metric, title) in zip(axes, PANELS, strict=True):
        for v in summary["variants"]:
            x = [int(b) for b in budgets if summary["budgets"][b][v]["seeds"]]
            stats = [summary["budgets"][b][v][metric] for b in budgets if summary["budgets"][b][v]["seeds"]]
            mean = np.array([s["mean"] for s in stats])
            sem = np.nan_to_num(np.array([s["sem"] for s in stats], dtype=float))
            ax.errorbar(x, mean, yerr=sem, marker="o", capsize=3, label=v)
        ax.set_xscale("log", base=2)
        ax.set_xlabel("stored frames per skill")
        ax.set_title(title + " (mean +- SE over training seeds)")
        ax.grid(alpha=0.3)
    axes[0].legend()
    fig.tight_layout()
    tmp = path.with_name(f".{path.name}.tmp.png")
    fig.savefig(tmp, dpi=120)
    plt.close(fig)
    atomic_write_bytes(path, tmp.read_bytes())
    tmp.unlink()


def main(args: list[str] | None = None) -> None:
    setup_logging()
    cfg = parse_command(BudgetConfig, args, prog=PROG)
    summary = collect(cfg)
    text = render(summary)
    if cfg.output is not None:
        write_checked_json(cfg.output / "memory_budget.json", summary)
        atomic_write_bytes(cfg.output / "memory_budget.md", text.encode())
        plot(summary, cfg.output / "memory_budget.png")
    print(text)  # noqa: T201 (command output)


if __name__ == "__main__":
    run_cli(PROG, main)
