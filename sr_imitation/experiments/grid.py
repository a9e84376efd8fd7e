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

import copy
import importlib
import json
import logging
import os
import sys
import threading
import time
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple, Protocol

from sr_imitation.experiments.archive import RunKey, archive_run, check_archive
from sr_imitation.infra.cli_errors import run_cli, setup_logging
from sr_imitation.infra.cli_parsing import parse_command
from sr_imitation.infra.folder_lock import hold_folder
from sr_imitation.offscreen import setup_offscreen_rendering
from sr_imitation.progress import PROGRESS_ENV, format_duration
from sr_imitation.reporting.results import final_headline
from sr_imitation.stream.rundir import PROGRESS_FILE, RunDirectory

logger = logging.getLogger(__name__)

SUBSTRATES: dict[str, str] = {
    "act": "sr_imitation.experiments.needle_compare",
    "sac": "sr_imitation.experiments.mt5_compare",
}
"""Substrate -> the module whose ``GRID`` (a :class:`GridSubstrate`) builds, runs and summarizes its runs; imported
on use, so a needle grid never imports Meta-World and a SAC grid never imports the needle environment."""

RUNNERS = ("loop", "ray", "processes")

KILL_HOOK_ENV = "SR_GRID_TEST_KILL"
"""Test hook (fault injection): ``<run name>:<phase key>:<marker file>`` makes the Ray task of that run kill its
own worker process (``os._exit(1)``) once ``progress.json`` records the phase (e.g. ``sr_seed0:1.wake``), unless
the marker file exists; the marker is written first, so only the first attempt dies."""


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


LOCAL_RAY_SYSTEM_CONFIG: dict[str, int] = {"health_check_period_ms": 3000, "health_check_failure_threshold": 100}
"""Ray's settings for the local Ray this runner starts (our choice). By default Ray's head marks a node dead after
5 missed health checks 3 s apart; on a 2-core machine whose cores the runs (and any other work) hold, the raylet
can answer late for that long, and every run on it then fails with "The task's local raylet died" (measured: CI,
2026-11-28, two pytest workers beside a Ray run). Here the head waits 100 missed checks (5 minutes). The cost: a
local raylet that truly crashed may be declared dead up to 5 minutes later (not measured)."""


@dataclass
class RayOptions:
    """Where the runs go and what each one asks for (``--ray.*``)."""

    address: str | None = None
    """A running Ray cluster: ``auto`` (on one of its nodes) or ``ray://<head>:10001`` (Ray's client:
    ``ray[client]``). ``None``: start Ray on this machine (``local_cpus`` cores) and stop it at the end."""
    local_cpus: int | None = None
    """Cores of the local Ray (``None`` - all of this machine's); ignored with ``address``."""
    num_cpus: float = 1.0
    """Cores per run (Ray resource ``num_cpus``); a run's torch threads and ``OMP_NUM_THREADS`` are this (at least 1)
    unless its ``torch_threads`` is set."""
    num_gpus: float | None = None
    """GPUs per run (``None`` - 1 when the preset trains on ``cuda``, else 0)."""
    memory_gb: float | None = None
    """Memory per run in GiB (Ray resource ``memory``); ``None`` - not reserved."""
    max_retries: int = 3
    """Times a run whose worker process died (killed, out of memory, node lost) is retried; each retry resumes it.
    A run that raises an error is not retried."""
    log_to_driver: bool = False
    """Also print every run's log lines on this console (they always go to ``<output_root>/logs/``)."""


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


def run_name(variant: str, seed: int) -> str:
    """A run's directory name under ``output_root`` and in the archive."""
    return f"{variant}_seed{seed}"


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
        data = json.loads(Path(preset).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"preset: cannot read {preset} ({exc})") from None
    if isinstance(data, dict) and data.get("substrate") == "sac":
        return "sac"
    if isinstance(data, dict) and isinstance(data.get("train"), dict) and "record" in data:
        return "act"
    if is_train_config(data):
        return "act"
    raise ValueError(f"preset: {preset} is neither an sr-main preset (record and train sections: the needle grid), "
                     "an ACT-SR sr-train config (policy and stream sections: your datasets) nor a SAC config "
                     "(\"substrate\": \"sac\": the Meta-World grid)")


