"""Skill datasets of a stream: loading, feature checks, the fixed stream statistics, splits and memory buffers.

A stream is a list of LeRobot datasets, one per skill (``<dataset_root>/<skill>`` by default, as ``sr-record``
writes them; or listed paths; or repo_ids resolved in the local Hugging Face cache as ``LeRobotDataset`` resolves
them, :func:`lerobot_cache_path`), so users can run it on their own recordings.

Statistics policy. LeRobot re-fits normalization statistics per dataset; a snapshot's outputs and the current
policy's would then live in different action spaces. ``--stream.stats`` says which statistics normalize the stream:
``seen`` (the default, our choice), the statistics of the skills seen so far (LeRobot's ``aggregate_stats`` of
datasets 1..k: count-weighted mean, pooled std), updated at the start of each skill's wake, saved with the run
(``stream_stats.safetensors`` for the first skill, ``skill_k_<name>/stream_stats.safetensors`` for each later one),
with the policy re-expressed so its actions do not change and the memories' targets re-expressed into the new action
space (:mod:`sr_imitation.substrates.act.normalization`) - what a continual learner may use; ``first``, the first
skill's dataset's for the whole stream (nothing from later skills is read, but a later skill's data may lie far outside
them); or ``union``, all the stream's datasets together, computed before the first skill (a fixed scaling shared by
every method; no later skill's data is trained on, but its range is read in advance, which a continual learner may
not do). Always with a floor on every standard deviation (``--stream.stats_min_std``) so that a nearly constant
dimension cannot blow up other skills' inputs. The statistics in use are written into every stage checkpoint's
processors. Why the needle presets fix ``union``: under the first skill's (approach) statistics, regrasp's goal
coordinates sit 30-55 standard deviations from the mean and the base learner reaches 0.33 on regrasp after its own
wake instead of 0.93 with regrasp's own statistics (docs/RESULTS.md, "Why the base learner failed").
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.datasets.dataset_metadata import LeRobotDatasetMetadata
from lerobot.datasets.factory import resolve_delta_timestamps
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE
from torch import Tensor

from lerobot_policy_act_sr.actor_memory import images_to_uint8
from sr_imitation.io import load_checked_safetensors, save_checked_safetensors
from sr_imitation.lerobot_compat import dataset_to_policy_features, lerobot_home
from sr_imitation.substrates.act.dataset_checks import DamagedDatasetError as DamagedDatasetError
from sr_imitation.substrates.act.dataset_checks import (
    DatasetMismatchError,
    check_data_files,
    dataset_info_path,
    read_meta_through,
)
from sr_imitation.substrates.act.dataset_checks import check_parquet_schema as check_parquet_schema
from sr_imitation.substrates.act.dataset_checks import read_video_through as read_video_through

logger = logging.getLogger(__name__)

STATS_KEYS = ("mean", "std", "min", "max")


def lerobot_cache_path(repo_id: str) -> Path:
    """Where ``LeRobotDataset(repo_id)`` without a ``root`` keeps the dataset: ``$HF_LEROBOT_HOME/<repo_id>``
    (default ``~/.cache/huggingface/lerobot/<repo_id>``), read from LeRobot's own constant at call time."""
    return lerobot_home() / repo_id


def cached_dataset_path(repo_id: str, key: str) -> Path:
    """:func:`lerobot_cache_path` of a dataset that must already be there (offline: nothing is downloaded);
    :class:`DatasetMismatchError` naming ``key``, the repo_id and the path looked at otherwise."""
    path = lerobot_cache_path(repo_id)
    if not dataset_info_path(path).is_file():
        raise DatasetMismatchError(
            f"{key}: {repo_id!r} is not in the local LeRobot cache (looked at {path}, no meta/info.json; nothing is "
            "downloaded: fetch it first, e.g. huggingface-cli download --repo-type dataset "
            f"{repo_id} --local-dir {path}, or set HF_LEROBOT_HOME)")
    return path


