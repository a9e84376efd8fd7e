"""Re-run one sleep phase of a finished stream with other sleep settings (sleep ablations without new wakes).

    python -m sr_imitation.experiments.sleep_replay --run=outputs/needle_compare/sr_seed0 --stage=3 \\
        --output_dir=outputs/replay/noanchor_s0_k3 --sleep.anchor_strength=0

The replay copies what stage k's sleep starts from (the stream statistics, memories M_1..M_k, the checkpoints of
stages < k and stage k's wake checkpoint, and their ``progress.json`` entries) into ``output_dir``, applies the
``--sleep.*`` flags (``sr-train``'s own sleep flags, parsed and checked by its config) to the run's sleep settings,
and resumes the stream there: stage k's sleep and its
evaluation run exactly as in the original run except for the overrides (same phase seeds). ``replay.json``
puts the original and the replayed sleep side by side: memory losses at the first and last sleep iteration,
stop reason, and success after sleep per skill.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sr_imitation.infra.cli_errors import run_cli, setup_logging
from sr_imitation.infra.cli_parsing import parse_command
from sr_imitation.infra.fingerprint import FINGERPRINT_FILE, write_fingerprint
from sr_imitation.io import write_checked_json
from sr_imitation.offscreen import setup_offscreen_rendering
from sr_imitation.stream.rundir import OverwriteRefusedError, check_not_an_input, read_progress, run_entries_problem
from sr_imitation.substrates.act.cli import parse_config
from sr_imitation.substrates.act.substrate import ACTSubstrate
from sr_imitation.substrates.act.trainer import ACTTrainer, TrainStreamConfig, resume_fingerprint, stored_config_dict

logger = logging.getLogger(__name__)
PROG = "python -m sr_imitation.experiments.sleep_replay"
"""The command as a user types it (usage errors and ``--help`` name it)."""


@dataclass
class SleepReplayConfig:
    run: Path = Path("outputs/needle_cpu")
    stage: int = 2
    output_dir: Path = Path("outputs/sleep_replay")
    overwrite: bool = False
    progress: bool = True


def _read_json(path: Path) -> dict[str, Any]:
    try:
        return read_progress(path)  # source runs of the first progress version may lack the seal
    except FileNotFoundError as exc:
        raise FileNotFoundError(f"{path}: not found (is {path.parent} an sr-train output directory?)") from exc


def prepare_replay(cfg: SleepReplayConfig, sleep_args: list[str] = ()) -> TrainStreamConfig:
    """Copy the state before stage ``cfg.stage``'s sleep into ``cfg.output_dir``; return the replay's config (the
    original run's, with ``sleep_args`` such as ``--sleep.anchor_strength=0`` applied)."""
    src, out, k = Path(cfg.run), Path(cfg.output_dir), cfg.stage
    other = [a for a in sleep_args if not a.startswith("--sleep.")]
    if other:
        raise ValueError(f"a sleep replay changes sleep settings only (--sleep.*), got {other}")
    progress = _read_json(src / "progress.json")
    if not (src / "train_config.json").is_file():
        raise FileNotFoundError(f"{src / 'train_config.json'}: not found (is {src} an sr-train output directory?)")
    # The source run's settings with the sleep flags applied, checked before anything is written.
    train = parse_config(TrainStreamConfig, src / "train_config.json", list(sleep_args))
    skills = train.stream.skills
    if not 2 <= k <= len(skills):
        raise ValueError(f"--stage must be in 2..{len(skills)} (stage 1 has no sleep), got {k}")
    needed = [f"{k}.wake", f"{k}.memory"]
    missing = [key for key in needed if key not in progress["completed"]]
    if missing:
        raise ValueError(f"{src / 'progress.json'}: stage {k} has not finished {missing}; nothing to replay")
    check_not_an_input(out, [src, *(train.stream.dataset_path(i) for i in range(len(skills)))],
                       cfg.overwrite and out.exists())
    if out.exists() and any(out.iterdir()):
        if not cfg.overwrite:
            raise FileExistsError(f"{out} already exists; pass --overwrite=true to replace it")
        problem = run_entries_problem(out, ("replay.json",))  # only a replay (a run) is replaced
        if problem is not None:
            raise OverwriteRefusedError(f"{out}: --overwrite=true refused: {problem}; remove or move it yourself, or "
                                        "choose another output_dir (nothing was removed)")
        shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)
    shutil.copy2(src / "stream_stats.safetensors", out / "stream_stats.safetensors")
    original = ACTSubstrate(dataclasses.replace(train, output_dir=src))
    replayed = ACTSubstrate(dataclasses.replace(train, output_dir=out))
    (out / "memories").mkdir()
    for i in range(k):  # the substrate's own file layout
        shutil.copy2(original.memory_path(i), replayed.memory_path(i))
        phases = ["wake"] if i == k - 1 else [p for p in ("wake", "sleep") if original.checkpoint_dir(i, p).is_dir()]
        for phase in phases:
            shutil.copytree(original.checkpoint_dir(i, phase), replayed.checkpoint_dir(i, phase))
    keep = {key: rec for key, rec in progress["completed"].items()
            if int(key.split(".")[0]) < k or key in (f"{k}.wake", f"{k}.memory", f"{k}.wake.eval")}
    write_checked_json(out / "progress.json", {**progress, "completed": keep})
    write_checked_json(out / "train_config.json", {**stored_config_dict(train), "output_dir": str(out)})
    train.output_dir, train.resume, train.progress = out, True, cfg.progress
    write_fingerprint(out / FINGERPRINT_FILE, resume_fingerprint(train))  # the replay's own settings, its data too
    return train


def replay(cfg: SleepReplayConfig, sleep_args: list[str] = ()) -> dict[str, Any]:
    """Run the replay and write ``replay.json`` (original vs replayed sleep of stage ``cfg.stage``)."""
    train = prepare_replay(cfg, sleep_args)
    ACTTrainer(train).run(stop_after=cfg.stage)
    progress = _read_json(Path(cfg.output_dir) / "progress.json")
    original = _read_json(Path(cfg.run) / "progress.json")["completed"]
    key = f"{cfg.stage}"

    def view(done: dict[str, Any]) -> dict[str, Any]:
        sleep, ev = done.get(f"{key}.sleep", {}), done.get(f"{key}.sleep.eval", {})
        return {name: sleep.get(name) for name in ("stop_iteration", "stop_reason", "anchor_lambda",
                                                      "initial_memory_losses", "final_memory_losses")} | {
            "success_after_wake": done.get(f"{key}.wake.eval", {}).get("success"),
            "success_after_sleep": ev.get("success"),
        }

    result = {"run": str(cfg.run), "stage": cfg.stage, "overrides": list(sleep_args),
              "original": view(original), "replay": view(progress["completed"])}
    write_checked_json(Path(cfg.output_dir) / "replay.json", result)
    return result


def main(args: list[str] | None = None) -> None:
    setup_offscreen_rendering()
    setup_logging()
    args = list(sys.argv[1:] if args is None else args)
    sleep_args = [a for a in args if a.startswith("--sleep.")]
    cfg = parse_command(SleepReplayConfig, [a for a in args if a not in sleep_args], prog=PROG)
    print(json.dumps(replay(cfg, sleep_args), indent=2))  # noqa: T201


if __name__ == "__main__":
    run_cli(PROG, main)  # user errors: one line (--debug: the traceback)