def grid_substrate(name: str) -> GridSubstrate:
    return importlib.import_module(SUBSTRATES[name]).GRID


# -- one run ---------------------------------------------------------------------------------------------------
def completed_phases(out: Path) -> list[str]:
    """The phases ``out/progress.json`` records as done (empty for a new run)."""
    try:
        return list(json.loads((Path(out) / PROGRESS_FILE).read_text()).get("completed", {}))
    except (OSError, ValueError, AttributeError):
        return []


def run_one(substrate: GridSubstrate, variant: str, run: Any) -> dict[str, Any]:
    """Run or resume one run as the only writer of its directory (its lock, taken before the directory is looked at
    and held to the end): ``resume`` is decided now (a retried task finds its killed attempt's directory and
    continues it); returns the wall time and the phases that were already done."""
    run = copy.copy(run)
    with hold_folder(run.output_dir, "sr-grid"):
        run.resume = RunDirectory.occupied(run.output_dir)
        done = completed_phases(run.output_dir)
        start = time.perf_counter()
        substrate.run(variant, run)
        return {"wall_s": time.perf_counter() - start, "resumed_phases": done}


def _arm_kill_hook(out: Path) -> None:
    """:data:`KILL_HOOK_ENV` (tests only)."""
    spec = os.environ.get(KILL_HOOK_ENV)
    if not spec:
        return
    name, phase, marker = spec.split(":", 2)
    if Path(out).name != name or Path(marker).exists():
        return

    def watch() -> None:
        while phase not in completed_phases(out):
            time.sleep(0.01)
        Path(marker).write_text(str(os.getpid()))
        os._exit(1)

    threading.Thread(target=watch, daemon=True).start()


def _task(module: str, variant: str, run: Any, log_file: str, threads: int) -> dict[str, Any]:
    """The body of one run's Ray task (a fresh worker process): threads, offscreen rendering, a log file, the run."""
    setup_offscreen_rendering()
    import torch

    torch.set_num_threads(threads)
    handler = logging.FileHandler(log_file)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    logging.getLogger().addHandler(handler)
    logging.getLogger().setLevel(logging.INFO)
    _arm_kill_hook(run.output_dir)
    try:
        info = run_one(importlib.import_module(module).GRID, variant, run)
    except BaseException:
        logger.exception("%s failed", run.output_dir)  # the whole traceback in the run's log
        raise
    return {**info, "node": os.uname().nodename, "pid": os.getpid()}


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
        runner = {"ray": _run_ray, "processes": _run_processes, "loop": _run_loop}[cfg.runner]
        runner(cfg, substrate, plan, todo, on_finished)
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


def _run_loop(cfg: GridConfig, substrate: GridSubstrate, plan: Mapping[RunKey, Any], todo: list[RunKey],
              on_finished: Callable[[RunKey, dict[str, Any]], None]) -> None:
    for key in todo:
        logger.info("=== %s seed %d -> %s", key[0], key[1], plan[key].output_dir)
        on_finished(key, run_one(substrate, key[0], plan[key]))


def _threads(run: Any, opts: RayOptions) -> int:
    """A run's torch threads: its ``torch_threads`` (pinned by :func:`_pin_threads`), else its cores."""
    return int(getattr(run, "torch_threads", None) or max(1, int(opts.num_cpus)))


def _resources(opts: RayOptions, substrate: GridSubstrate, run: Any) -> dict[str, Any]:
    gpus = opts.num_gpus if opts.num_gpus is not None else float(substrate.device(run).startswith("cuda"))
    env = {"OMP_NUM_THREADS": str(_threads(run, opts))}
    env.update({k: os.environ[k] for k in ("MUJOCO_GL", "PYOPENGL_PLATFORM", KILL_HOOK_ENV) if k in os.environ})
    out: dict[str, Any] = {"num_cpus": opts.num_cpus, "num_gpus": gpus, "max_retries": opts.max_retries,
                           "runtime_env": {"env_vars": env}}
    if opts.memory_gb is not None:
        out["memory"] = int(opts.memory_gb * 2**30)
    return out


