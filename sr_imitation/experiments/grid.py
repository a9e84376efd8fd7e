"""``sr-grid``: a grid of runs (variants x training seeds) of one preset, on Ray (local cores or a cluster) or in a
plain loop.

    sr-grid --preset=configs/needle_cpu_m16.json --variants=[sr,wake_only,sequential_bc] --seeds=[0,1,2] \\
        --output_root=outputs/needle_grid --archive=docs/results/needle_cpu_m16_compare
    sr-grid --preset=configs/sac_mt5_cpu.json --variants=[sr,wake_only] --seeds=[0,1] --ray.address=auto

The substrate follows from the preset: an ``sr-main`` preset (``record`` + ``train`` sections) or an ``sr-train``
config of ACT-SR (e.g. a stream on your own datasets, ``--stream.dataset_paths`` / ``repo_ids`` with your
``--eval.env``, or a run's ``train_config.json``) is the imitation comparison
(:mod:`sr_imitation.experiments.needle_compare`: its variants, its summary), a SAC config (``"substrate": "sac"``)
the Meta-World one (:mod:`sr_imitation.experiments.mt5_compare`). The driver (this process)

1. builds every run's config; an sr-main preset's datasets are recorded here, once, before anything fans out (an
   sr-train config's datasets are the user's: each run checks them before its first gradient);
2. skips every run that is finished with the settings it would have (its checked settings fingerprint,
   :func:`~sr_imitation.experiments.archive.archived_run`), in ``--archive`` or in ``--output_root``, all checked
   before the first run is submitted (another value of a setting refuses the whole grid in one line);
3. runs the others (``--runner``): ``ray`` submits each as one Ray task (``--ray.num_cpus`` / ``num_gpus`` /
   ``memory_gb`` each; torch threads and ``OMP_NUM_THREADS``: the run's ``torch_threads``, else its cores; a fresh
   worker process per run) that runs or resumes the run in its own ``<output_root>/<variant>_seed<seed>``; a task
   whose worker dies is retried (``--ray.max_retries``) and the retry resumes the run from its last recorded phase
   (``progress.json``), which reaches the numbers of an uninterrupted run (tested). ``processes`` runs each in a
   fresh process of this machine (one torch thread each unless the run's ``torch_threads`` says; ``--processes`` of
   them at once, default one per core; logs as with Ray); a process that dies fails its run only, and the grid run
   again resumes it. ``loop`` runs them here, one after another. A run that depends on another (``sr_mt8``
   continues the seed's ``sr`` run) starts when that one has finished. A run that raises an error stops the loop;
   with Ray or processes the other runs go on, and the failed ones (with the runs waiting for them) are named in one
   error at the end, the summary then left unwritten;
4. copies every run into ``--archive`` as it finishes and logs one line per finished run (variant, seed, final
   AFSR, wall time); Ray's dashboard shows the tasks where ``ray[default]`` is installed (not pinned here);
5. writes the summary once, at the end (``--summary_only=true``: only the summary, of the finished runs found).

Locally (no ``--ray.address``) Ray starts on this machine's cores and stops at the end; on a cluster started with
``ray start --head`` (and ``ray start --address=<head>:6379`` on the other nodes), ``--ray.address=auto`` on one of
its nodes submits there (``--ray.address=ray://<head>:10001`` from outside the cluster needs Ray's client,
``ray[client]``, not pinned here). Every node needs this environment and must see
``output_root``, ``archive`` and the datasets at the same paths (a shared filesystem): runs write there and the
driver archives and summarizes from there. A run's log goes to ``<output_root>/logs/<variant>_seed<seed>.log``
(``--ray.log_to_driver=true``: also to this console).
"""

from __future__ import annotations

