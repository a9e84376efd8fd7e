"""``sr-record``: record scripted-expert demos of the needle skills into LeRobot v3 datasets.

One dataset per skill at ``<root>/<skill>`` (features ``observation.images.wrist``, ``observation.state``,
``action``, plus ``next.reward``/``next.success``/``next.done``; task string = skill name), successful
episodes only. Each dataset is written to a hidden temporary directory next to the target and renamed into
place when complete, so an interrupted run never leaves a loadable half dataset at the target path.

Example::

    sr-record --skills=[approach,place] --num_episodes=100 --root=datasets/needle --image_size=96
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sr_imitation.envs.needle.env import ACTION_NAMES, STATE_DIM, STATE_NAMES, NeedleEnv
from sr_imitation.envs.needle.expert import ExpertSettings, NeedleExpert
from sr_imitation.envs.needle.skills import SKILL_NAMES, skill_from_name
from sr_imitation.infra.cli_errors import run_cli, setup_logging
from sr_imitation.infra.cli_parsing import parse_command
from sr_imitation.infra.folder_lock import MKDTEMP_SUFFIX, hold_folder, remove_leftovers
from sr_imitation.io import read_checked_json, write_checked_json
from sr_imitation.offscreen import setup_offscreen_rendering
from sr_imitation.progress import Progress

logger = logging.getLogger(__name__)

WRIST_KEY = "observation.images.wrist"
VIDEO_CODECS = ("h264", "hevc", "libsvtav1")


@dataclass
class RecordConfig:
    """Options of ``sr-record`` (one LeRobot dataset per skill at ``<root>/<skill>``)."""

    env: str = "needle"
    """Demonstration source: needle (this package's needle skills and scripted expert) or metaworld (Meta-World v3
    tasks by metaworld.policies' scripted policies, sr_imitation.recorders.metaworld: sr-record --env=metaworld --help
    lists its options)."""
    skills: list[str] = field(default_factory=lambda: list(SKILL_NAMES))
    """Skills to record, in stream order by default."""
    num_episodes: int = 100
    """Successful episodes per skill (failed expert episodes are discarded)."""
    root: Path = Path("datasets/needle")
    """Parent folder; each skill's dataset goes to <root>/<skill>."""
    repo_id_prefix: str = "local/sr_needle"
    """LeRobot repo_id of each dataset is <prefix>_<skill> (local only; nothing is pushed)."""
    image_size: int = 96
    """Wrist image height, and width unless image_width is set (96 is the CPU default)."""
    image_width: int | None = None
    """Wrist image width when not square, e.g. --image_size=480 --image_width=640 for the paper's 640x480."""
    video: bool = False
    """Store wrist images as mp4 (decode with video_backend=pyav) instead of PNG in parquet."""
    vcodec: str = "h264"
    """Video codec when video is true - h264, hevc or libsvtav1."""
    thresholds: str = "learnable"
    """Success-threshold preset of the expert's episodes - learnable or surgicai."""
    seed: int = 0
    """Base seed; episode k of skill i uses env seed seed * 1_000_000 + i * 10_000 + k."""
    fps: int = 30
    """Dataset frame rate."""
    overwrite: bool = False
    """Replace existing datasets at the targets, only datasets sr-record wrote (anything else is refused)."""
    episode_videos: bool = False
    """Also write one scene-camera mp4 per episode to <root>/<skill>_episode_videos."""
    max_failures: int = 50
    """Give up on a skill after this many failed expert episodes."""
    demo_threshold_scale: float = 1.0
    """A demo ends when the expert is inside this fraction of the success thresholds (position and rotation), not
    on their boundary. 1 reproduces SurgicAI's demos, which stop the step success is first reached; place and insert
    demos then end at a mean 9.7 deg rotation error against the 10 deg threshold, and a policy that imitates them
    stalls just outside (docs/RESULTS.md, "why the base learner failed"). Our choice; evaluation always uses the
    full thresholds."""
    expert_jaw_close_mm: float = 1.5
    """The expert starts closing the jaw (approach, regrasp) once its position error is below this many mm
    (SurgicAI's demos 1.5 mm, spec section 4.2). A policy closes about 1 mm early, and with the 2 mm regrasp
    threshold a demo that closes at 1.5 mm leaves it no room. Our choice."""

    def __post_init__(self) -> None:
        if self.env != "needle":
            raise ValueError(f"env must be needle or metaworld (give --env=metaworld as written), got {self.env!r}")
        if not self.skills:
            raise ValueError("skills must not be empty")
        self.skills = [skill_from_name(s).value for s in self.skills]
        if len(set(self.skills)) != len(self.skills):
            raise ValueError(f"skills must be distinct, got {self.skills}")
        if self.num_episodes < 1:
            raise ValueError(f"num_episodes must be >= 1, got {self.num_episodes}")
        if self.image_width is None:
            self.image_width = self.image_size
        for name in ("image_size", "image_width"):
            if not 8 <= getattr(self, name) <= 1280:
                raise ValueError(f"{name} must be in [8, 1280], got {getattr(self, name)}")
        if self.vcodec not in VIDEO_CODECS:
            raise ValueError(f"vcodec must be one of {VIDEO_CODECS}, got {self.vcodec!r}")
        if self.fps < 1:
            raise ValueError(f"fps must be >= 1, got {self.fps}")
        if self.max_failures < 0:
            raise ValueError(f"max_failures must be >= 0, got {self.max_failures}")
        if not 0.0 < self.demo_threshold_scale <= 1.0:
            raise ValueError(f"demo_threshold_scale must be in (0, 1], got {self.demo_threshold_scale}")
        if not 0.0 < self.expert_jaw_close_mm <= 10.0:
            raise ValueError(f"expert_jaw_close_mm must be in (0, 10], got {self.expert_jaw_close_mm}")
        self.root = Path(self.root)

    def target(self, skill: str) -> Path:
        return self.root / skill

    def episode_video_dir(self, skill: str) -> Path:
        return self.root / f"{skill}_episode_videos"