def load_metadata(root: Path, repo_id: str) -> LeRobotDatasetMetadata:
    """Load a local dataset's metadata, failing loudly (never reaching for the Hub).

    LeRobot falls back to downloading from the Hub when a local metadata file is missing, which turns a deleted
    file into a long traceback about the Hub; the files LeRobot v3 needs are checked first, and any other failure
    to read them is reported as one :class:`DatasetMismatchError` naming the dataset.
    """
    root = Path(root)
    if not dataset_info_path(root).is_file():
        raise DatasetMismatchError(f"{root}: not a LeRobot dataset (missing {dataset_info_path(root)})")
    missing = [name for name in ("meta/tasks.parquet",) if not (root / name).is_file()]
    if not any((root / "meta" / "episodes").glob("*/*.parquet")):
        missing.append("meta/episodes/*/*.parquet")
    if missing:
        raise DatasetMismatchError(f"{root}: incomplete LeRobot dataset, missing {', '.join(missing)}")
    key = (str(root.resolve()), repo_id, _meta_signature(root))
    meta = _METADATA_CACHE.get(key)
    if meta is None:
        read_meta_through(root)
        try:
            meta = LeRobotDatasetMetadata(repo_id, root=root)
        except Exception as exc:  # noqa: BLE001 - LeRobot raises anything from Arrow/JSON/Hub errors here
            raise DatasetMismatchError(
                f"{root}: cannot read the dataset metadata ({type(exc).__name__}: {exc})") from exc
        if meta.total_episodes == 0 or meta.total_frames == 0:
            raise DatasetMismatchError(f"{root}: dataset is empty ({meta.total_episodes} episodes)")
        if len(_METADATA_CACHE) >= 16:  # a stream's datasets, and a few more
            _METADATA_CACHE.pop(next(iter(_METADATA_CACHE)))
        _METADATA_CACHE[key] = meta
    return copy.deepcopy(meta)  # a caller may change its copy; the cached one stays as read


_METADATA_CACHE: dict[tuple[str, str, tuple[tuple[str, int, int, int, int], ...]], LeRobotDatasetMetadata] = {}
"""The metadata :func:`load_metadata` read last (our choice, for speed: a stream's start-up and each stage read the
same datasets' metadata several times, about 0.3 s a read through LeRobot's Arrow and ``datasets`` layers on a 2-core
CPU). Keyed by the dataset's path, repo_id and every ``meta/`` file's size, inode, modification and change time, so
a rewritten, replaced or touched metadata file is read again, through :func:`read_meta_through` first like any
read."""


def _meta_signature(root: Path) -> tuple[tuple[str, int, int, int, int], ...]:
    out = []
    for path in sorted((root / "meta").rglob("*")):
        if path.is_file():
            st = path.stat()
            out.append((str(path.relative_to(root)), st.st_size, st.st_ino, st.st_mtime_ns, st.st_ctime_ns))
    return tuple(out)


def check_stream_datasets(stream, use_images: bool) -> tuple[LeRobotDatasetMetadata, dict, dict]:
    """Open every dataset of a stream and match it to the policy, before anything is trained or written.

    The policy's features come from the first skill's dataset (:func:`policy_features`); every dataset must
    exist, be non-empty, have all its data/video files, provide those features with the same shapes, and share
    the first dataset's fps (the action chunk is defined in time steps). ``stream`` is a
    :class:`~sr_imitation.substrates.act.trainer.StreamConfig` (``skills``, ``dataset_path(i)``, ``repo_id(i)``).
    Returns the first dataset's metadata and the policy's input and output features.
    """
    metas = [load_metadata(stream.dataset_path(i), stream.repo_id(i)) for i in range(len(stream.skills))]
    inputs, outputs = policy_features(metas[0], use_images)
    for meta in metas:
        check_features(meta, inputs, outputs)
        if meta.fps != metas[0].fps:
            raise DatasetMismatchError(
                f"{dataset_info_path(meta.root)}: fps {meta.fps} differs from the first skill's {metas[0].fps}"
            )
        check_data_files(meta)
    return metas[0], inputs, outputs


