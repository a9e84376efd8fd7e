"""``sr-record --env=metaworld``: Meta-World v3 demonstrations by Meta-World's own scripted policies, as LeRobot v3
datasets.

One dataset per task at ``<root>/<task>`` (features ``observation.state``: Meta-World's 39-number observation as its
MT benchmarks give it, goal visible; ``action``: 4 numbers; ``next.reward``/``next.success``/``next.done``;
optionally ``observation.images.<camera>``, drawn by the offscreen renderer the needle and the SAC videos use; task
string = the task's name). The demonstrator is ``metaworld.policies``' scripted policy for the task; an episode
ends at Meta-World's first ``info["success"]`` (the frame that reaches it is the last one), and only successful
episodes are kept: the number dropped is logged and stored in ``meta/sr_record.json``.

Configurations: episode attempt ``a`` of a task uses ``metaworld.MT1(task)``'s configuration ``a mod 50`` (our
choice: the demonstrations cover the 50 configurations the evaluation draws from as evenly as the count allows, in
the same order for every task), with environment seed :func:`sr_imitation.recorders.needle.episode_seed` (the
task's index: its name's CRC-32 mod 100). The bytes of a dataset are a function of these settings (as for the needle
recorder), so its content digest identifies it.

Example (the MT5 imitation stream's datasets, ``configs/metaworld_mt5_imitation.json``)::

    sr-record --env=metaworld --root=datasets/metaworld_mt5 --num_episodes=50
"""

from __future__ import annotations

import contextlib
import logging
import shutil
import sys
import tempfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sr_imitation.envs.metaworld.env import ACTION_NAMES, DEFAULT_CAMERA, OBS_NAMES, MetaWorldEnv
from sr_imitation.envs.metaworld.tasks import (
    ACT_DIM,
    MT5_STREAM,
    NUM_CONFIGURATIONS,
    OBS_DIM,
    check_task,
    scripted_policy,
)
from sr_imitation.envs.metaworld.video import CAMERAS
from sr_imitation.infra.cli_parsing import parse_command
from sr_imitation.infra.folder_lock import hold_folder, remove_leftovers
from sr_imitation.io import write_checked_json
from sr_imitation.progress import Progress
from sr_imitation.recorders.needle import (
    RECORD_SETTINGS_FILE,
    STAGING_PATTERN,
    VIDEO_CODECS,
    _canonical_data_files,
    _canonical_stats,
    _replace_dir,
    episode_seed,
    foreign_dataset_problem,
    quiet_dataset_progress,
)

logger = logging.getLogger(__name__)