import importlib
import json
import logging
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from sr_imitation.experiments.archive import RunKey, archive_run, check_archive
from sr_imitation.experiments.grid_run import KILL_HOOK_ENV as KILL_HOOK_ENV
from sr_imitation.experiments.grid_run import completed_phases as completed_phases
from sr_imitation.experiments.grid_run import run_name
from sr_imitation.experiments.grid_run import run_one as run_one
from sr_imitation.experiments.grid_runners import LOCAL_RAY_SYSTEM_CONFIG as LOCAL_RAY_SYSTEM_CONFIG
from sr_imitation.experiments.grid_runners import RUNNERS, RayOptions
from sr_imitation.infra.cli_errors import run_cli, setup_logging
from sr_imitation.infra.cli_parsing import parse_command
from sr_imitation.infra.config_file import read_config_file
from sr_imitation.io import CorruptFileError
from sr_imitation.offscreen import setup_offscreen_rendering
from sr_imitation.progress import format_duration
from sr_imitation.reporting.results import final_headline

logger = logging.getLogger(__name__)

SUBSTRATES: dict[str, str] = {
    "act": "sr_imitation.experiments.needle_compare",
    "sac": "sr_imitation.experiments.mt5_compare",
}
"""Substrate -> the module whose ``GRID`` (a :class:`GridSubstrate`) builds, runs and summarizes its runs; imported
on use, so a needle grid never imports Meta-World and a SAC grid never imports the needle environment."""

class GridSubstrate(Protocol):
    """What a substrate's comparison module gives the grid runner (``GRID`` in the modules of :data:`SUBSTRATES`)."""

    variants: Mapping[str, object]
    """variant -> what it changes (the module's ``VARIANTS`` table)."""
    default_variants: list[str]
    default_seeds: list[int]

    def validate(self, variants: list[str]) -> None:
        """``ValueError`` naming an unknown variant or an impossible order."""

    def plan(self, cfg: GridConfig) -> dict[RunKey, Any]:
        """Every run's config (with its ``output_dir``), in order; records missing input data (the driver's job)."""

    def fingerprint(self, variant: str, run: Any) -> Any:
        """The run's settings fingerprint (what its ``settings_fingerprint.json`` must hold)."""

    def check(self, plan: Mapping[RunKey, Any], archived: Mapping[RunKey, Path | None]) -> None:
        """Refuse a plan that cannot run (before anything is submitted)."""

    def after(self, variant: str, seed: int) -> RunKey | None:
        """The run that must finish before this one starts (``None``: none)."""

    def device(self, run: Any) -> str:
        """The torch device the run trains on (``cuda...`` asks Ray for a GPU unless ``--ray.num_gpus`` says)."""

    def run(self, variant: str, run: Any) -> object:
        """Run or resume one run (``run.resume`` set by the grid runner)."""

    def summarize(self, runs: dict[str, dict[str, Path]], output_root: Path) -> dict[str, Any]:
        """Write the summary of ``{variant: {seed: run directory}}`` into ``output_root``; return it."""


@dataclass
class GridConfig:
    preset: Path = Path("configs/needle_cpu.json")
    """The config every run starts from: an sr-main preset (needle, ACT), an ACT-SR sr-train config (your own
    datasets and evaluation environment) or a SAC config (``"substrate": "sac"``)."""
    variants: list[str] = field(default_factory=list)
    """Variants to run, in this order (the substrate's ``VARIANTS``); empty - its default list."""
    seeds: list[int] = field(default_factory=list)
    """Training seeds (empty - the substrate's default list)."""
    output_root: Path = Path("outputs/grid")
    """Where the runs (``<variant>_seed<seed>``), their logs and the summary go."""
    extra: list[str] = field(default_factory=list)
    """Training flags added to every run (e.g. ``--eval.episodes=20``)."""
    archive: Path | None = None
    """A folder of finished runs' raw outputs (:mod:`sr_imitation.experiments.archive`): runs it holds with the same
    settings are skipped and summarized from there, runs finished now are copied into it. ``None``: only
    ``output_root``."""
    keep_weights: bool = True
    """With ``archive``: also keep each archived run's checkpoints and memories in the git-ignored
    ``<archive>.weights/<run>/``, their checksums in the archived ``weights.json`` (what a re-sleep of a stored stage
    reads: :mod:`sr_imitation.substrates.sac.resleep`, ``sr-sleep``)."""
    runner: str = "ray"
    """``ray``: every run a Ray task, as many at once as the cluster's resources allow; ``processes``: every run a
    process of this machine, ``processes`` at once, one torch thread each (no Ray); ``loop``: one after another in
    this process."""
    processes: int | None = None
    """With ``--runner=processes``: how many runs at once (``None``: one per core of this machine)."""
    summary_only: bool = False
    """Run nothing, only write the summary of the planned runs found finished (archive first, then
    ``output_root``; not checked against the settings)."""
    ray: RayOptions = field(default_factory=RayOptions)
    """Ray's address and each run's resources."""

    def __post_init__(self) -> None:
        if self.runner not in RUNNERS:
            raise ValueError(f"runner: unknown {self.runner!r}; choose from {list(RUNNERS)}")
        if self.processes is not None and self.processes < 1:
            raise ValueError(f"processes: must be >= 1, got {self.processes}")


