"""Every continual method on the needle stream, several training seeds, one table (the paper's Table 2).

    python -m sr_imitation.experiments.needle_compare --preset=configs/needle_cpu.json \\
        --seeds=[0,1,2,3,4] --variants=[sr,wake_only,sequential_bc,ewc,lwf,m2distill,mt_joint] \\
        --output_root=outputs/needle_compare

Variants (:data:`VARIANTS`): ``sr``; ``wake_only`` (SR without sleep); the paper's baselines ``sequential_bc``,
``ewc``, ``lwf``, ``m2distill``, with grids over the weights the paper does not give for ACT (EWC's lambda: ``ewc`` =
1, ``ewc_lam100``, ``ewc_lam10000``, ``ewc_lam1000000``; the distillation weights: ``lwf`` = 1, ``lwf_w0.1``,
``lwf_w0.01``, ``m2distill`` = 1, ``m2distill_w0.1``, ``m2distill_w0.01``); the SR
ablations ``sr_no_anchor`` (anchor strength 0), ``sr_mean_grad`` (the paper's Mean-grad: raw-gradient mean),
``sr_mean_normalized`` (mean of normalized gradients), ``sr_nash_fw`` (the paper's warm-started Frank-Wolfe, 5
iterations) and ``sr_sleep_only`` (our ablation: no wake-time distillation, gamma_k = 0, so every wake is sequential
BC and only sleep consolidates); the oracle ``mt_joint`` (:mod:`sr_imitation.imitation.mt_joint`, one ACT on the
union of the five datasets, reported apart). Every (variant, seed) is an ordinary ``sr-train`` run of the preset
(plus ``--extra`` flags) in ``<output_root>/<variant>_seed<seed>`` on the same recorded datasets (recorded once,
as by ``sr-main``); the runner skips finished runs (``results.json`` present), resumes killed ones and starts the
others, one after another, each evaluated on the preset's evaluation seeds.

Written to ``output_root`` (:func:`sr_imitation.stream.summary.write_summary`): ``summary.md`` / ``.json`` /
``.png`` (the final AFSR, PRS, BWT against both references and SPI, mean +- SE over training seeds, each seed's
value its mean over evaluation seeds; every metric's paired difference to ``sr`` over the seeds both have; the
final success per skill and the success right after each skill's own wake), ``dynamics.png`` (the metrics after
every stage, every method) and ``memory.md`` (the bytes and kinds each method's continual-learning mechanism
stores).
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

from sr_imitation.imitation.mt_joint import run_mt_joint
from sr_imitation.imitation.stream import TrainStreamConfig, train_stream
from sr_imitation.main_job import MainJobConfig, preset_with_datasets
from sr_imitation.offscreen import setup_offscreen_rendering
from sr_imitation.stream.config import check_choices
from sr_imitation.stream.summary import load_groups, print_final_means, write_summary
from sr_imitation.stream.summary import summarize as summary_of

logger = logging.getLogger(__name__)

# variant -> (continual method, sleep settings (--sleep.*) that differ from the preset)
VARIANTS: dict[str, tuple[str, dict[str, Any]]] = {
    "sr": ("sr", {"enabled": True}),
    "wake_only": ("sr", {"enabled": False}),
    "sequential_bc": ("sequential_bc", {"enabled": False}),
    "ewc": ("ewc", {"enabled": False}),
    "lwf": ("lwf", {"enabled": False}),
    "m2distill": ("m2distill", {"enabled": False}),
    "mt_joint": ("sequential_bc", {"enabled": False}),  # the oracle: run by imitation.mt_joint, not the stream
    # EWC's lambda grid on ACT (ewc above: lambda 1, the paper's MT5 choice); our grid, wider than the paper's MT5
    # {1, 100, 500}: the unit-Frobenius Fisher spreads over ACT's 678k deployed parameters, ~9x the SAC actor's
    "ewc_lam100": ("ewc", {"enabled": False}),
    "ewc_lam10000": ("ewc", {"enabled": False}),
    "ewc_lam1000000": ("ewc", {"enabled": False}),  # 10000 kept approach at 0.87 for three stages, lost it at the fifth
    # LwF's and M2Distill's distillation weights (the paper gives none; 1 is our default): at 1 LwF's teacher term on
    # the new skill's own observations outweighs the l1 behaviour cloning and the new skill is not learned
    # (seed 0: place 0.00 right after its wake), so the grid goes down
    "lwf_w0.1": ("lwf", {"enabled": False}),
    "lwf_w0.01": ("lwf", {"enabled": False}),
    "m2distill_w0.1": ("m2distill", {"enabled": False}),
    "m2distill_w0.01": ("m2distill", {"enabled": False}),
    "sr_no_anchor": ("sr", {"enabled": True, "anchor_strength": 0.0}),
    "sr_sleep_only": ("sr", {"enabled": True}),  # no wake distillation (POLICY): can sleep alone repair forgetting?
    "sr_mean_grad": ("sr", {"enabled": True, "aggregator": "mean_grad"}),  # the paper's Mean-grad (raw gradients)
    "sr_mean_normalized": ("sr", {"enabled": True, "aggregator": "mean_normalized"}),
    "sr_nash_fw": ("sr", {"enabled": True, "aggregator": "nash_fw"}),  # the paper's Frank-Wolfe, 5 iterations
}
OPTIONS: dict[str, dict[str, float]] = {
    "ewc_lam100": {"lam": 100.0}, "ewc_lam10000": {"lam": 10000.0}, "ewc_lam1000000": {"lam": 1e6},
    "lwf_w0.1": {"weight": 0.1}, "lwf_w0.01": {"weight": 0.01},
    "m2distill_w0.1": {"action_weight": 0.1, "feature_weight": 0.1},
    "m2distill_w0.01": {"action_weight": 0.01, "feature_weight": 0.01},
}
"""variant -> its method's --method_options."""
POLICY: dict[str, dict[str, float]] = {"sr_sleep_only": {"distill_weight_second": 0.0, "distill_weight_later": 0.0}}
"""variant -> policy settings (--policy.*) that differ from the preset (our ablation: sleep without the wake-time
distillation, i.e. sequential BC followed by each stage's sleep)."""
PAIRED_BASELINE = "sr"
TABLE_2 = ["sr", "wake_only", "sequential_bc", "ewc", "lwf", "m2distill", "mt_joint"]


