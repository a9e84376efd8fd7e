"""``sr-train --substrate=sac``: the stream engine with :class:`~sr_imitation.substrates.sac.substrate.SACSubstrate` and
``cfg.method``, and the measurements of a finished run for the shared results (:mod:`sr_imitation.reporting.results`).

Output layout (every file written atomically; ``progress.json`` records each phase after its files)::

    <output_dir>/settings_fingerprint.json, train_config.json   (written once at the start, never on resume;
                                                                  older runs: config.json)
    <output_dir>/progress.json
    <output_dir>/stages/01_reach/{wake/agent.safetensors, memory.safetensors, trajectories.safetensors}
    <output_dir>/stages/02_door-open/{wake/, sleep/agent.safetensors, sleep/sleep_diagnostics.json, ...}
    <output_dir>/videos/stage_02_door-open/{reach,door-open}_episode0_<success|failure>.mp4
    <output_dir>/results.json, results.md, metrics.png, success_matrix.png

Every phase seeds its own generators (:meth:`SACSubstrate.begin_phase`), so ``--resume`` after a kill at any point
continues from the last completed phase and, on CPU, reproduces the uninterrupted run exactly.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

from sr_imitation.infra.distributed import launched_world_size
from sr_imitation.reporting.results import RESULTS_VERSION
from sr_imitation.stream.run import StreamRun
from sr_imitation.substrates.sac.config import RLTrainConfig
from sr_imitation.substrates.sac.results import prs_pairs, write_results
from sr_imitation.substrates.sac.substrate import CHECKPOINT_FORMAT, CHECKPOINT_VERSION, SACSubstrate

logger = logging.getLogger(__name__)

__all__ = ["CHECKPOINT_FORMAT", "CHECKPOINT_VERSION", "RESULTS_VERSION", "SACTrainer", "prs_pairs",
           "write_results"]


def check_skill_names(skills: list[str]) -> None:
    """Every skill is a Meta-World v3 environment: ``ValueError`` naming ``stream.skills`` and the unknown names,
    before the first stage trains (a typo in a later skill would otherwise surface stages later)."""
    import metaworld  # noqa: PLC0415 (only the SAC substrate needs Meta-World)

    unknown = [s for s in skills if s not in metaworld.MT1.ENV_NAMES]
    if unknown:
        raise ValueError(f"stream.skills: {unknown} are not Meta-World v3 environments (use '-v3' names, e.g. "
                         "'reach-v3')")


class SACTrainer(StreamRun):
    """Runs (or resumes) one seed of the stream described by ``cfg`` (:class:`~sr_imitation.stream.run.StreamRun`
    with the SAC substrate); the skills are checked to be Meta-World environments before anything is written.

    ``after_stage`` (tests) is called with the stage index after each completed stage; raising there simulates
    a killed run (``after_phase(k, phase)``: after each phase).
    """

    def __init__(self, cfg: RLTrainConfig, after_stage: Callable[[int], None] | None = None,
                 after_phase: Callable[[int, str], None] | None = None) -> None:
        if launched_world_size() > 1:
            raise ValueError("several processes (torchrun / accelerate launch): the SAC substrate trains in one "
                             "process (its updates are single small batches); run seeds in parallel with sr-grid")
        check_skill_names(cfg.stream_skills)  # before the run directory is touched and the first gradient
        substrate = SACSubstrate(cfg)
        # Runs from before the engine (one checkpoint per stage) cannot be resumed by it: no legacy settings.
        super().__init__(cfg, substrate, fingerprint=cfg.resume_fingerprint(), stored_config=cfg.stored_config(),
                         after_phase=after_phase)
        self.cfg: RLTrainConfig = cfg
        self.substrate: SACSubstrate = substrate
        self.after_stage = after_stage

    def on_phase(self, k: int, phase: str) -> None:
        if self.after_stage is not None and phase == self.engine.phases(k)[-1]:
            self.after_stage(k)

    def stage_dir(self, k: int) -> Path:
        return self.substrate.stage_dir(k)