def is_train_config(data: object) -> bool:
    """Whether a config file's JSON is an ACT-SR ``sr-train`` config (``"substrate": "act"``, or ``policy`` and
    ``stream`` sections without a ``record`` one): a stream on datasets that already exist, the user's own."""
    if not isinstance(data, dict) or "record" in data or data.get("substrate", "act") != "act":
        return False
    return data.get("substrate") == "act" or (isinstance(data.get("policy"), dict) and isinstance(data.get("stream"),
                                                                                                  dict))


def substrate_of_preset(preset: Path) -> str:
    """``sac`` for a SAC config (its ``substrate`` key), ``act`` for an sr-main preset (``record`` and ``train``) or an
    ACT-SR sr-train config (:func:`is_train_config`); ``ValueError`` naming the file otherwise."""
    try:
        config = read_config_file(preset)  # a JSON object, or one line naming the file
    except (OSError, ValueError, CorruptFileError) as exc:
        raise ValueError(f"preset: {exc}") from None
    if config.settings.get("substrate") == "sac":
        return "sac"
    if (config.is_main_job_preset and isinstance(config.settings["train"], dict)) or is_train_config(config.settings):
        return "act"
    raise ValueError(f"preset: {preset} is neither an sr-main preset (record and train sections: the needle grid), "
                     "an ACT-SR sr-train config (policy and stream sections: your datasets) nor a SAC config "
                     "(\"substrate\": \"sac\": the Meta-World grid)")


def grid_substrate(name: str) -> GridSubstrate:
    return importlib.import_module(SUBSTRATES[name]).GRID


# -- the grid --------------------------------------------------------------------------------------------------
def _final_metric(run_dir: Path) -> str:
    """The run's :func:`~sr_imitation.reporting.results.final_headline`; ``AFSR -`` if its results are unreadable."""
    try:
        return final_headline(json.loads((Path(run_dir) / "results.json").read_text()))
    except (OSError, ValueError, AttributeError, TypeError):
        return "AFSR -"


def _finished_line(key: RunKey, info: dict[str, Any], count: int, total: int, elapsed: float | None = None) -> str:
    """One finished run: its final metric, wall time, resumed phases, and (``elapsed``: seconds since the grid
    started) the time the rest of the grid will take at the pace so far."""
    variant, seed = key
    n = len(info["resumed_phases"])
    resumed = f", resumed with {n} phase{'s' * (n != 1)} done" if n else ""
    left = f"; the other {total - count} at this pace: ~{format_duration(elapsed / count * (total - count))}" \
        if elapsed is not None and 0 < count < total else ""
    return (f"finished {variant} seed {seed}: {_final_metric(info['run_dir'])}, "
            f"{info['wall_s']:.1f} s{resumed} ({count}/{total}{left})")


def find_finished(cfg: GridConfig, substrate: GridSubstrate) -> dict[str, dict[str, Path]]:
    """``--summary_only``: every planned run found finished (the archive's copy first, then ``output_root``'s),
    unchecked; the missing ones are named in a warning."""
    runs: dict[str, dict[str, Path]] = {}
    missing = []
    for variant in cfg.variants:
        for seed in cfg.seeds:
            name = run_name(variant, seed)
            places = [p / name for p in (cfg.archive, cfg.output_root) if p is not None]
            found = next((p for p in places if (p / "results.json").is_file()), None)
            if found is None:
                missing.append(name)
            else:
                runs.setdefault(variant, {})[str(seed)] = found
    if missing:
        logger.warning("summary without %s (not finished)", ", ".join(missing))
    if not runs:
        raise FileNotFoundError(f"no finished run of the grid in {cfg.archive or ''} {cfg.output_root}")
    return runs