def dataset_features(image_height: int, image_width: int, video: bool) -> dict:
    """LeRobot feature spec of a needle dataset (integration notes §4)."""
    return {
        WRIST_KEY: {
            "dtype": "video" if video else "image",
            "shape": (image_height, image_width, 3),
            "names": ["height", "width", "channels"],
        },
        "observation.state": {"dtype": "float32", "shape": (STATE_DIM,), "names": list(STATE_NAMES)},
        "action": {"dtype": "float32", "shape": (7,), "names": list(ACTION_NAMES)},
        "next.reward": {"dtype": "float32", "shape": (1,), "names": None},
        "next.success": {"dtype": "bool", "shape": (1,), "names": None},
        "next.done": {"dtype": "bool", "shape": (1,), "names": None},
    }


RECORD_SETTINGS_FILE = "meta/sr_record.json"
"""Where a recorded dataset keeps the settings that decided its content (checksummed JSON)."""
CONTENT_SETTINGS = ("num_episodes", "image_size", "image_width", "video", "vcodec", "thresholds", "seed", "fps",
                    "demo_threshold_scale", "expert_jaw_close_mm")
"""RecordConfig fields that change what a dataset holds."""
LEGACY_SETTINGS = {"demo_threshold_scale": 1.0, "expert_jaw_close_mm": 1.5}
"""What a dataset recorded before RECORD_SETTINGS_FILE existed was recorded with."""


def content_settings(cfg: RecordConfig, skill: str) -> dict:
    return {"skill": skill, **{k: getattr(cfg, k) for k in CONTENT_SETTINGS}}


def check_recorded(cfg: RecordConfig, skills: list[str]) -> None:
    """Refuse, naming the file and keys, an existing dataset of ``skills`` recorded with other content settings
    than ``cfg``'s (a dataset from before the settings were stored is compared on :data:`LEGACY_SETTINGS`)."""
    for skill in skills:
        target = cfg.target(skill)
        if not target.exists():
            continue
        path = target / RECORD_SETTINGS_FILE
        stored = read_checked_json(path) if path.is_file() else LEGACY_SETTINGS
        wanted = content_settings(cfg, skill)
        diffs = [f"{k}={stored[k]!r} (config: {wanted[k]!r})" for k in stored if k in wanted and stored[k] != wanted[k]]
        if diffs:
            where = path if path.is_file() else f"{target} (recorded before {RECORD_SETTINGS_FILE} existed)"
            raise ValueError(f"{where}: recorded with {', '.join(diffs)}; re-record it (--record.overwrite=true with "
                             f"sr-main, --overwrite=true with sr-record) or choose another record.root")


def ensure_recorded(cfg: RecordConfig) -> None:
    """Make ``cfg.skills``' datasets available: refuse existing ones of other content settings (unless
    ``overwrite``, which records every skill again), record the missing ones."""
    if not cfg.overwrite:
        check_recorded(cfg, cfg.skills)
    missing = [s for s in cfg.skills if cfg.overwrite or not cfg.target(s).exists()]
    if missing:
        logger.info("recording demonstrations for %s into %s", missing, cfg.root)
        record(RecordConfig(**{**vars(cfg), "skills": missing}))
    else:
        logger.info("datasets for all skills exist in %s; not recording", cfg.root)


