"""The README's main job: SR beside wake-only on one needle preset, both runs at once, then one figure and results.md.

    python -m sr_imitation.experiments.main_compare                      # configs/needle_cpu_m16.json
    python -m sr_imitation.experiments.main_compare --train.resume=true  # continue; a finished run is skipped

The preset's datasets are recorded once (skipped when they exist), then each variant (needle_compare's
:data:`~sr_imitation.experiments.needle_compare.VARIANTS`: ``sr`` and ``wake_only``, SR with ``--sleep.enabled=false``)
runs as an ordinary ``sr-train`` run in ``<output_dir>/<variant>_seed<train.seed>``, each in its own process with one
torch thread (sr-grid's ``processes`` runner), their logs in ``<output_dir>/logs/``. Then ``comparison.png`` (both
success matrices, both AFSR curves over stages) and ``results.md`` (both final AFSRs and their difference, whatever its
sign) go to ``output_dir``. Flags are sr-main's (``--record.*``, ``--train.*``, ``--config_path``) plus the fields of
:class:`MainCompareConfig`; ``bash .ci/main.sh --config_path=<preset>`` runs the single-run ``sr-main`` instead.
"""

from __future__ import annotations

import logging
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sr_imitation.experiments.grid import GridConfig, run_grid, run_name
from sr_imitation.experiments.needle_compare import VARIANTS, NeedleGrid, run_config
from sr_imitation.infra.cli_errors import run_cli, setup_logging, split_config_path
from sr_imitation.infra.folder_lock import hold_folder
from sr_imitation.main_job import MainJobConfig, write_expert_video
from sr_imitation.offscreen import setup_offscreen_rendering
from sr_imitation.recorders.needle import ensure_recorded
from sr_imitation.reporting.side_by_side import FIGURE, REPORT, difference_sentence, write_side_by_side
from sr_imitation.stream.config import check_choices
from sr_imitation.stream.rundir import RunDirectory
from sr_imitation.substrates.act.cli import parse_config
from sr_imitation.substrates.act.trainer import TrainStreamConfig

logger = logging.getLogger(__name__)

PROG = "python -m sr_imitation.experiments.main_compare"
"""The command as a user types it (usage errors and ``--help`` name it)."""
DEFAULT_PRESET = Path("configs/needle_cpu_m16.json")
"""The preset without ``--config_path``: the small-memory needle preset (16 memory frames a skill), where sleep has
something to consolidate."""
ONE_SEED_NOTE = (
    "One training seed is an illustration, not evidence: on the small-memory needle preset, differences of about "
    "+-0.05 between SR and wake-only from one training seed to the next are common, and they move with the CPU type "
    "(runs are bit-identical on one CPU type only), so this difference may have either sign. The evidence - ten "
    "training seeds and a paired test - is README's \"Which method where\" table and docs/RESULTS.md.")
"""What results.md says of the one seed it shows."""
ONE_SEED_CAPTION = ("One training seed: an illustration, not evidence (seed-to-seed differences of +-0.05 are common "
                    "here). The evidence: README's \"Which method where\" table, docs/RESULTS.md.")
"""What the figure says of the one seed it shows."""


@dataclass
class MainCompareConfig(MainJobConfig):
    """sr-main's settings (``--record.*``, ``--train.*``) and which two variants run side by side, where."""

    variants: list[str] = field(default_factory=lambda: ["sr", "wake_only"])
    """The two variants (needle_compare's VARIANTS); the difference reported is the first's final AFSR minus the
    second's."""
    output_dir: Path = Path("outputs/needle_main")
    """The job's folder: each run in <output_dir>/<variant>_seed<train.seed>, their logs in logs/, comparison.png and
    results.md here (train.output_dir is not used)."""
    processes: int | None = None
    """Runs at once, each a process with one torch thread (None: one per core, at most one per run)."""
    expert_video: bool = True
    """Also write a full-suture video of the scripted expert (expert_suture.mp4) to output_dir."""

    def __post_init__(self) -> None:
        super().__post_init__()
        check_choices("variants", self.variants, VARIANTS)
        if len(self.variants) != 2 or self.variants[0] == self.variants[1]:
            raise ValueError(f"variants: give two different ones (e.g. [sr,wake_only]), got {self.variants}")
        if "mt_joint" in self.variants:
            raise ValueError("variants: mt_joint learns every skill at once: it has no stages to compare")
        if self.processes is not None and self.processes < 1:
            raise ValueError(f"processes: must be >= 1, got {self.processes}")


