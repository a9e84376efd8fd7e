"""The three ways ``sr-grid`` carries out its runs (``--runner``): one after another here, as Ray tasks, or as
processes of this machine."""

from __future__ import annotations

import logging
import os
import sys
import time
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

from sr_imitation.experiments.archive import RunKey
from sr_imitation.experiments.grid_run import KILL_HOOK_ENV, completed_phases, run_name, run_one, run_task
from sr_imitation.progress import PROGRESS_ENV

logger = logging.getLogger(__name__)

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


def run_loop(cfg: Any, substrate: Any, plan: Mapping[RunKey, Any], todo: list[RunKey],
             on_finished: Callable[[RunKey, dict[str, Any]], None]) -> None:
    """Every run in ``todo`` here, one after another (an error stops the loop). The runners' arguments: the grid's
    settings (:class:`~sr_imitation.experiments.grid.GridConfig`), its
    :class:`~sr_imitation.experiments.grid.GridSubstrate`, every run's config, the runs to run in order and what to
    call with each finished one's record."""
    for key in todo:
        logger.info("=== %s seed %d -> %s", key[0], key[1], plan[key].output_dir)
        on_finished(key, run_one(substrate, key[0], plan[key]))


def _threads(run: Any, opts: RayOptions) -> int:
    """A run's torch threads: its ``torch_threads`` (pinned by the grid before it plans), else its cores."""
    return int(getattr(run, "torch_threads", None) or max(1, int(opts.num_cpus)))


def _resources(opts: RayOptions, substrate: Any, run: Any) -> dict[str, Any]:
    gpus = opts.num_gpus if opts.num_gpus is not None else float(substrate.device(run).startswith("cuda"))
    env = {"OMP_NUM_THREADS": str(_threads(run, opts))}
    env.update({k: os.environ[k] for k in ("MUJOCO_GL", "PYOPENGL_PLATFORM", KILL_HOOK_ENV) if k in os.environ})
    out: dict[str, Any] = {"num_cpus": opts.num_cpus, "num_gpus": gpus, "max_retries": opts.max_retries,
                           "runtime_env": {"env_vars": env}}
    if opts.memory_gb is not None:
        out["memory"] = int(opts.memory_gb * 2**30)
    return out


def run_ray(cfg: Any, substrate: Any, plan: Mapping[RunKey, Any], todo: list[RunKey],
            on_finished: Callable[[RunKey, dict[str, Any]], None]) -> None:
    """Every run in ``todo`` as one Ray task (a fresh worker process each; ``--ray.*``); a run waits for the run it
    continues. A task that fails fails its run (and those waiting for it) only; they are named in one error at the
    end."""
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
        task = ray.remote(max_calls=1)(run_task)  # a fresh worker process per run
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


def _raise_failed(failed: Mapping[RunKey, str], total: int, cfg: Any) -> None:
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
    """The body of one run's process (``--runner=processes``): :func:`run_task` with everything the process writes
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
        run_task(module, variant, run, log_file, threads)
    except BaseException:  # noqa: BLE001 - logged by run_task; the driver reads the exit status
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


def run_processes(cfg: Any, substrate: Any, plan: Mapping[RunKey, Any], todo: list[RunKey],
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


RUNNERS: dict[str, Callable[..., None]] = {"loop": run_loop, "ray": run_ray, "processes": run_processes}
"""``--runner`` -> the function that carries out the runs."""
