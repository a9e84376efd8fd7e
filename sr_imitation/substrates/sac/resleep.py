"""``sr-sac-sleep``: redo one stage's sleep of a finished SAC run with other sleep settings, from its stored weights.

    sr-sac-sleep --source=docs/results/sac_sleep_calibration.weights/sr_seed100 \\
        --archived=docs/results/sac_sleep_calibration/sr_seed100 --stage=5 \\
        --output_dir=outputs/resleep/sr_seed100_a1 --changes=[--sleep.early_stop_tol=0]

A sleep variant can so be screened in minutes on wakes that took hours: the new run directory starts as
the source run killed right after stage ``stage``'s wake evaluation (its stages before, checkpoints, memories and
records, copied; the stage's own wake checkpoint and records), and the stream engine resumes it with the changed
settings: it redoes every memory phase up to that stage from the stored wake checkpoints (the same memory if the
memory kind is unchanged; another kind, e.g. SR's ``memory: expert`` option, is built from the stored wake-end
actors), then the stage's sleep and its evaluation, and writes the results of any run (``results.json``,
``results.md``, plots; the same schema, the earlier stages' rows as the source recorded them). The stages after
``stage`` are not run (``stage`` must be the source's last, or the results would mix settings: the rows after it
would be the source's).

Only settings a re-sleep may change are accepted (:data:`CHANGEABLE`: the sleep's, SR's method options, the
evaluation videos); anything else differing from the source's stored settings is refused in one line before
anything is written. With ``--archived`` the source's files are first checked against the archive's
``weights.json`` (:func:`~sr_imitation.infra.weight_store.verify_weights`). What was re-slept from what is
recorded in ``resleep.json`` (sealed; written last, once the new run holds everything it takes from the source)
beside the run's own files. The same command again continues a killed re-sleep (or rewrites a finished one's
report); a start killed before ``resleep.json`` exists is redone with ``--overwrite=true``. With the source's
settings unchanged the re-sleep repeats the source's sleep bit for bit on the same CPU type (a resume's guarantee;
tested).
"""

from __future__ import annotations

import logging
import shutil
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sr_imitation.infra.cli_errors import run_cli, setup_logging
from sr_imitation.infra.cli_parsing import parse_command
from sr_imitation.infra.fingerprint import (
    FINGERPRINT_FILE,
    SettingsFingerprint,
    read_fingerprint,
    resume_differences,
    settings_digest,
)
from sr_imitation.infra.folder_lock import hold_folder
from sr_imitation.io import read_checked_json, write_checked_json
from sr_imitation.stream.rundir import PROGRESS_FILE, RUN_CONFIG_FILE, RunDirectory

logger = logging.getLogger(__name__)

PROG = "sr-sac-sleep"
RESLEEP_FILE = "resleep.json"
"""In a re-slept run: its source, the stage and the settings changed (sealed)."""
CHANGEABLE = ("sleep.", "method_options", "method_config.", "eval.videos_per_skill", "progress", "torch_threads")
"""Settings (fingerprint keys, by prefix) a re-sleep may change: they act on the sleep or on nothing the source's
stages computed. SR's ``reset_wake`` option changes the wakes and is refused (:data:`WAKE_OPTIONS`)."""
WAKE_OPTIONS = ("method_options.reset_wake", "method_config.reset_wake")
"""Method options that change what a wake computes: a re-sleep cannot change them."""
REDONE = ("sleep", "trajectories.safetensors")
"""What a re-slept stage's folder does not take from the source: the sleep's checkpoint and the stage evaluation's
trajectories (both made again)."""


@dataclass
class ResleepConfig:
    """``sr-sac-sleep``'s command line."""

    source: Path = Path()
    """A finished SAC run: its output directory or its weight store (``<archive>.weights/<run>``)."""
    output_dir: Path = Path()
    """The new run directory (must not exist, unless ``overwrite``)."""
    stage: int = 0
    """The stage (1-based) whose sleep is redone; 0: the source's last stage (the only one allowed for now)."""
    changes: list[str] = field(default_factory=list)
    """``sr-train --substrate=sac`` flags that differ from the source run (``--sleep.*``, ``--method_options=...``,
    ``--eval.videos_per_skill``)."""
    archived: Path | None = None
    """The archived run whose ``weights.json`` the source's files are checked against before anything is read."""
    overwrite: bool = False
    """Replace ``output_dir`` if it holds a run of this package."""

    def __post_init__(self) -> None:
        if self.stage < 0:
            raise ValueError(f"stage must be >= 1 (or 0: the last), got {self.stage}")


def check_changes(source: Path, fingerprint: SettingsFingerprint) -> list[str]:
    """The settings keys that differ from the source's fingerprint (compared as a resume compares them:
    :func:`~sr_imitation.infra.fingerprint.check_settings`); ``ValueError`` naming the first ones a re-sleep may
    not change."""
    changed = sorted(resume_differences(read_fingerprint(source / FINGERPRINT_FILE), fingerprint))
    refused = [k for k in changed if k.startswith(WAKE_OPTIONS) or not k.startswith(CHANGEABLE)]
    if refused:
        raise ValueError(f"changes: a re-sleep may change the sleep's settings only; {', '.join(refused[:4])} would "
                         f"change what {source / FINGERPRINT_FILE} records for the wakes (run sr-train instead)")
    return changed


