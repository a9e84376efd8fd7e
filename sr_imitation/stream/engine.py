"""Algorithm 1 of the paper, written once for every substrate and every continual method.

    for each skill k = 1..K:
        wake:        train the policy on skill k (+ the method's wake terms: distillation from M_1..M_{k-1},
                     an auxiliary loss, a gradient adjustment)
        memory:      store the frozen memory M_k (if the method keeps memories; which one is the method's choice)
        wake.eval:   evaluate right after the wake (the reference of BWT_wake)
        if the method sleeps after k:
            sleep:       theta <- sleep_consolidate(theta; M_1..M_k, anchor theta_{k-1}, gates from theta_i^wake)
            sleep.eval:  evaluate every learned skill

The substrate (:class:`~sr_imitation.stream.substrate.Substrate`) does what depends on the policy; the method
(:class:`~sr_imitation.stream.methods.ContinualMethod`) answers what depends on the method; the run directory
(:class:`~sr_imitation.stream.rundir.RunDirectory`) records each phase after its files are written. Every phase
seeds its own generators (:meth:`Substrate.begin_phase`), so a run killed at any point and resumed redoes at most
the interrupted phase and reaches the same numbers as an uninterrupted run.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from sr_imitation.core.memory import Memory
from sr_imitation.infra.fingerprint import (
    FINGERPRINT_FILE,
    SettingsFingerprint,
    check_settings,
    check_stack,
    is_allowed,
    read_fingerprint,
    settings_digest,
)
from sr_imitation.infra.folder_lock import hold_folder
from sr_imitation.infra.provenance import log_code_version
from sr_imitation.infra.runlog import RunLog, WandbConfig
from sr_imitation.io import read_checked_json
from sr_imitation.stream.methods import ContinualMethod
from sr_imitation.stream.methods.registry import refusal
from sr_imitation.stream.rundir import PROGRESS_FILE, RunDirectory
from sr_imitation.stream.substrate import (
    Substrate,
    SubstrateProtocolError,
    check_hook_calls,
    check_substrate,
    phase_seed,
)

logger = logging.getLogger(__name__)

POLICY_PHASES = ("wake", "sleep")
"""Phases that change the policy (and checkpoint it)."""


class StreamEngine:
    """Runs (or resumes) one stream: ``substrate`` x ``method`` in ``run``.

    ``after_phase(k, phase)`` (tests) is called after each newly completed phase; raising there simulates a kill.

    Logging: every phase logs INFO lines, and the run log (:class:`~sr_imitation.infra.runlog.RunLog`,
    ``<run>/log.jsonl``, always on; mirrored to wandb with ``wandb.enable``) gets one ``phase`` record per completed
    phase (its numbers flattened), one ``sleep`` record per sleep iteration (objective, memory losses, alpha, gradient
    norms, anchor coefficient, solver status) and whatever the substrate logs (``wake`` epochs) through
    ``substrate.run_log``.
    """

    def __init__(self, substrate: Substrate, method: ContinualMethod, run: RunDirectory, progress: bool = True,
                 after_phase: Callable[[int, str], None] | None = None, wandb: WandbConfig | None = None,
                 log_config: dict[str, Any] | None = None, extend_from: Path | None = None) -> None:
        check_substrate(substrate)  # every protocol member, named in one line, before anything is written
        reason = refusal(method, substrate)
        if reason is not None:
            raise ValueError(f"method {reason}")
        self.substrate = substrate
        self.method = method
        self.run_dir = run
        self.progress = progress
        self.after_phase = after_phase
        self.skills = list(substrate.skills)
        self.memories: list[Memory] = []
        self.wandb = wandb
        self.log_config = log_config
        self.extend_from = None if extend_from is None else Path(extend_from)
        self.log: RunLog | None = None

    # -- the algorithm --------------------------------------------------------------------------------------
    def phase_seed(self, k: int, phase: str) -> int:
        """The seed handed to ``phase`` of stage ``k`` (0-based): the substrate's scheme of the run seed."""
        return phase_seed(self.substrate.seed_scheme, self.substrate.run_seed, k, phase)

    def phases(self, k: int) -> list[str]:
        """The phases of stage ``k`` (0-based) for this method."""
        out = ["wake"]
        if self.method.stores_memories:
            out.append("memory")
        out.append("wake.eval")
        if self.method.sleeps_after(k + 1):
            out += ["sleep", "sleep.eval"]
        return out

    def final_phase(self, k: int) -> str:
        """The phase whose checkpoint ends stage ``k``: its sleep if it slept, else its wake."""
        return "sleep" if self.run_dir.done(k, "sleep") else "wake"

    def run(self, stop_after: int | None = None, report: bool = True) -> dict[str, Any]:
        """Run every pending phase; with ``stop_after=k`` stop after stage k (1-based) and return the progress
        record instead of the results (partial runs); ``report=False``: the progress record, never the results (a
        process that does not evaluate, :mod:`sr_imitation.infra.distributed`). The run directory's lock
        (:func:`~sr_imitation.infra.folder_lock.hold_folder`) is held throughout, taken before the directory is
        looked at: a second writer of the same run is refused in one line, before it writes anything."""
        last = len(self.skills) if stop_after is None else stop_after
        if not 1 <= last <= len(self.skills):
            raise ValueError(f"stop_after must be in 1..{len(self.skills)}, got {stop_after}")
        with hold_folder(self.run_dir.path):
            return self._run_owned(last, report)

    def _run_owned(self, last: int, report: bool) -> dict[str, Any]:
        """:meth:`run` once the run directory's lock is held."""
        log_code_version(logger)
        fresh = self.run_dir.starts_fresh()
        source = self._check_extension() if self.extend_from is not None and fresh else None  # before writing
        self.run_dir.prepare()
        with self.run_dir.undo_on_error():  # a run --overwrite replaced comes back if the start fails
            if source is not None:
                self._import_stages(*source)
            self.log = RunLog(self.run_dir.path, self.wandb, self.log_config)
            self.substrate.run_log = self.log
            try:
                return self._run(last, report)
            finally:
                self.log.close()

    def _run(self, last: int, report: bool = True) -> dict[str, Any]:
        self.substrate.setup()
        self.method.setup(self.substrate)
        pending_load: tuple[int, str] | None = None
        for k in range(last):
            for phase in self.phases(k):
                if self.run_dir.done(k, phase):  # recorded with all its files: restore what later phases need
                    if phase in POLICY_PHASES:
                        pending_load = (k, phase)
                    elif phase == "memory":
                        self.memories.append(self.substrate.load_memory(k, name=self.method.memory_name))
                    continue
                if pending_load is not None:
                    logger.info("resuming at stage %d (%s) %s, from the policy of stage %d %s", k + 1, self.skills[k],
                                phase, pending_load[0] + 1, pending_load[1])
                    self.substrate.load_policy(*pending_load)
                    pending_load = None
                self.substrate.begin_phase(k, phase, self.phase_seed(k, phase))
                logger.info("stage %d (%s): %s", k + 1, self.skills[k], phase)
                t0 = time.perf_counter()
                record = self._run_phase(k, phase)
                record.setdefault("seconds", time.perf_counter() - t0)
                self.run_dir.mark(k, phase, record)
                self.log.log("phase", stage=k + 1, phase=phase, **_scalars(record))
                logger.info("stage %d (%s): %s done in %.1f s", k + 1, self.skills[k], phase, record["seconds"])
                if self.after_phase is not None:
                    self.after_phase(k, phase)
        if last < len(self.skills) or not report:
            return dict(self.run_dir.progress)
        kept = self.memories + self.method.extra_memories(self.substrate, len(self.skills))
        return self.substrate.report(self.run_dir.progress, kept,
                                     [self.final_phase(k) for k in range(len(self.skills))])

    # -- extending a finished stream -------------------------------------------------------------------------
    def _check_extension(self) -> tuple[Path, int, dict[str, Any]]:
        """Check that ``extend_from`` is a finished run of this configuration whose skills are this stream's first
        ones (only the substrate's :attr:`extension_keys` may differ); nothing is written. Returns the source, its
        number of stages and its progress records."""
        source = self.extend_from
        if source is None:
            raise ValueError("no extend_from run given")
        fingerprint_path = source / FINGERPRINT_FILE
        if not fingerprint_path.is_file():
            raise FileNotFoundError(f"{fingerprint_path}: extend_from must name a finished run (no fingerprint)")
        stored = read_fingerprint(fingerprint_path)
        allowed = tuple(self.substrate.extension_keys)
        mine = {k: v for k, v in self.run_dir.fingerprint.settings.items() if not is_allowed(k, allowed)}
        check_stack(fingerprint_path, stored, self.run_dir.fingerprint)
        check_settings(fingerprint_path, {k: v for k, v in stored.items() if not is_allowed(k, allowed)},
                       SettingsFingerprint(mine, settings_digest(mine), self.run_dir.fingerprint.allow,
                                           self.run_dir.fingerprint.derived,
                                           added={k: v for k, v in self.run_dir.fingerprint.added.items()
                                                  if not is_allowed(k, allowed)}))
        skills = list(self.substrate.source_skills(stored))
        n = len(skills)
        if not 1 <= n < len(self.skills) or self.skills[:n] != skills:
            raise ValueError(f"{source}: its skills {skills} are not the first skills of this stream {self.skills}")
        done = read_checked_json(source / PROGRESS_FILE).get("completed", {})
        keys = [RunDirectory.key(k, p) for k in range(n) for p in self.phases(k)]
        missing = [key for key in keys if key not in done]
        if missing:
            raise ValueError(f"{source}: not a finished run of this method (phases {missing[:4]} missing)")
        return source, n, done

    def _import_stages(self, source: Path, n: int, done: dict[str, Any]) -> None:
        """Copy the source's stages (checkpoints, memories, evaluations) and their progress records; the engine
        then continues with stage n + 1 as a resume would (anchor: stage n's final checkpoint)."""
        self.substrate.import_stages(source, n)
        keys = [RunDirectory.key(k, phase) for k in range(n) for phase in self.phases(k)]
        self.run_dir.mark_all({key: done[key] for key in keys})
        logger.info("extending %s: stages 1-%d imported, continuing with %s", source, n, self.skills[n])

    def _run_phase(self, k: int, phase: str) -> dict[str, Any]:
        if phase == "wake":
            memories, weight = self.method.wake_memories(k + 1, self.memories)
            self.method.begin_wake(k, self.memories, self.substrate)
            self.method.hook_calls = None
            record, files = self.substrate.wake(k, memories, weight, self.method)
            check_hook_calls(self.substrate, self.method)  # a declared hook the wake left out changes nothing
            self._save_policy(k, "wake", files)
            return record
        if phase == "memory":
            memory = self.method.make_memory(k, self.substrate)
            self._check_memory_saved(k)
            self.memories.append(memory)
            return {"bytes": memory.nbytes(), "size": memory.size}
        if phase == "wake.eval":
            return self.substrate.evaluate(k, phase, self.substrate.wake_eval_skills(k, "sleep" in self.phases(k)))
        if phase == "sleep":
            return self._sleep(k)
        if phase == "sleep.eval":
            return self.substrate.evaluate(k, phase, list(range(k + 1)))
        raise ValueError(f"unknown phase {phase!r}")

    def _sleep(self, k: int) -> dict[str, Any]:
        """Algorithm 1, lines 7-15: the one place a stream calls the core's sleep."""
        # theta_{k-1}^sleep (none before the first skill: only methods that consolidate after skill 1 get here)
        anchor = self.substrate.parameters_at(k - 1, self.final_phase(k - 1)) if k > 0 else None
        wake_snapshots = [self.substrate.parameters_at(i, "wake") for i in range(k)]  # theta_i^wake, i < k
        memories = self.method.sleep_memories(k, self.memories)
        problem = self.method.prepare_sleep(k, self.substrate.sleep_problem(k, memories), self.substrate)
        before = problem.diagnostics() if problem.diagnostics is not None else {}
        t0 = time.perf_counter()
        log = self.log

        def on_iteration(iteration: int, values: dict[str, Any]) -> None:
            if log is not None:
                log.log("sleep", stage=k + 1, step=iteration, **values)

        result = problem.consolidate(memories, anchor, wake_snapshots, is_final_skill=k == len(self.skills) - 1,
                                     progress=self.progress, on_iteration=on_iteration)
        logger.info("stage %d sleep: %d iterations (%s), solver %s", k + 1, result.stop_iteration,
                    result.stop_reason, dict(result.solver_status))
        seconds = time.perf_counter() - t0
        record: dict[str, Any] = {"seconds": seconds, **result.summary()}
        if problem.diagnostics is not None:
            after = problem.diagnostics()
            record.update({f"{key}_before": value for key, value in before.items()})
            record.update({f"{key}_after": value for key, value in after.items()})
        self._save_policy(k, "sleep", {"sleep_diagnostics.json": result.to_dict()})
        return record

    # -- what a substrate could otherwise leave out silently ----------------------------------------------------
    def _save_policy(self, k: int, phase: str, files: dict[str, Any]) -> None:
        """The substrate's checkpoint, then every extra file there (:meth:`Substrate.policy_file`)."""
        self.substrate.save_policy(k, phase, files)
        dropped = [name for name in files if not Path(self.substrate.policy_file(k, phase, name)).is_file()]
        if dropped:
            where = self.substrate.policy_file(k, phase, dropped[0])
            raise SubstrateProtocolError(f"{type(self.substrate).__name__}.save_policy did not write {dropped} (at "
                                         f"{where}): a substrate writes every file the engine hands it")

    def _check_memory_saved(self, k: int) -> None:
        """M_k is where a resume loads it from: a memory made but not saved fails only when a run resumes."""
        try:
            self.substrate.load_memory(k, name=self.method.memory_name)
        except FileNotFoundError as exc:
            raise SubstrateProtocolError(
                f"{type(self.substrate).__name__}: the memory of stage {k + 1} was made but not saved where "
                f"load_memory(k, name={self.method.memory_name!r}) finds it ({exc}); a resume could not continue "
                "(make_memory, or the method's save_memory, saves it)") from exc


def _scalars(record: dict[str, Any], prefix: str = "", depth: int = 0) -> dict[str, Any]:
    """The numbers of a phase record, flattened with ``.`` (two levels deep; lists of numbers kept)."""
    out: dict[str, Any] = {}
    for key, value in record.items():
        name = f"{prefix}{key}"
        if isinstance(value, bool) or value is None:
            continue
        if isinstance(value, int | float):
            out[name] = value
        elif isinstance(value, dict) and depth < 2:
            out.update(_scalars(value, f"{name}.", depth + 1))
        elif isinstance(value, list) and value and all(isinstance(v, int | float) for v in value):
            out[name] = value
    return out
