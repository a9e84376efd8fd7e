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
import dataclasses
import logging
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import draccus

from sr_imitation.imitation.cli import parse_config
from sr_imitation.imitation.stream import train_stream
from sr_imitation.main_job import MainJobConfig
from sr_imitation.offscreen import setup_offscreen_rendering
from sr_imitation.record import RecordConfig, record
from sr_imitation.stream.summary import load_groups, print_final_means, write_summary
from sr_imitation.stream.summary import summarize as summary_of

logger = logging.getLogger(__name__)

# variant -> (continual method, sleep settings (--sleep.*) that differ from the preset)
VARIANTS: dict[str, tuple[str, dict[str, Any]]] = {
    "sr": ("sr", {"enabled": True}),
    "wake_only": ("sr", {"enabled": False}),
    "sequential_bc": ("sequential_bc", {"enabled": False}),
    "sr_no_anchor": ("sr", {"enabled": True, "anchor_strength": 0.0}),
    "sr_mean_grad": ("sr", {"enabled": True, "aggregator": "mean_grad"}),  # the paper's Mean-grad (raw gradients)
    "sr_mean_normalized": ("sr", {"enabled": True, "aggregator": "mean_normalized"}),
    "sr_nash_fw": ("sr", {"enabled": True, "aggregator": "nash_fw"}),  # the paper's Frank-Wolfe, 5 iterations
}
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
            train.method, sleep_settings = VARIANTS[variant]
            train.sleep = dataclasses.replace(train.sleep, **sleep_settings)
            train.seed = seed
            train.output_dir = cfg.output_root / f"{variant}_seed{seed}"
            train.resume = (train.output_dir / "progress.json").exists()
            logger.info("=== %s seed %d -> %s", variant, seed, train.output_dir)
            train_stream(train)
            runs[variant][str(seed)] = train.output_dir
    return summarize(runs, cfg.output_root)


def summarize(runs: dict[str, dict[str, Path]], output_root: Path) -> dict[str, Any]:
    """The shared multi-run summary (:mod:`sr_imitation.stream.summary`) of ``{variant: {seed: run directory}}``,
    paired against ``wake_only``; writes ``summary.json``, ``summary.md`` and ``summary.png``."""
    summary = summary_of(load_groups(runs), PAIRED_BASELINE)
    write_summary(output_root, summary)
    return summary


def main(args: list[str] | None = None) -> None:
    setup_offscreen_rendering()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    cfg = draccus.parse(CompareConfig, args=list(sys.argv[1:] if args is None else args))
    print_final_means(run_compare(cfg), [cfg.output_root / "summary.md"])


if __name__ == "__main__":
    main()
