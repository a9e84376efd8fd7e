"""Every continual method on the needle stream, several training seeds, one table (the paper's Table 2).

    python -m sr_imitation.experiments.needle_compare --preset=configs/needle_cpu.json \\
        --seeds=[0,1,2,3,4] --variants=[sr,wake_only,sequential_bc,ewc_lam10000,lwf_w0.1,m2distill_w0.01,mt_joint] \\
        --output_root=outputs/needle_compare

Variants (:data:`VARIANTS`): ``sr``; ``wake_only`` (SR without sleep); the paper's baselines ``sequential_bc``,
``ewc``, ``lwf``, ``m2distill``, with grids over the weights the paper does not give for ACT (EWC's lambda: ``ewc`` =
1, ``ewc_lam100``, ``ewc_lam10000``, ``ewc_lam1000000``; the distillation weights: ``lwf`` = 1, ``lwf_w0.1``,
``lwf_w0.01``, ``m2distill`` = 1, ``m2distill_w0.1``, ``m2distill_w0.01``); ``replay``, LIBERO's experience replay
(:mod:`sr_imitation.stream.methods.replay`: behaviour cloning on ``--memory.buffer_size`` stored demonstration frames
per earlier skill, as many as SR's memories hold, mixed into every wake batch; no sleep); ``reset_distill``, Reset &
Distill on ACT (:mod:`sr_imitation.stream.methods.reset_distill`: a fresh ACT per skill, its action chunks on as many
frames as SR's memory holds distilled into the shared ACT after every skill, with the presets' sleep budget);
``sr_c``, SR with Reset & Distill's wake (``--method_options={reset_wake: true}``: every wake from a fresh ACT, every
sleep from the shared policy; the SAC protocol's variant c on ACT, whose memories already distill the wake-end
actor); the SR
ablations ``sr_no_anchor`` (anchor strength 0), ``sr_mean_grad`` (the paper's Mean-grad: raw-gradient mean),
``sr_mean_normalized`` (mean of normalized gradients), ``sr_nash_fw`` (the paper's warm-started Frank-Wolfe, 5
iterations) and ``sr_sleep_only`` (our ablation: no wake-time distillation, gamma_k = 0, so every wake is sequential
BC and only sleep consolidates); the oracle ``mt_joint`` (:mod:`sr_imitation.substrates.act.mt_joint`, one ACT on the
union of the five datasets, reported apart). Every (variant, seed) is an ordinary ``sr-train`` run of the preset
(plus ``--extra`` flags) in ``<output_root>/<variant>_seed<seed>`` on the same recorded datasets (recorded once,
as by ``sr-main``), each evaluated on the preset's evaluation seeds. The preset may also be an ``sr-train`` config
of your own skills (``--stream.dataset_paths`` or ``repo_ids``, your ``--eval.env``; :func:`base_config`): the same
grid then answers "does sleep help on my skills?" with ``--variants=[sr,wake_only]`` and
:mod:`sr_imitation.experiments.hypotheses` on ``output_root``. The runner is ``sr-grid``'s
(:mod:`sr_imitation.experiments.grid`; this module is its needle variant table, :data:`GRID`): it skips finished runs
(``results.json`` and the same settings), resumes killed ones and starts the others, one after another
(``--runner=loop``, the default here) or as Ray tasks, one per core (``--runner=ray``, ``--ray.*``).
``--archive=docs/results/<folder>`` (:mod:`sr_imitation.experiments.archive`) also skips the runs that folder holds
with the same settings and copies every run finished now into it, so a comparison spread over sessions keeps its raw
outputs in one place.

Written to ``output_root`` (:func:`sr_imitation.reporting.summary.write_summary`): ``summary.md`` / ``.json`` /
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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

from sr_imitation.experiments.archive import RunKey
from sr_imitation.experiments.grid import GridConfig, is_train_config, run_grid, run_name
from sr_imitation.experiments.grid import main as grid_main
from sr_imitation.infra.cli_errors import run_cli
from sr_imitation.infra.config_file import read_config_file
from sr_imitation.main_job import MainJobConfig, preset_with_datasets
from sr_imitation.reporting.summary import load_groups, write_summary
from sr_imitation.reporting.summary import summarize as summary_of
from sr_imitation.stream.config import check_choices
from sr_imitation.stream.rundir import RunDirectory
from sr_imitation.substrates.act.cli import parse_train_config
from sr_imitation.substrates.act.mt_joint import joint_fingerprint, run_mt_joint
from sr_imitation.substrates.act.trainer import TrainStreamConfig, resume_fingerprint, train_stream

logger = logging.getLogger(__name__)
PROG = "python -m sr_imitation.experiments.needle_compare"
"""The command as a user types it (usage errors and ``--help`` name it)."""

class Variant(NamedTuple):
    """What one variant changes in the preset: the continual method, sleep settings (``--sleep.*``), the method's own
    options (``--method_options``) and policy settings (``--policy.*``)."""

    method: str
    sleep: dict[str, Any]
    options: dict[str, float] = {}
    policy: dict[str, float] = {}


_OFF: dict[str, Any] = {"enabled": False}
VARIANTS: dict[str, Variant] = {
    "sr": Variant("sr", {"enabled": True}),
    "wake_only": Variant("sr", _OFF),
    "sequential_bc": Variant("sequential_bc", _OFF),
    "ewc": Variant("ewc", _OFF),
    "lwf": Variant("lwf", _OFF),
    "m2distill": Variant("m2distill", _OFF),
    "replay": Variant("replay", _OFF),  # LIBERO's ER: --memory.buffer_size demonstration frames per earlier skill
    # Reset & Distill on ACT: a fresh ACT per skill, its action chunks on --memory.buffer_size frames (SR's memory)
    # distilled into the shared ACT after every skill; the paper gives no ACT settings: our choice is the presets'
    # sleep budget (1000 steps, batch 32, lr 1e-5), so that it differs from SR in the method, not the optimizer's budget
    "reset_distill": Variant("reset_distill", {"enabled": True}, {"iterations": 1000, "batch_size": 32, "lr": 1e-5}),
    # the SAC protocol's variant c on ACT: Reset & Distill's wake (a fresh ACT per skill) with SR's sleep. ACT-SR's
    # memories are already the wake-end actor's outputs on stored frames (the paper's IL memory objective), which is
    # what the SAC option expert_memory: instead ("b1") adds there, so sr_c here is the SAC gate's sr_c_b1
    "sr_c": Variant("sr", {"enabled": True}, {"reset_wake": True}),
    "mt_joint": Variant("sequential_bc", _OFF),  # the oracle: run by substrates.act.mt_joint, not the stream
    # EWC's lambda grid on ACT (ewc above: lambda 1, the paper's MT5 choice); our grid, wider than the paper's MT5
    # {1, 100, 500}: the unit-Frobenius Fisher spreads over ACT's 678k deployed parameters, ~9x the SAC actor's
    "ewc_lam100": Variant("ewc", _OFF, {"lam": 100.0}),
    "ewc_lam10000": Variant("ewc", _OFF, {"lam": 10000.0}),
    "ewc_lam1000000": Variant("ewc", _OFF, {"lam": 1e6}),  # 10000 kept approach for three stages, lost it at the 5th
    # the grid goes on until success right after a skill's own wake drops, i.e. until the penalty binds (at 1e6
    # every skill was still learned right after its own wake and then forgotten; our choice of steps)
    "ewc_lam1e8": Variant("ewc", _OFF, {"lam": 1e8}),
    "ewc_lam1e10": Variant("ewc", _OFF, {"lam": 1e10}),
    # LwF's and M2Distill's distillation weights (the paper gives none; 1 is our default): at 1 LwF's teacher term on
    # the new skill's own observations outweighs the l1 behaviour cloning and the new skill is not learned
    # (seed 0: place 0.00 right after its wake), so the grid goes down
    "lwf_w0.1": Variant("lwf", _OFF, {"weight": 0.1}),
    "lwf_w0.01": Variant("lwf", _OFF, {"weight": 0.01}),
    "m2distill_w0.1": Variant("m2distill", _OFF, {"action_weight": 0.1, "feature_weight": 0.1}),
    "m2distill_w0.01": Variant("m2distill", _OFF, {"action_weight": 0.01, "feature_weight": 0.01}),
    "sr_no_anchor": Variant("sr", {"enabled": True, "anchor_strength": 0.0}),
    # our ablation: sleep without the wake-time distillation (gamma_k = 0), i.e. sequential BC followed by each
    # stage's sleep - can sleep alone repair forgetting?
    "sr_sleep_only": Variant("sr", {"enabled": True},
                             policy={"distill_weight_second": 0.0, "distill_weight_later": 0.0}),
    "sr_mean_grad": Variant("sr", {"enabled": True, "aggregator": "mean_grad"}),  # the paper's Mean-grad (raw)
    "sr_mean_normalized": Variant("sr", {"enabled": True, "aggregator": "mean_normalized"}),
    "sr_nash_fw": Variant("sr", {"enabled": True, "aggregator": "nash_fw"}),  # the paper's Frank-Wolfe, 5 iterations
}
PAIRED_BASELINE = "sr"
TABLE_2 = ["sr", "wake_only", "sequential_bc", "ewc_lam10000", "lwf_w0.1", "m2distill_w0.01", "mt_joint"]
"""The default variants: each baseline at the grid value that scored best on training seed 0 of the CPU preset
(final AFSR, ties broken by BWT; docs/RESULTS.md): EWC lambda 10000 (0.207; 1, 100 and 1e6: 0.200), LwF weight 0.1
(0.200, BWT -0.650; 0.01: -0.775; 1: AFSR 0.000), M2Distill weights 0.01 (0.200, BWT -0.842; 0.1: -0.992; 1: 0.020).
Our choice: the paper gives no weights for ACT."""


@dataclass
class CompareConfig(GridConfig):
    """The needle comparison's command line: :class:`~sr_imitation.experiments.grid.GridConfig` with this module's
    defaults (and ``--runner=loop``)."""

    preset: Path = Path("configs/needle_cpu.json")
    """The sr-main config every run starts from (its record section gives the datasets), or an ACT-SR sr-train
    config on your own datasets (:func:`base_config`)."""
    variants: list[str] = field(default_factory=lambda: list(TABLE_2))
    """Variants to run (:data:`VARIANTS`), in this order."""
    seeds: list[int] = field(default_factory=lambda: [0, 1, 2, 3, 4])
    """Training seeds."""
    output_root: Path = Path("outputs/needle_compare")
    """Where the runs and the tables go."""
    runner: str = "loop"
    """``loop``: one run after another in this process (as before sr-grid); ``ray``: every run a Ray task, as many at
    once as there are cores (``--ray.*``: :mod:`sr_imitation.experiments.grid`)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        GRID.validate(self.variants)