def _run_ray(cfg: GridConfig, substrate: GridSubstrate, plan: Mapping[RunKey, Any], todo: list[RunKey],
             on_finished: Callable[[RunKey, dict[str, Any]], None]) -> None:
    import ray

    opts = cfg.ray
    started = not ray.is_initialized()
    if started:
        with warnings.catch_warnings():  # Ray 2.52's notice of a future default: runs without GPUs keep seeing none
            warnings.filterwarnings("ignore", message=".*RAY_ACCEL_ENV_VAR_OVERRIDE_ON_ZERO", category=FutureWarning)
            local = opts.address is None
            ray.init(address=opts.address, num_cpus=opts.local_cpus if local else None,
                     log_to_driver=opts.log_to_driver, _system_config=LOCAL_RAY_SYSTEM_CONFIG if local else None)
    try:
        res = ray.cluster_resources()
        logger.info("Ray: %g CPUs, %g GPUs, %.1f GiB memory", res.get("CPU", 0), res.get("GPU", 0),
                    res.get("memory", 0) / 2**30)
        task = ray.remote(max_calls=1)(_task)  # a fresh worker process per run
        logs = Path(cfg.output_root) / "logs"
        logs.mkdir(parents=True, exist_ok=True)
        module = type(substrate).__module__  # its GRID, imported by the worker
        waiting = {key: substrate.after(*key) for key in todo}  # held back until the run they continue finished
        pending: dict[Any, RunKey] = {}
        failed: dict[RunKey, str] = {}

        def submit(key: RunKey) -> None:
            variant, seed = key
            run = plan[key]
            ref = task.options(name=run_name(variant, seed), **_resources(opts, substrate, run)).remote(
                module, variant, run, str(logs / f"{run_name(variant, seed)}.log"), _threads(run, opts))
            logger.info("submitted %s seed %d -> %s", variant, seed, run.output_dir)
            pending[ref] = key

        def release(finished_key: RunKey, ok: bool) -> None:
            for key, dep in list(waiting.items()):
                if dep == finished_key:
                    del waiting[key]
                    if ok:
                        submit(key)
                    else:
                        failed[key] = f"not started: {run_name(*dep)} failed"
                        release(key, False)

        for key in todo:
            if waiting[key] not in todo:
                del waiting[key]
                submit(key)
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            key = pending.pop(ready[0])
            try:
                info = ray.get(ready[0])
            except Exception as exc:  # noqa: BLE001 - the run's own error or Ray's; the other runs go on
                failed[key] = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
                logger.error("failed %s seed %d: %s (log: %s)", key[0], key[1], failed[key],
                             logs / f"{run_name(*key)}.log")
                release(key, False)
                continue
            on_finished(key, info)
            release(key, True)
        _raise_failed(failed, len(todo), cfg)
    finally:
        if started:
            ray.shutdown()


def _raise_failed(failed: Mapping[RunKey, str], total: int, cfg: GridConfig) -> None:
    """One error naming every failed run and why (nothing when none failed).

    Args:
        failed: (variant, seed) -> why it failed, in a few words.
        total: how many runs the grid started or held back.
        cfg: the grid's settings (``archive``: whether the finished runs were archived).
    """
    if failed:
        raise RuntimeError(f"{len(failed)} of {total} runs failed (the finished ones are kept"
                           f"{' and archived' if cfg.archive else ''}; run the grid again to resume the others): "
                           + "; ".join(f"{run_name(*k)}: {why}" for k, why in failed.items()))


POLL_S = 5.0
"""Seconds between two looks of the ``processes`` runner at its runs (ended processes, newly completed phases)."""


def _process_main(module: str, variant: str, run: Any, log_file: str, threads: int) -> None:
    """The body of one run's process (``--runner=processes``): :func:`_task` with everything the process writes
    (log lines, progress as log lines, warnings, a traceback) in the run's log, not on the driver's console where two
    runs would interleave; an error exits with status 1."""
    os.environ[PROGRESS_ENV] = "log"
    os.environ["OMP_NUM_THREADS"] = str(threads)
    Path(log_file).parent.mkdir(parents=True, exist_ok=True)
    with open(log_file, "ab", buffering=0) as log:
        for stream in (sys.stdout, sys.stderr):
            stream.flush()
            os.dup2(log.fileno(), stream.fileno())
    logging.getLogger().handlers.clear()  # a console handler an import installed writes to the log now: no copies
    try:
        _task(module, variant, run, log_file, threads)
    except BaseException:  # noqa: BLE001 - logged by _task; the driver reads the exit status
        sys.exit(1)