@dataclass
class CompareConfig:
    preset: Path = Path("configs/needle_cpu.json")
    """The sr-main config every run starts from (its record section gives the datasets)."""
    seeds: list[int] = field(default_factory=lambda: [0, 1, 2, 3, 4])
    """Training seeds."""
    variants: list[str] = field(default_factory=lambda: list(TABLE_2))
    """Variants to run (:data:`VARIANTS`), in this order."""
    output_root: Path = Path("outputs/needle_compare")
    """Where the runs and the tables go."""
    extra: list[str] = field(default_factory=list)
    """sr-train flags added to every run (e.g. ``--eval.episodes=20``)."""

    def __post_init__(self) -> None:
        check_choices("variants", self.variants, VARIANTS)


def run_config(cfg: CompareConfig, base: MainJobConfig, variant: str, seed: int) -> TrainStreamConfig:
    """The ``sr-train`` config of one run: the preset's (with ``extra``) plus the variant's method and sleep."""
    train = copy.deepcopy(base.train)
    train.method, sleep_settings = VARIANTS[variant]
    train.sleep = dataclasses.replace(train.sleep, **sleep_settings)
    train.method_options = {**train.method_options, **OPTIONS.get(variant, {})}
    if variant in POLICY:
        train.policy = dataclasses.replace(train.policy, **POLICY[variant])
    train.seed = seed
    train.output_dir = cfg.output_root / f"{variant}_seed{seed}"
    train.resume = (train.output_dir / "progress.json").exists()
    return train


def run_compare(cfg: CompareConfig) -> dict:
    base = preset_with_datasets(cfg.preset, cfg.extra)
    runs: dict[str, dict[str, Path]] = {v: {} for v in cfg.variants}
    for variant in cfg.variants:
        for seed in cfg.seeds:
            train = run_config(cfg, base, variant, seed)
            if (train.output_dir / "results.json").exists():
                logger.info("=== %s seed %d: finished (%s), skipped", variant, seed, train.output_dir)
            else:
                logger.info("=== %s seed %d -> %s", variant, seed, train.output_dir)
                (run_mt_joint if variant == "mt_joint" else train_stream)(train)
            runs[variant][str(seed)] = train.output_dir
    return summarize(runs, cfg.output_root)


def summarize(runs: dict[str, dict[str, Path]], output_root: Path) -> dict[str, Any]:
    """The shared multi-run summary (:mod:`sr_imitation.stream.summary`) of ``{variant: {seed: run directory}}``,
    paired against ``sr`` (against the first variant without it); writes the tables and plots."""
    groups = load_groups(runs)
    summary = summary_of(groups, PAIRED_BASELINE if PAIRED_BASELINE in groups else next(iter(groups)))
    write_summary(output_root, summary)
    return summary


def main(args: list[str] | None = None) -> None:
    setup_offscreen_rendering()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    cfg = draccus.parse(CompareConfig, args=list(sys.argv[1:] if args is None else args))
    print_final_means(run_compare(cfg), [cfg.output_root / "summary.md", cfg.output_root / "memory.md"])


if __name__ == "__main__":
    main()
