"""Sleep vs wake-only vs sequential BC on the needle stream, several training seeds, one table.

    python -m sr_imitation.experiments.needle_compare --preset=configs/needle_cpu.json \\
        --seeds=[0,1,2] --variants=[sr,wake_only,sequential_bc] --output_root=outputs/needle_compare

Every (variant, seed) is an ordinary ``sr-train`` run in ``<output_root>/<variant>_seed<seed>`` on the same
recorded datasets (recorded once, as by ``sr-main``); an interrupted comparison resumes each run where it stopped.
The summary (``summary.json``, ``summary.md``) reports the final AFSR, PRS, BWT and SPI as mean +- standard error
over training seeds (each seed's value is itself the mean over its evaluation seeds).
"""

from __future__ import annotations

import copy
import json
import logging
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path

import draccus

from sr_imitation.core.io import atomic_write_bytes, atomic_write_json
from sr_imitation.core.metrics import mean_sem
from sr_imitation.imitation.stream import train_stream
from sr_imitation.main_job import MainJobConfig
from sr_imitation.record import RecordConfig, record

logger = logging.getLogger(__name__)

VARIANTS = {
    "sr": {"method": "sr", "sleep": True},
    "wake_only": {"method": "sr", "sleep": False},
    "sequential_bc": {"method": "sequential_bc", "sleep": False},
}
METRICS = ("afsr", "prs", "bwt", "spi")


@dataclass
class CompareConfig:
    """``preset``: the sr-main config every run starts from (its record section gives the datasets)."""

    preset: Path = Path("configs/needle_cpu.json")
    seeds: list[int] = field(default_factory=lambda: [0, 1, 2])
    variants: list[str] = field(default_factory=lambda: list(VARIANTS))
    output_root: Path = Path("outputs/needle_compare")

    def __post_init__(self) -> None:
        unknown = [v for v in self.variants if v not in VARIANTS]
        if unknown:
            raise ValueError(f"unknown variants {unknown}; choose from {sorted(VARIANTS)}")


def run_compare(cfg: CompareConfig) -> dict:
    base = draccus.parse(MainJobConfig, config_path=str(cfg.preset), args=[])
    rec = base.record
    missing = [s for s in rec.skills if not rec.target(s).exists()]
    if missing:
        record(RecordConfig(**{**vars(rec), "skills": missing}))
    finals: dict[str, dict[str, list[float]]] = {v: {m: [] for m in METRICS} for v in cfg.variants}
    runs = {}
    for variant in cfg.variants:
        for seed in cfg.seeds:
            train = copy.deepcopy(base.train)
            train.method = VARIANTS[variant]["method"]
            train.policy.sleep = VARIANTS[variant]["sleep"]
            train.seed = seed
            train.output_dir = cfg.output_root / f"{variant}_seed{seed}"
            train.resume = (train.output_dir / "progress.json").exists()
            logger.info("=== %s seed %d -> %s", variant, seed, train.output_dir)
            results = train_stream(train)
            runs[f"{variant}_seed{seed}"] = str(train.output_dir / "results.json")
            for m in METRICS:
                finals[variant][m].append(results["metrics"][m]["final_mean"])
    summary = {v: {m: dict(zip(("mean", "sem"), mean_sem([x for x in vals if x is not None]), strict=True))
                   | {"per_seed": vals} for m, vals in per.items()} for v, per in finals.items()}
    out = {"seeds": cfg.seeds, "runs": runs, "summary": summary}
    atomic_write_json(cfg.output_root / "summary.json", out)
    lines = [f"Final metrics after the full stream, mean +- SE over training seeds {cfg.seeds}:", "",
             "| variant | AFSR | PRS | BWT | SPI |", "|---|---|---|---|---|"]
    for v in cfg.variants:
        cells = [f"{summary[v][m]['mean']:.3f} +- {summary[v][m]['sem']:.3f}" for m in METRICS]
        lines.append(f"| {v} | " + " | ".join(cells) + " |")
    atomic_write_bytes(cfg.output_root / "summary.md", ("\n".join(lines) + "\n").encode())
    return out


def main(args: list[str] | None = None) -> None:
    os.environ.setdefault("MUJOCO_GL", "egl")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    cfg = draccus.parse(CompareConfig, args=list(sys.argv[1:] if args is None else args))
    result = run_compare(cfg)
    print(json.dumps(result["summary"], indent=2))  # noqa: T201
    print(f"written {cfg.output_root / 'summary.md'}")  # noqa: T201


if __name__ == "__main__":
    main()