@dataclass
class MetaWorldRecordConfig:
    """Options of ``sr-record --env=metaworld`` (one LeRobot dataset per task at ``<root>/<task>``)."""

    env: str = "metaworld"
    """The demonstration source (this command: metaworld; sr-record without --env records the needle)."""
    skills: list[str] = field(default_factory=lambda: list(MT5_STREAM))
    """Meta-World v3 tasks to record (default: the paper's MT5 order)."""
    num_episodes: int = 50
    """Successful episodes per task (failed scripted episodes are dropped and counted)."""
    root: Path = Path("datasets/metaworld_mt5")
    """Parent folder; each task's dataset goes to <root>/<task>."""
    repo_id_prefix: str = "local/sr_metaworld"
    """LeRobot repo_id of each dataset is <prefix>_<task> (local only; nothing is pushed)."""
    camera: str | None = None
    """Also store images of this Meta-World camera as observation.images.<camera> (e.g. corner2); null: state only."""
    image_size: int = 64
    """Camera image height and width when camera is set."""
    video: bool = False
    """Store camera images as mp4 (decode with video_backend=pyav) instead of PNG in parquet."""
    vcodec: str = "h264"
    """Video codec when video is true - h264, hevc or libsvtav1."""
    max_steps: int = 200
    """Step limit of one scripted episode (the experts' first success comes by step 92 on every MT5 task)."""
    seed: int = 0
    """Base seed of the environment seeds (episode_seed(seed, task index, attempt))."""
    fps: int = 80
    """Dataset frame rate (Meta-World's control rate: 80 steps per simulated second)."""
    overwrite: bool = False
    """Replace existing datasets at the targets, only datasets sr-record wrote (anything else is refused)."""
    max_failures: int = 50
    """Give up on a task after this many failed scripted episodes."""

    def __post_init__(self) -> None:
        if self.env != "metaworld":
            raise ValueError(f"env: this recorder is --env=metaworld, got {self.env!r}")
        if not self.skills:
            raise ValueError("skills must not be empty")
        for i, task in enumerate(self.skills):
            try:
                check_task(task)
            except ValueError as exc:
                raise ValueError(f"skills[{i}]: {exc}") from None
        if len(set(self.skills)) != len(self.skills):
            raise ValueError(f"skills must be distinct, got {self.skills}")
        for name in ("num_episodes", "max_steps", "fps"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.max_failures < 0:
            raise ValueError(f"max_failures must be >= 0, got {self.max_failures}")
        if self.camera is not None and self.camera not in CAMERAS:
            raise ValueError(f"camera must be one of {list(CAMERAS)} or null, got {self.camera!r}")
        if not 8 <= self.image_size <= 1280:
            raise ValueError(f"image_size must be in [8, 1280], got {self.image_size}")
        if self.vcodec not in VIDEO_CODECS:
            raise ValueError(f"vcodec must be one of {VIDEO_CODECS}, got {self.vcodec!r}")
        self.root = Path(self.root)

    def target(self, task: str) -> Path:
        return self.root / task


def dataset_features(cfg: MetaWorldRecordConfig) -> dict:
    """LeRobot feature spec of a Meta-World dataset."""
    features: dict = {
        "observation.state": {"dtype": "float32", "shape": (OBS_DIM,), "names": list(OBS_NAMES)},
        "action": {"dtype": "float32", "shape": (ACT_DIM,), "names": list(ACTION_NAMES)},
        "next.reward": {"dtype": "float32", "shape": (1,), "names": None},
        "next.success": {"dtype": "bool", "shape": (1,), "names": None},
        "next.done": {"dtype": "bool", "shape": (1,), "names": None},
    }
    if cfg.camera is not None:
        features[f"observation.images.{cfg.camera}"] = {
            "dtype": "video" if cfg.video else "image", "shape": (cfg.image_size, cfg.image_size, 3),
            "names": ["height", "width", "channels"]}
    return features


def content_settings(cfg: MetaWorldRecordConfig, task: str) -> dict:
    """What decides a dataset's content (stored checksummed in ``meta/sr_record.json``)."""
    keys = ("num_episodes", "camera", "image_size", "video", "vcodec", "max_steps", "seed", "fps")
    return {"env": "metaworld", "skill": task, **{k: getattr(cfg, k) for k in keys}}


def run_demo(env: MetaWorldEnv, act, seed: int, configuration: int, image_key: str | None, max_steps: int
             ) -> tuple[list[dict], bool]:
    """One scripted episode on ``configuration``, ended at the first success; returns (frames, success)."""
    obs, _ = env.reset(seed=seed, options={"configuration": configuration})
    frames: list[dict] = []
    for _ in range(max_steps):
        action = np.asarray(act(obs["agent_pos"]), dtype=np.float32)
        next_obs, reward, terminated, truncated, info = env.step(action)
        frame = {"observation.state": obs["agent_pos"], "action": action,
                 "next.reward": np.array([reward], dtype=np.float32),
                 "next.success": np.array([info["is_success"]], dtype=bool),
                 "next.done": np.array([terminated or truncated], dtype=bool), "task": env.task}
        if image_key is not None:
            frame[image_key] = next(iter(obs["pixels"].values()))
        frames.append(frame)
        obs = next_obs
        if info["is_success"]:
            return frames, True
        if terminated or truncated:
            break
    return frames, False


def record_task(cfg: MetaWorldRecordConfig, task: str, task_index: int) -> Path:
    """Record ``cfg.num_episodes`` successful scripted episodes of ``task``; returns the dataset path."""
    from sr_imitation.lerobot_compat import create_dataset

    target = cfg.target(task)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{task}.tmp-", dir=target.parent))
    image_key = None if cfg.camera is None else f"observation.images.{cfg.camera}"
    env = MetaWorldEnv(task, obs_type="agent_pos" if cfg.camera is None else "pixels_agent_pos",
                       image_height=cfg.image_size, image_width=cfg.image_size, camera=cfg.camera or DEFAULT_CAMERA,
                       max_episode_steps=cfg.max_steps)
    act = scripted_policy(task)
    dataset = None
    try:
        dataset = create_dataset(repo_id=f"{cfg.repo_id_prefix}_{task}", fps=cfg.fps,
                                        features=dataset_features(cfg), root=tmp / "dataset",
                                        robot_type="metaworld_sawyer", use_videos=cfg.video, vcodec=cfg.vcodec)
        failed: list[int] = []
        attempt = 0
        with Progress(cfg.num_episodes, f"record {task}", logger, unit="ep") as bar:
            while bar.n < cfg.num_episodes:
                configuration = attempt % NUM_CONFIGURATIONS
                frames, success = run_demo(env, act, episode_seed(cfg.seed, task_index, attempt), configuration,
                                           image_key, cfg.max_steps)
                attempt += 1
                if not success:
                    failed.append(configuration)
                    if len(failed) > cfg.max_failures:
                        raise RuntimeError(f"{task}: more than {cfg.max_failures} failed scripted episodes "
                                           f"(configurations {sorted(set(failed))})")
                    continue
                for frame in frames:
                    dataset.add_frame(frame)
                dataset.save_episode()
                bar.update(1)
        dataset.finalize()
        dataset = None
        _canonical_stats(tmp / "dataset")
        _canonical_data_files(tmp / "dataset", f"sr-record-metaworld:{cfg.seed}:{task}")
        write_checked_json(tmp / "dataset" / RECORD_SETTINGS_FILE,
                           {**content_settings(cfg, task), "failed_configurations": failed})
        images = tmp / "dataset" / "images"
        if images.is_dir() and not any(p.is_file() for p in images.rglob("*")):
            shutil.rmtree(images)
        _replace_dir(tmp / "dataset", target)
        logger.info("%s: %d episodes, %d scripted episodes failed (configurations %s) -> %s", task,
                    cfg.num_episodes, len(failed), sorted(set(failed)), target)
        return target
    finally:
        env.close()
        if dataset is not None:
            with contextlib.suppress(Exception):
                dataset.finalize()
            del dataset
        shutil.rmtree(tmp, ignore_errors=True)


def record(cfg: MetaWorldRecordConfig) -> list[Path]:
    """Record every task in ``cfg.skills``; refuses up front if a target exists and not ``overwrite``, or, with
    ``overwrite``, if a target is not a dataset sr-record wrote
    (:func:`sr_imitation.recorders.needle.foreign_dataset_problem`: nothing is removed). ``cfg.root``'s lock is held
    throughout, taken before the targets are looked at."""
    with hold_folder(cfg.root, "sr-record"):
        remove_leftovers(cfg.root, cfg.root, STAGING_PATTERN, "sr-record")  # a killed earlier recording's
        return _record(cfg)


def _record(cfg: MetaWorldRecordConfig) -> list[Path]:
    """:func:`record` once ``cfg.root``'s lock is held."""
    for task in cfg.skills:
        target = cfg.target(task)
        if not (target.exists() or target.is_symlink()):
            continue
        if not cfg.overwrite:
            raise FileExistsError(f"{target}: the dataset already exists; pass --overwrite=true to replace it")
        problem = foreign_dataset_problem(target)
        if problem is not None:
            raise FileExistsError(f"{target}: --overwrite=true refused: {problem}; remove or move it yourself, or "
                                  "choose another root (nothing was removed)")
    with quiet_dataset_progress():
        return [record_task(cfg, task, zlib.crc32(task.encode()) % 100) for task in cfg.skills]


def main(args: list[str]) -> list[Path]:
    """``sr-record --env=metaworld ...`` (called by :func:`sr_imitation.recorders.cli.main`)."""
    cfg = parse_command(MetaWorldRecordConfig, args, prog="sr-record --env=metaworld")
    return record(cfg)


if __name__ == "__main__":
    main(sys.argv[1:])
