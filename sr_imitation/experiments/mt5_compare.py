"""Every continual method on the Meta-World stream, several training seeds, one table.

    python -m sr_imitation.experiments.mt5_compare --preset=configs/sac_mt5_cpu.json \\
        --seeds=[0,1] --variants=[sr,wake_only,ewc] --output_root=outputs/mt5_compare

Each (variant, seed) is an ordinary ``sr-train --substrate=sac`` run of the preset plus the variant's flags, in
``<output_root>/<variant>_seed<seed>``. The runner is ``sr-grid``'s (:mod:`sr_imitation.experiments.grid`; this
module is its MT5 variant table, :data:`GRID`): it skips finished runs (``results.json`` and the same settings),
resumes killed ones and starts the others, one after another (``--runner=loop``, the default here) or as Ray tasks,
one per core (``--runner=ray``, ``--ray.*``; ``sr_mt8`` starts when its seed's ``sr`` run has finished)
(``--archive=docs/results/<folder>``: also skips the runs that folder holds with the same settings and copies each
run finished now into it, :mod:`sr_imitation.experiments.archive`), then writes the shared multi-run summary
(``summary.json`` / ``.md`` / ``.png``: AFSR, PRS, BWT against both references, SPI, mean +- SE over seeds, paired
differences to ``sr``) and ``memory.md`` (bytes each method's continual-learning mechanism stores at the end of the
stream, by memory kind, next to the paper's memory-budget table).

Variants (:data:`VARIANTS`): ``sr``; ``wake_only`` (the SR ablation: same wake, no sleep, no memory); ``sequential``
(plain SAC fine-tuning); the paper's baselines ``ewc``, ``agem``, ``der``, ``clear``, ``reset_distill``,
``progress_compress``, ``nash_mtl``, ``pcgrad``, ``componet``; the SR ablations ``sr_mean_grad`` (raw-gradient
mean), ``sr_no_anchor``, ``sr_no_exc``, ``sr_no_wake_exc``, ``sr_no_sleep_exc``; the streams ``sr_reverse`` (reverse
MT5) and ``sr_mt8`` (MT8 continued from the same seed's finished ``sr`` run, which must be listed before it); the
oracle ``mt_joint`` (:mod:`sr_imitation.substrates.sac.mt_joint`, reported apart). Baselines use the plain ReLU actor of
the paper's SAC substrate (excitability is part of Sleeping Robots: appendix A.1, "For Sleeping Robots, each hidden
neuron additionally carries the homeostatic excitability variable"); ``--excitability.enabled=false`` keeps every
gain at 1, which is that actor.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sr_imitation.experiments.archive import RunKey
from sr_imitation.experiments.grid import GridConfig, run_grid, run_name
from sr_imitation.experiments.grid import main as grid_main
from sr_imitation.infra.cli_errors import run_cli
from sr_imitation.reporting.summary import load_groups, write_summary
from sr_imitation.reporting.summary import summarize as summary_of
from sr_imitation.stream.config import check_choices
from sr_imitation.stream.rundir import RunDirectory

logger = logging.getLogger(__name__)
PROG = "python -m sr_imitation.experiments.mt5_compare"
"""The command as a user types it (usage errors and ``--help`` name it)."""

SLEEP_CANDIDATES: dict[str, list[str]] = {
    "control": [],
    "a1": ["--sleep.early_stop_tol=0"],
    "a2": ["--sleep.early_stop_scale=memory_scale"],
    "b1": ["--method_options={expert_memory: instead}"],
    "b2": ["--method_options={expert_memory: beside}"],
}
"""Issue 59's sleep candidates -> the ``sr-train`` flags each changes (the protocol's a1, a2, b1, b2; ``control``:
none): the ``sr_<name>`` variants below, and the re-sleeps of ``experiments/sleep_screening.py``."""
PLAIN_ACTOR = ["--excitability.enabled=false"]
VARIANTS: dict[str, list[str]] = {
    "sr": [],
    "wake_only": ["--sleep.enabled=false"],
    "sequential": ["--method=sequential_bc", *PLAIN_ACTOR],
    "ewc": ["--method=ewc", *PLAIN_ACTOR],
    "agem": ["--method=agem", *PLAIN_ACTOR],
    "der": ["--method=der", *PLAIN_ACTOR],
    "clear": ["--method=clear", *PLAIN_ACTOR],
    "reset_distill": ["--method=reset_distill", *PLAIN_ACTOR],
    "progress_compress": ["--method=progress_compress", *PLAIN_ACTOR],
    "nash_mtl": ["--method=nash_mtl", *PLAIN_ACTOR],
    "pcgrad": ["--method=pcgrad", *PLAIN_ACTOR],
    "componet": ["--method=componet"],  # its own plain-ReLU actor (sr_imitation.substrates.sac.composed_actor)
    "sr_mean_grad": ["--sleep.aggregator=mean_grad"],
    "sr_no_anchor": ["--sleep.anchor_strength=0"],
    "sr_no_exc": ["--excitability.enabled=false"],
    "sr_no_wake_exc": ["--excitability.wake_enabled=false"],
    "sr_no_sleep_exc": ["--excitability.sleep_enabled=false"],
    "sr_reverse": ["--stream.name=mt5-reverse"],
    "sr_mt8": ["--stream.name=mt8"],  # + --stream.extend_from=<the seed's sr run>
    "mt_joint": [],  # the oracle (substrates.sac.mt_joint): all skills at once, plain actor; reported apart
    # the candidate sleeps as whole runs (docs/RESULTS.md, "a SAC sleep that keeps what its wakes learn"):
    # sr_<candidate> with the screening's flags; c adds Reset & Distill's wake to the A-winner's setting (or to none)
    **{f"sr_{name}": flags for name, flags in SLEEP_CANDIDATES.items() if name != "control"},
    "sr_c": ["--method_options={reset_wake: true}"],
    "sr_c_a1": ["--method_options={reset_wake: true}", "--sleep.early_stop_tol=0"],
    "sr_c_a2": ["--method_options={reset_wake: true}", "--sleep.early_stop_scale=memory_scale"],
    "sr_c_b1": ["--method_options={reset_wake: true, expert_memory: instead}"],
    "sr_c_b2": ["--method_options={reset_wake: true, expert_memory: beside}"],
    # c_b1 with the plain actor in its wakes: Reset & Distill's wakes and expert memories bit for bit (SR's wake keeps
    # homeostatic excitability unless told otherwise), so only the consolidation differs (RESULTS' 2026-12-02 protocol)
    "sr_c_b1_pw": ["--method_options={reset_wake: true, expert_memory: instead}", "--excitability.wake_enabled=false"],
}
"""variant -> the flags it adds to the preset (``sr-train --substrate=sac``)."""

PAPER_MEMORY_MB = {"ewc": 3.0, "agem": 0.7, "der": 1.6, "clear": 2.5, "reset_distill": 2.2,
                   "progress_compress": 3.0, "nash_mtl": 3.7, "pcgrad": 3.7, "componet": 4.0, "sr": 3.7}
"""The paper's memory-budget table (MB at K = 5)."""