def seed_run(cfg: ResleepConfig, run_cfg: Any, trainer: Any, changed: list[str]) -> dict[str, Any]:
    """Make ``output_dir`` the source run killed after the re-slept stage's wake evaluation: its fingerprint and
    config (the new settings), the stages before (every file), the stage's own wake files, and the records of
    those phases except the memory phases (redone from the stored wakes). Returns the ``resleep.json`` record."""
    source = Path(cfg.source)
    progress = read_checked_json(source / PROGRESS_FILE)["completed"]
    substrate, engine = trainer.substrate, trainer.engine
    stages = len(substrate.skills)
    stage = cfg.stage or stages
    if stage != stages:
        raise ValueError(f"stage: only the source's last stage ({stages}) can be re-slept (later stages would keep "
                         f"the source's settings), got {stage}")
    k = stage - 1
    if "sleep" not in engine.phases(k):
        raise ValueError(f"stage {stage}: the run as configured does not sleep there (sleep.enabled, method)")
    keep = {RunDirectory.key(i, p): progress[RunDirectory.key(i, p)] for i in range(stage) for p in engine.phases(i)
            if p != "memory" and (i < k or p in ("wake", "wake.eval"))}
    missing = [key for key in keep if key not in progress]
    if missing:
        raise ValueError(f"{source}: not a finished run of this method up to stage {stage} (phases {missing[:4]} "
                         "missing)")
    rd = trainer.run_dir
    with rd.undo_on_error():
        rd.prepare()
        for i in range(stage):
            src = source / substrate.stage_dir(i).relative_to(substrate.out)
            if not src.is_dir():
                raise FileNotFoundError(f"{src}: missing from the source (no weights stored for stage {i + 1})")
            ignore = shutil.ignore_patterns(*REDONE) if i == k else None
            shutil.copytree(src, substrate.stage_dir(i), ignore=ignore, dirs_exist_ok=False)
        rd.mark_all(keep)
        record = seeding_record(cfg, changed, stage)
        write_checked_json(rd.path / RESLEEP_FILE, record)  # last: the seeded run is complete once it exists
    return record


def seeding_record(cfg: ResleepConfig, changed: list[str], stage: int) -> dict[str, Any]:
    """What ``resleep.json`` records: the source (and its settings' sha256), the stage, the changes."""
    source = Path(cfg.source)
    return {"source": str(source), "archived": None if cfg.archived is None else str(cfg.archived), "stage": stage,
            "changed": changed, "changes": list(cfg.changes),
            "source_settings_sha256": settings_digest(read_fingerprint(source / FINGERPRINT_FILE))}


def _check_same_resleep(cfg: ResleepConfig, changed: list[str], record: dict[str, Any], path: Path) -> None:
    want = seeding_record(cfg, changed, record.get("stage", 0))
    differ = [k for k in ("source", "stage", "changes", "source_settings_sha256") if record.get(k) != want[k]]
    if differ:
        raise ValueError(f"{path}: a re-sleep of another source or with other changes ({', '.join(differ)} differ); "
                         "choose another output_dir or pass --overwrite=true")


def resleep(cfg: ResleepConfig) -> dict[str, Any]:
    """Redo the sleep (see the module docstring) as the only writer of ``output_dir`` (its lock held from before it
    is looked at to the end); returns the new run's results."""
    from sr_imitation.infra.weight_store import verify_weights

    source = Path(cfg.source)
    config_file = source / RUN_CONFIG_FILE
    if not config_file.is_file():
        raise FileNotFoundError(f"{config_file}: no such file (source must be a finished SAC run or its weight "
                                "store)")
    if cfg.archived is not None:
        verify_weights(Path(cfg.archived), source)
    with hold_folder(cfg.output_dir):
        return _resleep(cfg, source, config_file)


def _resleep(cfg: ResleepConfig, source: Path, config_file: Path) -> dict[str, Any]:
    """:func:`resleep` once ``output_dir``'s lock is held."""
    from sr_imitation.substrates.sac.cli import parse
    from sr_imitation.substrates.sac.trainer import SACTrainer

    run_cfg = parse([f"--config_path={config_file}", f"--output_dir={cfg.output_dir}",
                     f"--overwrite={str(cfg.overwrite).lower()}", "--resume=false", *cfg.changes])
    changed = check_changes(source, run_cfg.resume_fingerprint())  # before anything is written
    seeded = Path(cfg.output_dir) / RESLEEP_FILE
    if seeded.is_file() and not cfg.overwrite:  # the same re-sleep, killed or finished: continue it
        record = read_checked_json(seeded)
        _check_same_resleep(cfg, changed, record, seeded)
        logger.info("continuing the re-sleep in %s", cfg.output_dir)
    else:
        logger.info("re-sleeping %s: settings changed %s", source, changed or "none (a repeat of its sleep)")
        record = seed_run(cfg, run_cfg, SACTrainer(run_cfg), changed)
    run_cfg.resume, run_cfg.overwrite = True, False
    results = SACTrainer(run_cfg).run()
    logger.info("re-slept stage %d of %s: final AFSR %s; results in %s", record["stage"], source,
                results["metrics"]["afsr"]["final"], Path(cfg.output_dir) / "results.json")
    return results


def main(args: list[str] | None = None) -> None:
    setup_logging()
    resleep(parse_command(ResleepConfig, list(sys.argv[1:] if args is None else args), prog=PROG))


def entry() -> None:
    """``sr-sac-sleep``: :func:`main` with one-line user errors (``--debug`` for tracebacks)."""
    run_cli(PROG, main)


if __name__ == "__main__":
    entry()
