"""One run entry for every substrate: :class:`StreamRun` builds what a run of a stream is made of, the same way
whatever the policy family, and runs it.

    check_substrate(substrate)                                                  # the protocol, in one line
    check_shared_settings(cfg, substrate.name)                                  # what could be left out silently
    method    = make_method(cfg.method, substrate, substrate.method_settings(), cfg.method_options)
    run_dir   = RunDirectory(cfg.output_dir, fingerprint, train_config.json, ...)  # checked before anything is written
    engine    = StreamEngine(substrate, method, run_dir, ...)                    # Algorithm 1, once
    preflight()                                                                 # the substrate's checks
    engine.run()

A substrate's trainer (``sr_imitation.substrates.act.trainer.ACTTrainer``,
``sr_imitation.substrates.sac.trainer.SACTrainer``) subclasses it and adds only its own: the settings fingerprint and
stored configuration of its run config, the checks before the first phase (:meth:`StreamRun.preflight`: datasets,
environments) and what follows a finished phase (:meth:`StreamRun.on_phase`, e.g. the ``last`` checkpoint link).
Everything else (method, run directory, engine, the saved config's name, resume) is here, once.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from sr_imitation.infra.fingerprint import SettingsFingerprint
from sr_imitation.infra.folder_lock import hold_folder
from sr_imitation.stream.config import RunConfig, check_shared_settings
from sr_imitation.stream.engine import StreamEngine
from sr_imitation.stream.methods import ContinualMethod, make_method
from sr_imitation.stream.rundir import RUN_CONFIG_FILE, RunDirectory
from sr_imitation.stream.substrate import Substrate, check_substrate


class StreamRun:
    """Runs (or resumes) one stream: ``cfg.method`` on ``substrate`` through the engine, in ``cfg.output_dir``.

    Args:
        cfg: the run's configuration (a substrate's subclass of :class:`~sr_imitation.stream.config.RunConfig`
            with a ``stream.extend_from``).
        substrate: the policy family's :class:`~sr_imitation.stream.substrate.Substrate`.
        fingerprint: the settings a resume must keep (written to ``settings_fingerprint.json``, checked on resume
            before anything is written).
        stored_config: the configuration saved as ``train_config.json`` (and logged).
        check_inputs: checks the run's recorded inputs on resume (datasets by content), or ``None``.
        inputs: the paths the run reads (datasets; ``stream.extend_from`` is added here): the output directory may
            neither lie inside one nor, with ``--overwrite``, hold one.
        after_phase: called with ``(k, phase)`` after each newly completed phase, after :meth:`on_phase` (tests
            raise there to simulate a killed run).
    """

    def __init__(self, cfg: RunConfig, substrate: Substrate, *, fingerprint: SettingsFingerprint,
                 stored_config: dict[str, Any], check_inputs: Callable[..., Any] | None = None,
                 after_phase: Callable[[int, str], None] | None = None, inputs: Sequence[Path] = ()) -> None:
        self.cfg = cfg
        self.out = Path(cfg.output_dir)
        check_substrate(substrate)
        check_shared_settings(cfg, substrate.name)  # here, for every substrate: none can leave it out
        self.substrate = substrate
        # --method_options go from the run's configuration straight to the method, not through the substrate
        self.method: ContinualMethod = make_method(cfg.method, substrate, substrate.method_settings(),
                                                   cfg.method_options or {})
        self.run_dir = RunDirectory(self.out, fingerprint, RUN_CONFIG_FILE, stored_config, cfg.resume, cfg.overwrite,
                                    check_inputs=check_inputs, inputs=[*inputs, cfg.stream.extend_from])
        self.after_phase = after_phase
        self.engine = StreamEngine(substrate, self.method, self.run_dir, cfg.progress, self._after_phase,
                                   wandb=cfg.wandb, log_config=stored_config,
                                   extend_from=cfg.stream.extend_from)

    def preflight(self) -> None:
        """Checks before the first phase runs (a substrate's datasets, environments); nothing by default."""

    def on_phase(self, k: int, phase: str) -> None:
        """After each newly completed phase of stage ``k`` (0-based); nothing by default."""

    def _after_phase(self, k: int, phase: str) -> None:
        self.on_phase(k, phase)
        if self.after_phase is not None:
            self.after_phase(k, phase)

    def final_phase(self, k: int) -> str:
        """The last phase of stage ``k`` for this method (its consolidated policy)."""
        return self.engine.final_phase(k)

    def run(self, stop_after: int | None = None, report: bool = True) -> dict[str, Any]:
        """Every pending phase; with ``stop_after=k`` stop after stage k (1-based), or with ``report=False``, return
        the progress instead of the final results. The run directory's lock is held throughout (the engine's,
        taken here already so that the checks before the first phase run as its only writer)."""
        with hold_folder(self.out):
            self.preflight()
            return self.engine.run(stop_after, report)