def policy_features(meta: LeRobotDatasetMetadata, use_images: bool) -> tuple[dict, dict]:
    """Input and output features for the policy from the first skill's dataset.

    In state-only mode the cameras are dropped and the state is also declared as
    ``observation.environment_state`` (ACT needs an image or an environment state).
    """
    features = dataset_to_policy_features(meta.features)
    outputs = {k: f for k, f in features.items() if f.type is FeatureType.ACTION}
    inputs = {k: f for k, f in features.items() if f.type is not FeatureType.ACTION}
    if ACTION not in outputs:
        raise DatasetMismatchError(f"{dataset_info_path(meta.root)}: no '{ACTION}' feature")
    if OBS_STATE not in inputs:
        raise DatasetMismatchError(f"{dataset_info_path(meta.root)}: no '{OBS_STATE}' feature")
    if not use_images:
        inputs = {k: f for k, f in inputs.items() if f.type is not FeatureType.VISUAL}
        inputs[OBS_ENV_STATE] = PolicyFeature(type=FeatureType.ENV, shape=inputs[OBS_STATE].shape)
    elif not any(f.type is FeatureType.VISUAL for f in inputs.values()):
        raise DatasetMismatchError(
            f"{dataset_info_path(meta.root)}: no camera feature; use --policy.use_images=false for state-only ACT"
        )
    return inputs, outputs


def check_features(meta: LeRobotDatasetMetadata, input_features: dict, output_features: dict) -> None:
    """Every policy feature must exist in the dataset with the same shape (error names file and key)."""
    info = dataset_info_path(meta.root)
    available = dataset_to_policy_features(meta.features)
    for key, feature in {**input_features, **output_features}.items():
        if key == OBS_ENV_STATE and key not in available:
            key, feature = OBS_STATE, input_features[key]  # state-only mode: fed from the state
        if key not in available:
            raise DatasetMismatchError(f"{info}: missing feature '{key}' that the policy needs")
        if tuple(available[key].shape) != tuple(feature.shape):
            raise DatasetMismatchError(
                f"{info}: feature '{key}' has shape {tuple(available[key].shape)}, the policy expects "
                f"{tuple(feature.shape)}"
            )


STATS_SOURCES = ("seen", "first", "union")
"""Choices of ``--stream.stats`` (module docstring)."""


def stream_stats(metas: Sequence[LeRobotDatasetMetadata], input_features: dict, min_std: float = 1e-2) -> dict:
    """The fixed statistics of the stream: those of ``metas`` together (one dataset: its own), with
    ``std >= min_std`` (module docstring)."""
    from lerobot.datasets.compute_stats import aggregate_stats

    pooled = metas[0].stats if len(metas) == 1 else aggregate_stats([m.stats for m in metas])
    stats: dict[str, dict[str, Tensor]] = {}
    for key, values in pooled.items():
        if key not in input_features and key != ACTION:
            continue
        entry = {name: torch.as_tensor(np.asarray(values[name]), dtype=torch.float32) for name in STATS_KEYS}
        entry["std"] = entry["std"].clamp_min(min_std)
        stats[key] = entry
    if OBS_ENV_STATE in input_features and OBS_ENV_STATE not in stats:
        stats[OBS_ENV_STATE] = {k: v.clone() for k, v in stats[OBS_STATE].items()}
    return stats


def save_stats(path: Path, stats: dict) -> None:
    flat = {f"{key}/{name}": t for key, entry in stats.items() for name, t in entry.items()}
    save_checked_safetensors(path, flat, {"format": "sr_imitation.stream_stats", "format_version": 1})


def load_stats(path: Path) -> dict:
    flat, _ = load_checked_safetensors(path)
    stats: dict[str, dict[str, Tensor]] = {}
    for name, t in flat.items():
        key, stat = name.rsplit("/", 1)
        stats.setdefault(key, {})[stat] = t
    return stats