def base_config(preset: Path, flags: list[str]) -> TrainStreamConfig:
    """The ``sr-train`` config every run starts from: an ``sr-main`` preset's train section (its datasets recorded if
    missing, checked if present) or an ACT-SR ``sr-train`` config as ``sr-train --config_path`` reads it (your own
    datasets: each run checks them before its first gradient); ``flags`` (``--extra``) applied to it."""
    config = read_config_file(preset)
    if is_train_config(config.settings):
        return parse_train_config(config, list(flags))
    return preset_with_datasets(config, flags).train


def run_config(cfg: GridConfig, base: MainJobConfig | TrainStreamConfig, variant: str, seed: int) -> TrainStreamConfig:
    """The ``sr-train`` config of one run: the preset's (with ``extra``) plus the variant's method and sleep."""
    train = copy.deepcopy(base.train if isinstance(base, MainJobConfig) else base)
    spec = VARIANTS[variant]
    train.method = spec.method
    train.sleep = dataclasses.replace(train.sleep, **spec.sleep)
    train.method_options = {**train.method_options, **spec.options}
    if spec.policy:
        train.policy = dataclasses.replace(train.policy, **spec.policy)
    train.seed = seed
    train.output_dir = cfg.output_root / run_name(variant, seed)
    train.resume = RunDirectory.occupied(train.output_dir)
    train.overwrite = False  # a grid resumes or skips its runs, never restarts one (a user config may say otherwise)
    return train