class MainCompareGrid(NeedleGrid):
    """The needle grid of one parsed job (its record and train flags applied), summarized side by side."""

    def __init__(self, job: MainCompareConfig | None = None) -> None:
        self.job = job

    def plan(self, cfg: GridConfig) -> dict[tuple[str, int], TrainStreamConfig]:
        """Record the job's datasets if missing (once, before any run starts), then each variant's run config."""
        assert self.job is not None  # the driver's grid has its job; a run's process only calls run()
        ensure_recorded(self.job.record)
        return {(v, s): run_config(cfg, self.job, v, s) for v in cfg.variants for s in cfg.seeds}

    def summarize(self, runs: dict[str, dict[str, Path]], output_root: Path) -> dict[str, Any]:
        """``comparison.png`` and ``results.md`` of the two runs."""
        assert self.job is not None
        job = self.job
        pair = {v: runs[v][str(job.train.seed)] for v in job.variants}
        title = f"{' beside '.join(job.variants)}, needle stream, training seed {job.train.seed}"
        return write_side_by_side(output_root, pair, title, _context(job), [ONE_SEED_NOTE], ONE_SEED_CAPTION)


GRID = MainCompareGrid()
"""What a run's process imports (sr-grid's ``processes`` runner): it only runs a planned run, with no job."""


def _context(job: MainCompareConfig) -> str:
    """results.md's first paragraph: the stream, the memory, the evaluation and what each variant is."""
    ev = job.train.eval
    return (f"Stream {', '.join(job.train.stream.skills)}; {job.train.memory.buffer_size} memory frames a skill; "
            f"training seed {job.train.seed}; every success is over {len(ev.seeds)} evaluation seed(s) x "
            f"{ev.episodes} episode(s). Variants: " + "; ".join(_describe(v) for v in job.variants) + ".")


def _describe(variant: str) -> str:
    """``wake_only = method sr, sleep off``: what a variant runs."""
    spec = VARIANTS[variant]
    return f"{variant} = method {spec.method}, sleep {'on' if spec.sleep.get('enabled') else 'off'}"


def run_dirs(job: MainCompareConfig) -> dict[str, Path]:
    """Each variant's run folder.

    Args:
        job: the parsed job.

    Returns:
        variant -> ``<output_dir>/<variant>_seed<train.seed>``.
    """
    return {v: Path(job.output_dir) / run_name(v, job.train.seed) for v in job.variants}


def _check_resume(job: MainCompareConfig) -> None:
    """Refuse, in one line, a job whose run folders exist unless ``--train.resume=true`` (never overwritten)."""
    if job.train.overwrite:
        raise ValueError(f"train.overwrite: this job never overwrites its runs; remove {job.output_dir} to start "
                         "again, or give another --output_dir")
    occupied = [str(d) for d in run_dirs(job).values() if RunDirectory.occupied(d)]
    if occupied and not job.train.resume:
        raise FileExistsError(f"{', '.join(occupied)}: a run is already there; --train.resume=true continues this "
                              "comparison (a finished run is skipped), or give another --output_dir")


def run_main_compare(job: MainCompareConfig, preset: Path) -> dict[str, Any]:
    """Record what is missing, run (or resume) both variants at once, write the figure and results.md, as the only
    writer of ``job.output_dir`` (its lock held throughout; each run's folder locked by its process).

    Args:
        job: the parsed job.
        preset: the config file it came from (named in the grid's settings).

    Returns:
        :func:`~sr_imitation.reporting.side_by_side.side_by_side`'s result.
    """
    with hold_folder(job.output_dir, PROG):
        _check_resume(job)
        processes = job.processes or max(1, min(len(job.variants), os.cpu_count() or 1))
        grid = GridConfig(preset=preset, variants=list(job.variants), seeds=[job.train.seed],
                          output_root=Path(job.output_dir), runner="processes", processes=processes)
        summary = run_grid(grid, MainCompareGrid(job))
        if job.expert_video:
            write_expert_video(job, Path(job.output_dir))
        return summary


def main(args: list[str] | None = None) -> None:
    """Parse the command line (``--config_path`` defaults to :data:`DEFAULT_PRESET`), run the job, print where the
    figure and the tables are and the difference."""
    setup_offscreen_rendering()
    setup_logging()
    config_path, rest = split_config_path(list(sys.argv[1:] if args is None else args))
    preset = Path(config_path) if config_path else DEFAULT_PRESET
    job = parse_config(MainCompareConfig, str(preset), rest, prog=PROG)
    summary = run_main_compare(job, preset)
    out = Path(job.output_dir)
    print(f"datasets: {job.record.root.resolve()}")  # noqa: T201
    for name in summary["names"]:
        print(f"{name}: {Path(summary['runs'][name]['dir']).resolve()}")  # noqa: T201
    print(f"figure:   {(out / FIGURE).resolve()}\nresults:  {(out / REPORT).resolve()}")  # noqa: T201
    print(difference_sentence(summary) + " One seed: an illustration, not evidence (see results.md).")  # noqa: T201


if __name__ == "__main__":
    run_cli(PROG, main)  # user errors: one line (--debug: the traceback)