def episode_seed(base_seed: int, skill_index: int, attempt: int) -> int:
    return base_seed * 1_000_000 + skill_index * 10_000 + attempt


def run_demo(env: NeedleEnv, seed: int, scene_video: bool, expert: ExpertSettings | None = None
             ) -> tuple[list[dict], list[np.ndarray], bool]:
    """One expert episode; returns (frames for the dataset, scene-camera frames, success)."""
    obs, _ = env.reset(seed=seed)
    expert = NeedleExpert(env, seed=seed, settings=expert)
    expert.reset()
    frames: list[dict] = []
    scene: list[np.ndarray] = [env.render()] if scene_video else []
    while True:
        action = expert.act()
        next_obs, reward, terminated, truncated, info = env.step(action)
        frames.append(
            {
                WRIST_KEY: obs["pixels"],
                "observation.state": obs["agent_pos"],
                "action": action.astype(np.float32),
                "next.reward": np.array([reward], dtype=np.float32),
                "next.success": np.array([info["is_success"]], dtype=bool),
                "next.done": np.array([terminated or truncated], dtype=bool),
                "task": env.task,
            }
        )
        if scene_video:
            scene.append(env.render())
        obs = next_obs
        if terminated or truncated:
            return frames, scene, bool(info["is_success"])


@contextlib.contextmanager
def quiet_dataset_progress():
    """Hugging Face ``datasets``' per-episode ``Map:`` progress bars off while a recorder writes (one line per
    episode would flood the log; the recorder's own progress line says how far it is); restored afterwards. Also
    silenced: LeRobot 0.4.4's ``compute_stats`` warning "Converting input from bool to uint8" for the boolean
    ``next.success`` / ``next.done`` features (raised by its histogram of every recorded episode; it changes no
    number and says nothing a user can act on)."""
    import warnings

    from datasets.utils import logging as hf_logging

    was_enabled = hf_logging.is_progress_bar_enabled()
    hf_logging.disable_progress_bar()
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="Converting input from bool to", category=RuntimeWarning)
            yield
    finally:
        if was_enabled:
            hf_logging.enable_progress_bar()


def _replace_dir(src: Path, dst: Path) -> None:
    """Move the finished ``src`` to ``dst``; an existing ``dst`` is swapped out first, then deleted."""
    old = None
    if dst.exists():
        old = dst.with_name(f".{dst.name}.old-{os.getpid()}")
        dst.rename(old)
    src.rename(dst)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def _canonical_data_files(dataset_root: Path, key: str) -> None:
    """Give every data parquet file a fingerprint that is a function of ``key`` and the file's place.

    LeRobot writes each episode through ``datasets.Dataset``, whose fingerprint lands in the parquet schema's
    ``huggingface`` metadata; it hashes pickled transforms, so it changed from process to process and two
    recordings of the same demos differed in bytes, hence in their content digest (``inputs.datasets.<skill>``).
    The files are rewritten row group by row group with LeRobot's writer settings; only that value changes."""
    import hashlib
    import json

    import pyarrow.parquet as pq

    for path in sorted((dataset_root / "data").rglob("*.parquet")):
        source = pq.ParquetFile(path)
        schema = source.schema_arrow
        meta = dict(schema.metadata or {})
        if b"huggingface" not in meta:
            continue
        hf = json.loads(meta[b"huggingface"])
        rel = path.relative_to(dataset_root).as_posix()
        hf["fingerprint"] = hashlib.sha256(f"{key}:{rel}".encode()).hexdigest()[:16]
        meta[b"huggingface"] = json.dumps(hf).encode()
        schema = schema.with_metadata(meta)
        tmp = path.with_name(path.name + ".tmp")
        with pq.ParquetWriter(tmp, schema=schema, compression="snappy", use_dictionary=True) as writer:
            for i in range(source.num_row_groups):
                writer.write_table(source.read_row_group(i).replace_schema_metadata(meta))
        os.replace(tmp, path)