class NeedleGrid:
    """The needle comparison for the grid runner (:class:`~sr_imitation.experiments.grid.GridSubstrate`)."""

    variants = VARIANTS
    default_variants = TABLE_2
    default_seeds = [0, 1, 2, 3, 4]

    def validate(self, variants: list[str]) -> None:
        check_choices("variants", variants, VARIANTS)

    def plan(self, cfg: GridConfig) -> dict[RunKey, TrainStreamConfig]:
        base = base_config(cfg.preset, cfg.extra)  # a preset's datasets recorded once, here, before any run starts
        return {(v, s): run_config(cfg, base, v, s) for v in cfg.variants for s in cfg.seeds}

    def fingerprint(self, variant: str, train: TrainStreamConfig) -> Any:
        return (joint_fingerprint if variant == "mt_joint" else resume_fingerprint)(train)

    def check(self, plan: Any, archived: Any) -> None:
        pass

    def after(self, variant: str, seed: int) -> RunKey | None:
        return None

    def device(self, train: TrainStreamConfig) -> str:
        return str(train.policy.device)

    def run(self, variant: str, train: TrainStreamConfig) -> object:
        return (run_mt_joint if variant == "mt_joint" else train_stream)(train)

    def summarize(self, runs: dict[str, dict[str, Path]], output_root: Path) -> dict[str, Any]:
        return summarize(runs, output_root)


GRID = NeedleGrid()


def run_compare(cfg: CompareConfig) -> dict:
    return run_grid(cfg, GRID)


def summarize(runs: dict[str, dict[str, Path]], output_root: Path) -> dict[str, Any]:
    """The shared multi-run summary (:mod:`sr_imitation.reporting.summary`) of ``{variant: {seed: run directory}}``,
    paired against ``sr`` (against the first variant without it); writes the tables and plots."""
    groups = load_groups(runs)
    summary = summary_of(groups, PAIRED_BASELINE if PAIRED_BASELINE in groups else next(iter(groups)))
    write_summary(output_root, summary)
    return summary


def main(args: list[str] | None = None) -> None:
    grid_main(args, CompareConfig, GRID, prog=PROG)


if __name__ == "__main__":
    run_cli(PROG, main)  # user errors: one line (--debug: the traceback)