SECTIONS: dict[str, list[str]] = {
    "Continual baselines (the paper's Table 1, MT5 final performance)": [
        "wake_only", "sequential", "ewc", "agem", "der", "clear", "reset_distill", "progress_compress", "nash_mtl",
        "pcgrad", "componet"],
    "Ablations (the paper's MT5 ablation table)": [
        "wake_only", "sr_mean_grad", "sr_no_anchor", "sr_no_exc", "sr_no_wake_exc", "sr_no_sleep_exc"],
    "Order and length (the paper's order/length table; MT8's metrics are over its eight skills)": [
        "sr_reverse", "sr_mt8"],
    "The candidate SAC sleeps as whole runs (docs/RESULTS.md, their protocol), beside Reset & Distill": [
        "sr_a1", "sr_a2", "sr_b1", "sr_b2", "sr_c", "sr_c_a1", "sr_c_a2", "sr_c_b1", "sr_c_b2", "sr_c_b1_pw",
        "reset_distill"],
    "Oracle, reported apart (multi-task SAC on all skills at once; BWT 0 by definition)": ["mt_joint"],
}
"""The tables of ``summary.md`` (each with ``sr``'s row), as the paper groups them."""

PAIRED_BASELINE = "sr"


@dataclass
class MT5CompareConfig(GridConfig):
    """The MT5 comparison's command line: :class:`~sr_imitation.experiments.grid.GridConfig` with this module's
    defaults (and ``--runner=loop``)."""

    preset: Path = Path("configs/sac_mt5_cpu.json")
    """The SAC configuration every run starts from."""
    variants: list[str] = field(default_factory=lambda: ["sr", "wake_only"])
    """Variants to run (:data:`VARIANTS`), in this order."""
    seeds: list[int] = field(default_factory=lambda: [0, 1])
    """Training seeds."""
    output_root: Path = Path("outputs/mt5_compare")
    """Where the runs, the summary and the memory table go."""
    runner: str = "loop"
    """``loop``: one run after another in this process (as before sr-grid); ``ray``: every run a Ray task, as many at
    once as there are cores (``--ray.*``: :mod:`sr_imitation.experiments.grid`)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        GRID.validate(self.variants)


def run_args(cfg: GridConfig, variant: str, seed: int) -> list[str]:
    """The ``sr-train --substrate=sac`` arguments of one run."""
    out = cfg.output_root / run_name(variant, seed)
    args = [f"--config_path={cfg.preset}", f"--seed={seed}", f"--output_dir={out}", *VARIANTS[variant], *cfg.extra]
    if variant == "sr_mt8":
        args.append(f"--stream.extend_from={cfg.output_root / run_name('sr', seed)}")
    if RunDirectory.occupied(out):
        args.append("--resume=true")
    return args


class MT5Grid:
    """The MT5 comparison for the grid runner (:class:`~sr_imitation.experiments.grid.GridSubstrate`); Meta-World
    and the SAC substrate are imported on use."""

    variants = VARIANTS
    default_variants = ["sr", "wake_only"]
    default_seeds = [0, 1]

    def validate(self, variants: list[str]) -> None:
        check_choices("variants", variants, VARIANTS)
        if "sr_mt8" in variants and ("sr" not in variants or variants.index("sr") > variants.index("sr_mt8")):
            raise ValueError("variants: sr_mt8 continues the seed's sr run; list sr before it")

    def plan(self, cfg: GridConfig) -> dict[RunKey, Any]:
        from sr_imitation.substrates.sac.cli import parse

        return {(v, s): parse(run_args(cfg, v, s)) for v in cfg.variants for s in cfg.seeds}

    def fingerprint(self, variant: str, run: Any) -> Any:
        from sr_imitation.substrates.sac.mt_joint import joint_fingerprint

        return joint_fingerprint(run) if variant == "mt_joint" else run.resume_fingerprint()

    def check(self, plan: Mapping[RunKey, Any], archived: Mapping[RunKey, Path | None]) -> None:
        for (variant, seed), run in plan.items():
            source = run.stream.extend_from
            if variant == "sr_mt8" and archived[variant, seed] is None and archived[("sr", seed)] is not None \
                    and not (Path(source) / "stages").is_dir():
                raise FileNotFoundError(
                    f"{source}: sr_mt8 seed {seed} continues this sr run, which is only in the archive "
                    f"({archived[('sr', seed)]}, report files, no checkpoints); run sr seed {seed} into this "
                    "output_root first (without --archive), then sr_mt8")

    def after(self, variant: str, seed: int) -> RunKey | None:
        return ("sr", seed) if variant == "sr_mt8" else None

    def device(self, run: Any) -> str:
        return str(run.device)

    def run(self, variant: str, run: Any) -> object:
        from sr_imitation.substrates.sac import cli
        from sr_imitation.substrates.sac.mt_joint import run_mt_joint

        return (run_mt_joint if variant == "mt_joint" else cli.train)(run)

    def summarize(self, runs: dict[str, dict[str, Path]], output_root: Path) -> dict[str, Any]:
        return summarize(runs, output_root)


GRID = MT5Grid()


def run_compare(cfg: MT5CompareConfig) -> dict[str, Any]:
    return run_grid(cfg, GRID)


def summarize(runs: dict[str, dict[str, Path]], output_root: Path) -> dict[str, Any]:
    """The shared summary of ``{variant: {seed: run}}`` paired against ``sr``, and the memory table."""
    groups = load_groups(runs)
    summary = summary_of(groups, PAIRED_BASELINE if PAIRED_BASELINE in groups else next(iter(groups)))
    write_summary(output_root, summary, PAPER_MEMORY_MB, SECTIONS)
    return summary


def main(args: list[str] | None = None) -> None:
    grid_main(args, MT5CompareConfig, GRID, prog=PROG)


if __name__ == "__main__":
    run_cli(PROG, main)  # user errors: one line (--debug: the traceback)