def _canonical_stats(dataset_root: Path) -> None:
    """Rewrite ``meta/stats.json`` with its features in ``meta/info.json``'s order.

    LeRobot aggregates the statistics over a ``set`` of feature names, so their order in the file (and its
    bytes) followed ``PYTHONHASHSEED``; LeRobot reads the file as a mapping, so the order is free to fix."""
    import json

    stats_path = dataset_root / "meta" / "stats.json"
    stats = json.loads(stats_path.read_text())
    order = list(json.loads((dataset_root / "meta" / "info.json").read_text())["features"])
    ordered = {k: stats[k] for k in order if k in stats} | {k: stats[k] for k in sorted(stats) if k not in order}
    stats_path.write_text(json.dumps(ordered, indent=4, ensure_ascii=False))


STAGING_PATTERN = r"\..+\.tmp-" + MKDTEMP_SUFFIX
"""The name of a dataset being recorded (``.<skill>.tmp-XXXXXXXX`` in the root, both recorders): one found while
``sr-record`` holds the root's lock was left by a killed recording, and is removed."""


def record_skill(cfg: RecordConfig, skill: str, skill_index: int) -> Path:
    """Record ``cfg.num_episodes`` successful demos of ``skill``; returns the dataset path.

    The dataset's bytes are a function of the recording settings (same settings, same files, whatever the
    process's hash seed), so its content digest identifies the demos."""
    from sr_imitation.lerobot_compat import create_dataset
    from sr_imitation.video import write_mp4

    target = cfg.target(skill)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{skill}.tmp-", dir=target.parent))
    env = NeedleEnv(
        skill=skill,
        thresholds=cfg.thresholds,
        obs_type="pixels_agent_pos",
        image_height=cfg.image_size,
        image_width=cfg.image_width,
        render_mode="rgb_array" if cfg.episode_videos else None,
        threshold_scale=cfg.demo_threshold_scale,
    )
    expert = ExpertSettings(jaw_close_cm=cfg.expert_jaw_close_mm / 10.0)
    dataset = None
    try:
        dataset = create_dataset(
            repo_id=f"{cfg.repo_id_prefix}_{skill}",
            fps=cfg.fps,
            features=dataset_features(cfg.image_size, cfg.image_width, cfg.video),
            root=tmp / "dataset",
            robot_type=ROBOT_TYPE,
            use_videos=cfg.video,
            vcodec=cfg.vcodec,
        )
        failures, attempt = 0, 0
        with Progress(cfg.num_episodes, f"record {skill}", logger, unit="ep") as bar:
            while bar.n < cfg.num_episodes:
                seed = episode_seed(cfg.seed, skill_index, attempt)
                attempt += 1
                frames, scene, success = run_demo(env, seed, cfg.episode_videos, expert)
                if not success:
                    failures += 1
                    logger.warning("%s: expert failed on seed %d (%d failures)", skill, seed, failures)
                    if failures > cfg.max_failures:
                        raise RuntimeError(f"{skill}: more than {cfg.max_failures} failed expert episodes")
                    continue
                for frame in frames:
                    dataset.add_frame(frame)
                dataset.save_episode()
                if cfg.episode_videos:
                    write_mp4(tmp / "episode_videos" / f"episode_{bar.n:06d}.mp4", scene, fps=cfg.fps)
                bar.update(1)
        dataset.finalize()
        dataset = None
        _canonical_stats(tmp / "dataset")
        _canonical_data_files(tmp / "dataset", f"sr-record:{cfg.seed}:{skill}")
        write_checked_json(tmp / "dataset" / RECORD_SETTINGS_FILE, content_settings(cfg, skill))
        images = tmp / "dataset" / "images"
        if images.is_dir() and not any(p.is_file() for p in images.rglob("*")):
            shutil.rmtree(images)  # LeRobot's PNG staging folder, empty once episodes are embedded
        _replace_dir(tmp / "dataset", target)
        if cfg.episode_videos:
            _replace_dir(tmp / "episode_videos", cfg.episode_video_dir(skill))
        logger.info("%s: %d episodes (%d expert failures) -> %s", skill, cfg.num_episodes, failures, target)
        return target
    finally:
        env.close()
        if dataset is not None:  # interrupted: close LeRobot's parquet writers before deleting their files
            with contextlib.suppress(Exception):
                dataset.finalize()
            del dataset
        shutil.rmtree(tmp, ignore_errors=True)


DATASET_ENTRIES = ("meta", "data", "videos", "images")
"""What a LeRobot dataset holds at its top level (``images/``: LeRobot's PNG staging folder)."""
ROBOT_TYPE = "sr_needle_psm"
"""The ``robot_type`` this program records (``meta/info.json``)."""