class InMemoryChunkDataset(torch.utils.data.Dataset):
    """A LeRobot dataset decoded once into tensors, serving ACT's items (state, images, action chunk + padding).

    ``LeRobotDataset.__getitem__`` queries Arrow for every frame and its action chunk (~4 ms per item here), which
    is most of a small ACT step on CPU. Skill datasets are small (a few thousand frames), so they are decoded
    once: states and actions as float32, images as uint8. Items equal ``LeRobotDataset`` items (tested): the
    action chunk of frame t is actions[t : t + chunk] within its episode, padded with the episode's last action
    and flagged in ``action_is_pad`` past the end. Video datasets keep LeRobot's decoder (not materialized).
    """

    def __init__(self, dataset: LeRobotDataset, keys: Sequence[str], chunk_size: int) -> None:
        columns = dataset.hf_dataset.select_columns([*keys, ACTION, "episode_index"])
        data = columns[:]
        self.keys = list(keys)
        self.tensors: dict[str, Tensor] = {}
        for key in keys:
            stacked = torch.stack(list(data[key]))
            self.tensors[key] = images_to_uint8(stacked) if key.startswith("observation.images") else stacked.float()
        actions = torch.stack(list(data[ACTION])).float()
        episodes = torch.as_tensor([int(e) for e in data["episode_index"]])
        n = len(episodes)
        # Last frame index of each frame's episode (frames are stored episode by episode).
        ends = torch.empty(n, dtype=torch.long)
        boundaries = torch.nonzero(episodes[1:] != episodes[:-1]).flatten().tolist() + [n - 1]
        start = 0
        for end in boundaries:
            ends[start : end + 1] = end
            start = end + 1
        offsets = torch.arange(chunk_size)
        raw = torch.arange(n)[:, None] + offsets[None, :]
        self.action_is_pad = raw > ends[:, None]
        self.chunk_index = torch.minimum(raw, ends[:, None])
        self.actions = actions

    def __len__(self) -> int:
        return len(self.actions)

    def __getitem__(self, i: int) -> dict[str, Tensor]:
        item = {k: (v[i].float() / 255.0 if v.dtype == torch.uint8 else v[i]) for k, v in self.tensors.items()}
        item[ACTION] = self.actions[self.chunk_index[i]]
        item["action_is_pad"] = self.action_is_pad[i]
        return item


@dataclass
class SkillData:
    """One skill's dataset with its episode split (frame indices into ``dataset``)."""

    skill: str
    root: Path
    dataset: torch.utils.data.Dataset
    train_indices: list[int]
    val_indices: list[int]


def episode_split(num_episodes: int, val_fraction: float, seed: int) -> tuple[list[int], list[int]]:
    """Random split of episode ids; at least one training episode, and one validation episode if possible."""
    order = np.random.default_rng(seed).permutation(num_episodes).tolist()
    n_val = min(max(1, round(val_fraction * num_episodes)), num_episodes - 1) if num_episodes > 1 else 0
    return sorted(order[n_val:]), sorted(order[:n_val])


def load_skill_data(
    skill: str,
    root: Path,
    repo_id: str,
    policy_cfg,
    val_fraction: float,
    seed: int,
    video_backend: str = "pyav",
    materialize: bool = True,
) -> SkillData:
    """Load a skill's dataset with ACT's action-chunk delta timestamps and split it by episode."""
    meta = load_metadata(root, repo_id)
    check_features(meta, policy_cfg.input_features, policy_cfg.output_features)
    delta = resolve_delta_timestamps(policy_cfg, meta)
    dataset = LeRobotDataset(repo_id, root=root, delta_timestamps=delta, video_backend=video_backend)
    if materialize and not meta.video_keys:
        keys = [k for k in policy_cfg.input_features if k in meta.features]
        dataset = InMemoryChunkDataset(dataset, keys, policy_cfg.chunk_size)
    train_eps, val_eps = episode_split(meta.total_episodes, val_fraction, seed)
    starts = meta.episodes["dataset_from_index"]
    ends = meta.episodes["dataset_to_index"]

    def frames(eps: Sequence[int]) -> list[int]:
        return [i for e in eps for i in range(int(starts[e]), int(ends[e]))]

    logger.info("skill %s: %d episodes (%d train / %d val), %d frames from %s", skill, meta.total_episodes,
                len(train_eps), len(val_eps), meta.total_frames, root)
    return SkillData(skill, Path(root), dataset, frames(train_eps), frames(val_eps))


def sample_observation_buffer(data: SkillData, size: int, keys: Sequence[str], seed: int) -> dict[str, Tensor]:
    """|B_k| unordered observations drawn uniformly without replacement (with replacement if too few frames).

    Images are stored as uint8; actions are never stored.
    """
    pool = data.train_indices + data.val_indices
    rng = np.random.default_rng(seed)
    picks = rng.choice(pool, size=size, replace=len(pool) < size)
    items = [data.dataset[int(i)] for i in picks]
    out: dict[str, Tensor] = {}
    for key in keys:
        stacked = torch.stack([item[key] for item in items])
        out[key] = images_to_uint8(stacked) if key.startswith("observation.images") else stacked.float()
    return out
