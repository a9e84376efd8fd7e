"""``sr-main``: the README's main job in one command.

    sr-main --config_path=configs/needle_cpu.json

1. records scripted-expert demonstrations of every stream skill into LeRobot datasets (skipped for skills whose
   dataset already exists, so a re-run or ``--train.resume=true`` does not record again);
2. runs the five-skill wake-sleep stream with evaluation after every wake and sleep phase;
3. writes ``results.json``, ``results.md``, ``metrics.png``, ``success_matrix.png`` and rollout videos to
   ``train.output_dir``, plus a full-suture video of the scripted expert (``expert_suture.mp4``).
"""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path

from sr_imitation.infra.cli_errors import run_cli, setup_logging
from sr_imitation.infra.config_file import ConfigFile, split_config
from sr_imitation.infra.folder_lock import hold_folder
from sr_imitation.offscreen import setup_offscreen_rendering
from sr_imitation.recorders.needle import ensure_recorded
from sr_imitation.stream.methods import replaced_key_refusal, replaced_setting_refusal
from sr_imitation.substrates.act.cli import parse_config, parse_preset
from sr_imitation.substrates.act.config import MainJobConfig
from sr_imitation.substrates.act.trainer import train_stream

logger = logging.getLogger(__name__)

__all__ = ["MainJobConfig", "main", "preset_with_datasets", "run_main_job", "write_expert_video"]


def preset_with_datasets(preset: Path | ConfigFile, train_flags: list[str]) -> MainJobConfig:
    """An sr-main preset with ``sr-train`` flags applied to its train section (``--seed=1``), its datasets recorded
    if missing and checked if present (the experiment drivers' start); with ``--stream.dataset_root`` the stream reads
    the user's own datasets there and nothing is recorded (each run checks them before its first gradient)."""
    cfg, own_datasets = parse_preset(preset, train_flags)
    if not own_datasets:
        ensure_recorded(cfg.record)
    return cfg


def run_main_job(cfg: MainJobConfig) -> dict:
    """Record what is missing, run the stream and write the expert video, as the only writer of
    ``train.output_dir`` (its lock held throughout; the datasets' root is locked while it is recorded into)."""
    with hold_folder(cfg.train.output_dir, "sr-main"):
        return _run_main_job(cfg)


def _run_main_job(cfg: MainJobConfig) -> dict:
    """:func:`run_main_job` once ``train.output_dir``'s lock is held."""
    ensure_recorded(cfg.record)  # datasets of other record settings: refused, not reused
    results = train_stream(cfg.train)
    if cfg.expert_video:
        write_expert_video(cfg, Path(cfg.train.output_dir))
    return results


def write_expert_video(cfg: MainJobConfig, folder: Path) -> Path:
    """The scripted expert's full suture (``expert_suture.mp4``, seeded by ``train.seed``), unless already there.

    Args:
        cfg: the job's settings (the record section's thresholds and frame rate).
        folder: where the video goes.

    Returns:
        The video's path.
    """
    from sr_imitation.envs.needle.chained import run_chained_episode
    from sr_imitation.video import write_mp4

    out = folder / "expert_suture.mp4"
    if not out.exists():
        _, frames = run_chained_episode(cfg.train.seed, cfg.record.thresholds, render=True)
        tmp = write_mp4(out.with_name(".expert_suture.tmp.mp4"), frames, fps=cfg.record.fps)
        os.replace(tmp, out)
    return out


def main(args: list[str] | None = None) -> None:
    setup_offscreen_rendering()
    setup_logging()
    config, rest = split_config(list(sys.argv[1:] if args is None else args))
    cfg = parse_config(MainJobConfig, config, rest, prog="sr-main")
    refusal = replaced_setting_refusal(cfg.train.method, rest, prefix="train.")  # the rule of sr-train's flags
    train = None if config is None or config.sealed else config.settings.get("train")
    if refusal is None and isinstance(train, dict) and train.get("method") == cfg.train.method:  # and of its file
        refusal = replaced_key_refusal(cfg.train.method, train, str(config.path), prefix="train.")
    if refusal is not None:
        raise ValueError(refusal)
    results = run_main_job(cfg)
    out = Path(cfg.train.output_dir)
    m = results["metrics"]
    print(f"datasets: {cfg.record.root.resolve()}")  # noqa: T201
    written = [name for name in ("results.md", "metrics.png", "success_matrix.png", "videos/", "expert_suture.mp4")
               if (out / name).exists()]  # what this run wrote beside results.json (plots and videos may be off)
    print(f"results:  {(out / 'results.json').resolve()}  (also: {', '.join(written) or 'nothing else'})")  # noqa: T201
    print("final " + ", ".join(  # noqa: T201
        f"{k.upper()}={m[k]['final']:.3f}" for k in ("afsr", "prs", "bwt", "bwt_wake", "spi")
        if k in m and m[k]["final"] is not None
    ))


def entry() -> None:
    """Console script ``sr-main``: :func:`main` with one-line user errors (``--debug`` for tracebacks)."""
    run_cli("sr-main", main)


if __name__ == "__main__":
    entry()