def foreign_dataset_problem(target: Path) -> str | None:
    """Why ``--overwrite`` may not replace ``target`` (``None`` if it may): it is not a LeRobot dataset recorded by
    this program (``meta/sr_record.json``, or ``robot_type`` :data:`ROBOT_TYPE` in ``meta/info.json`` for datasets
    recorded before that file existed), or it holds anything besides a dataset's folders. An empty folder may go."""
    if not target.is_dir() or target.is_symlink():
        return "it is not a folder"
    if not any(target.iterdir()):
        return None
    info = target / "meta" / "info.json"
    if not info.is_file():
        return f"it is not a LeRobot dataset (no {info.relative_to(target)})"
    if not (target / RECORD_SETTINGS_FILE).is_file():
        try:
            robot = json.loads(info.read_text()).get("robot_type")
        except (OSError, ValueError, AttributeError):
            robot = None
        if robot != ROBOT_TYPE:
            return f"it is a dataset sr-record did not record (robot_type {robot!r}, no {RECORD_SETTINGS_FILE})"
    foreign = sorted(p.name for p in target.iterdir() if p.name not in DATASET_ENTRIES)
    if foreign:
        return f"it holds {', '.join(foreign[:3])}, which no dataset holds"
    return None


def check_overwrite(cfg: RecordConfig) -> None:
    """Before anything is recorded: every target ``--overwrite`` would replace is a dataset of ours, every episode
    video folder holds only episode videos; ``FileExistsError`` naming the first other one (nothing is removed)."""
    for skill in cfg.skills:
        target = cfg.target(skill)
        if target.exists() or target.is_symlink():
            problem = foreign_dataset_problem(target)
            if problem is not None:
                raise FileExistsError(f"{target}: --overwrite=true refused: {problem}; remove or move it yourself, "
                                      "or choose another root (nothing was removed)")
        videos = cfg.episode_video_dir(skill)
        if cfg.episode_videos and (videos.exists() or videos.is_symlink()):
            other = [p.name for p in videos.iterdir()] if videos.is_dir() and not videos.is_symlink() else ["?"]
            other = [n for n in other if not (n.startswith("episode_") and n.endswith(".mp4"))]
            if other:
                raise FileExistsError(f"{videos}: --overwrite=true refused: it holds {', '.join(sorted(other)[:3])}, "
                                      "which are not episode videos; remove or move it yourself (nothing was removed)")


def record(cfg: RecordConfig) -> list[Path]:
    """Record every skill in ``cfg.skills`` as the only writer of ``cfg.root`` (its lock held throughout, taken before
    the targets are looked at); refuses up front if a target exists and not ``overwrite``, or, with ``overwrite``, if
    a target is not a dataset of ours (:func:`check_overwrite`)."""
    with hold_folder(cfg.root, "sr-record"):
        remove_leftovers(cfg.root, cfg.root, STAGING_PATTERN, "sr-record")  # a killed earlier recording's
        if not cfg.overwrite:
            existing = [str(cfg.target(s)) for s in cfg.skills if cfg.target(s).exists()]
            if existing:
                raise FileExistsError(
                    f"Dataset(s) already exist: {existing}; pass --overwrite=true to replace them"
                )
        else:
            check_overwrite(cfg)
        with quiet_dataset_progress():
            return [record_skill(cfg, skill, SKILL_NAMES.index(skill)) for skill in cfg.skills]


def report_recorded(record_datasets: Callable[[], list[Path]]) -> None:
    """Run a recorder for ``sr-record`` (offscreen rendering and logging set up first): an existing target is one
    line, every dataset written is printed, and for video datasets the command that shows one
    (:mod:`sr_imitation.recorders.viz`)."""
    setup_offscreen_rendering()
    setup_logging()
    try:
        paths = record_datasets()
    except FileExistsError as e:
        raise SystemExit(f"sr-record: {e}") from None
    for path in paths:
        print(f"wrote {path.resolve()}")  # noqa: T201  (the CLI reports where the data went)
    videos = [path for path in paths if (path / "videos").is_dir()]
    if videos:
        from sr_imitation.recorders.viz import view_hint  # noqa: PLC0415

        print(view_hint(videos[0].name, str(videos[0])))  # noqa: T201


def main(args: list[str] | None = None) -> None:
    """Console entry point ``sr-record`` (draccus flags, LeRobot style)."""
    setup_offscreen_rendering()
    cfg = parse_command(RecordConfig, sys.argv[1:] if args is None else args, prog="sr-record")
    report_recorded(lambda: record(cfg))


def entry() -> None:
    """Console script ``sr-record``: :func:`main` with one-line user errors."""
    run_cli("sr-record", main)


if __name__ == "__main__":
    entry()