def run_grid(cfg: GridConfig, substrate: GridSubstrate | None = None) -> dict[str, Any]:
    """Run the grid ``cfg`` describes (see the module docstring); returns the summary."""
    substrate = substrate or grid_substrate(substrate_of_preset(cfg.preset))
    cfg.variants = list(cfg.variants or substrate.default_variants)
    cfg.seeds = list(cfg.seeds if cfg.seeds else substrate.default_seeds)
    substrate.validate(cfg.variants)
    if cfg.summary_only:
        return substrate.summarize(find_finished(cfg, substrate), cfg.output_root)
    plan = substrate.plan(cfg)
    _pin_threads(plan, cfg)
    # every skip decided, and every differing setting refused, before the first run starts
    archived = check_archive(plan, cfg.archive, substrate.fingerprint)
    finished = check_archive({k: run for k, run in plan.items() if archived[k] is None}, cfg.output_root,
                             substrate.fingerprint)  # finished earlier in output_root, with the same settings
    substrate.check(plan, archived)
    todo = [key for key in plan if archived[key] is None and finished[key] is None]
    logger.info("grid of %d runs: %d in the archive, %d finished in %s, %d to run (runner: %s)", len(plan),
                sum(v is not None for v in archived.values()), sum(v is not None for v in finished.values()),
                cfg.output_root, len(todo), cfg.runner)
    done: list[RunKey] = []
    start = time.monotonic()

    def on_finished(key: RunKey, info: dict[str, Any]) -> None:
        out = Path(plan[key].output_dir)
        if cfg.archive is not None:
            archive_run(out, cfg.archive, out.name, cfg.keep_weights)
        done.append(key)
        logger.info(_finished_line(key, {**info, "run_dir": out}, len(done), len(todo), time.monotonic() - start))

    if todo:
        RUNNERS[cfg.runner](cfg, substrate, plan, todo, on_finished)
    runs: dict[str, dict[str, Path]] = {}
    for key, run in plan.items():
        out = Path(run.output_dir)
        kept = archived[key]
        if kept is None and cfg.archive is not None:  # finished now (archived above) or earlier here (now)
            kept = cfg.archive / out.name if key in done else archive_run(out, cfg.archive, out.name, cfg.keep_weights)
        runs.setdefault(key[0], {})[str(key[1])] = kept or out
    return substrate.summarize(runs, cfg.output_root)


def _pin_threads(plan: Mapping[RunKey, Any], cfg: GridConfig) -> None:
    """A run that leaves its torch threads to the process (``torch_threads`` null) gets the number it will run with
    (a Ray task: its cores; a process of ``--runner=processes``: one; the loop: this process's), so that the
    driver's fingerprints, the archive check and the run itself agree: results are reproducible at a fixed thread
    count only, and the count is fingerprinted."""
    import torch

    threads = {"ray": max(1, int(cfg.ray.num_cpus)), "processes": 1}.get(cfg.runner) or torch.get_num_threads()
    for run in plan.values():
        if getattr(run, "torch_threads", 0) is None:
            run.torch_threads = threads


def main(args: list[str] | None = None, config_class: type[GridConfig] = GridConfig,
         substrate: GridSubstrate | None = None, prog: str = "sr-grid") -> None:
    """Parse ``args`` into ``config_class`` (the comparison modules pass theirs, with their defaults, and their
    command's name ``prog`` for usage errors and ``--help``), run the grid, print the final means and where the tables
    are."""
    from sr_imitation.reporting.summary import print_final_means

    setup_offscreen_rendering()
    setup_logging()
    cfg = parse_command(config_class, args, prog=prog)
    summary = run_grid(cfg, substrate)
    print_final_means(summary, [cfg.output_root / "summary.md", cfg.output_root / "memory.md"])


def entry() -> None:
    """Console script ``sr-grid``: :func:`main` with one-line user errors (``--debug`` for tracebacks)."""
    run_cli("sr-grid", main)


if __name__ == "__main__":
    entry()