class _Started(NamedTuple):
    """One run's process as the ``processes`` runner follows it."""

    process: Any
    start: float
    resumed: list[str]
    """Phases done before the process started."""


def _start_process(ctx: Any, module: str, key: RunKey, run: Any, logs: Path) -> _Started:
    """Start ``run``'s process (spawned: a fresh interpreter) and log where its output goes.

    Args:
        ctx: the ``spawn`` multiprocessing context.
        module: the module whose ``GRID`` runs it.
        key: (variant, seed).
        run: the run's config (``output_dir``, ``torch_threads`` pinned).
        logs: the folder of the runs' logs.

    Returns:
        The process, its start time and the phases the run had already done.
    """
    log = logs / f"{run_name(*key)}.log"
    resumed = completed_phases(run.output_dir)
    process = ctx.Process(target=_process_main, name=run_name(*key),
                          args=(module, key[0], run, str(log), int(getattr(run, "torch_threads", None) or 1)))
    process.start()
    logger.info("started %s seed %d -> %s (log: %s)", key[0], key[1], run.output_dir, log)
    return _Started(process, time.perf_counter(), resumed)


def _log_new_phases(plan: Mapping[RunKey, Any], running: Mapping[RunKey, _Started], seen: dict[RunKey, int]) -> None:
    """One line for each running run that completed phases since the last look: how many, and its latest stage
    (``seen``: the count at the last look, updated)."""
    for key in running:
        phases = completed_phases(plan[key].output_dir)
        if len(phases) > seen.get(key, 0):
            stage = max((int(p.split(".")[0]) for p in phases if p.split(".")[0].isdigit()), default=0)
            logger.info("%s: %d phases done, stage %d reached", run_name(*key), len(phases), stage)
        seen[key] = len(phases)


def _run_processes(cfg: GridConfig, substrate: GridSubstrate, plan: Mapping[RunKey, Any], todo: list[RunKey],
                   on_finished: Callable[[RunKey, dict[str, Any]], None]) -> None:
    """Every run in ``todo`` in its own process, ``cfg.processes`` at once (default: one per core); a run waits for
    the run it continues (``substrate.after``). A process that fails fails its run (and those waiting for it) only;
    they are named in one error at the end."""
    import multiprocessing
    from multiprocessing.connection import wait

    ctx = multiprocessing.get_context("spawn")
    slots = cfg.processes or os.cpu_count() or 1
    logs = Path(cfg.output_root) / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    module = type(substrate).__module__  # its GRID, imported by the process
    waiting = {key: substrate.after(*key) for key in todo}
    ready = [key for key in todo if waiting[key] not in todo]
    waiting = {key: dep for key, dep in waiting.items() if dep in todo}
    running: dict[RunKey, _Started] = {}
    seen: dict[RunKey, int] = {}
    failed: dict[RunKey, str] = {}
    try:
        while ready or running:
            while ready and len(running) < slots:
                key = ready.pop(0)
                running[key] = _start_process(ctx, module, key, plan[key], logs)
                seen[key] = len(running[key].resumed)
            wait([started.process.sentinel for started in running.values()], timeout=POLL_S)
            _log_new_phases(plan, running, seen)
            for key in [k for k, started in running.items() if not started.process.is_alive()]:
                started = running.pop(key)
                started.process.join()
                ok = started.process.exitcode == 0
                if ok:
                    on_finished(key, {"wall_s": time.perf_counter() - started.start, "resumed_phases": started.resumed})
                else:
                    log = logs / f"{run_name(*key)}.log"
                    failed[key] = f"its process ended with status {started.process.exitcode} (log: {log})"
                    logger.error("failed %s seed %d: %s", key[0], key[1], failed[key])
                for dependent in [k for k, dep in waiting.items() if dep == key and ok]:
                    del waiting[dependent]
                    ready.append(dependent)
    finally:  # the driver stopped early (an interrupt, an error): its runs stop with it (a re-run resumes them)
        for started in running.values():
            started.process.terminate()
            started.process.join()
    failed.update({key: f"not started: {run_name(*dep)} failed" for key, dep in waiting.items()})
    _raise_failed(failed, len(todo), cfg)


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
