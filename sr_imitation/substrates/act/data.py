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
import json
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.datasets.dataset_metadata import LeRobotDatasetMetadata
from lerobot.datasets.factory import resolve_delta_timestamps
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE
from torch import Tensor

from lerobot_policy_act_sr.actor_memory import images_to_uint8
from sr_imitation.io import CorruptFileError, load_checked_safetensors, save_checked_safetensors
from sr_imitation.lerobot_compat import dataset_to_policy_features, lerobot_home

logger = logging.getLogger(__name__)

STATS_KEYS = ("mean", "std", "min", "max")


class DatasetMismatchError(ValueError):
    """A stream dataset is missing, empty, or its features do not match the policy."""


class DamagedDatasetError(DatasetMismatchError, CorruptFileError):
    """A dataset file that does not read through (truncated, damaged, a NaN in an observation or action): one line
    naming the file. Also a :class:`~sr_imitation.io.CorruptFileError`, so that the command line prints this line
    and not the Arrow, JSON or FFmpeg error it was raised from, which names no file
    (:mod:`sr_imitation.infra.cli_errors`)."""

    def __init__(self, path: str | Path, problem: str) -> None:
        CorruptFileError.__init__(self, path, problem)


def dataset_info_path(root: Path) -> Path:
    return Path(root) / "meta" / "info.json"


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


DAMAGED_ADVICE = "the dataset is damaged: record or copy it again"
"""The end of every message about a damaged dataset file."""


def read_meta_through(root: Path) -> None:
    """Parse every ``meta/*.json`` file and read every ``meta/**/*.parquet`` file (tasks, episodes) of the dataset at
    ``root`` through (:func:`read_through`): a truncated or damaged metadata file is one :class:`DamagedDatasetError`
    naming it, instead of LeRobot's message that names neither the file nor the dataset ("Unterminated string",
    "Parquet magic bytes not found in footer")."""
    meta_dir = Path(root) / "meta"
    for path in sorted(meta_dir.glob("*.json")):
        try:
            json.loads(path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, ValueError) as exc:
            raise DamagedDatasetError(path, f"unreadable JSON file ({type(exc).__name__}: {exc}); "
                                            f"{DAMAGED_ADVICE}") from exc
    for path in sorted(meta_dir.rglob("*.parquet")):
        read_through(path)


def finite_columns(meta: LeRobotDatasetMetadata) -> list[str]:
    """The numeric observation and action columns of a dataset (``action``, ``observation.*`` with a float dtype):
    those a NaN or an infinity in would reach the policy (other columns, a reward or a user's own, are not read by
    it and are not checked)."""
    return [key for key, feature in meta.features.items()
            if (key == ACTION or key.startswith("observation."))
            and str(feature.get("dtype", "")).startswith("float")]


def check_data_files(meta: LeRobotDatasetMetadata) -> None:
    """Every data (parquet) and video file the episodes reference exists, is non-empty and reads through: every
    parquet page decoded, with no NaN or infinity in an observation or action (:func:`read_through`), and every
    frame of every video decoded, covering every frame its episodes use (:func:`read_video_through`). A corrupt or
    truncated file is one :class:`DatasetMismatchError` naming it (and the episode, frame and column where it
    applies), before the first gradient and before an earlier run is replaced (``--overwrite``), instead of a
    traceback when its skill's stage begins. Every data file's columns must be those ``meta/info.json`` declares,
    with its shapes and dtypes (:func:`check_parquet_schema`), before any is read through; the videos are read
    whether or not the policy uses images, since LeRobot decodes them for every item either way."""
    data = {meta.get_data_file_path(e) for e in range(meta.total_episodes)}
    videos: dict[Path, list[tuple[int, float, int]]] = {}  # file -> (episode, its start in s, its frames)
    ends, begins = meta.episodes["dataset_to_index"], meta.episodes["dataset_from_index"]
    for key in meta.video_keys:
        starts = meta.episodes[f"videos/{key}/from_timestamp"]
        for e in range(meta.total_episodes):
            videos.setdefault(meta.get_video_file_path(e, key), []).append(
                (e, float(starts[e]), int(ends[e]) - int(begins[e])))
    paths = data | set(videos)
    missing = sorted(str(p) for p in paths if not (meta.root / p).is_file() or (meta.root / p).stat().st_size == 0)
    if missing:
        raise DatasetMismatchError(f"{meta.root}: missing or empty data files {missing}")
    for path in sorted(data):
        check_parquet_schema(meta.root / path, dataset_info_path(meta.root), meta.features)
    columns = finite_columns(meta)
    frames = sum(read_through(meta.root / p, columns) for p in sorted(data))
    if frames != meta.total_frames:
        raise DatasetMismatchError(f"{dataset_info_path(meta.root)}: declares {meta.total_frames} frames, its data "
                                   f"files hold {frames}")
    for path in sorted(videos):
        read_video_through(meta.root / path, videos[path], meta.fps)


def check_parquet_schema(path: Path, info: Path, features: dict[str, dict]) -> None:
    """The data file ``path`` holds exactly the columns ``info`` (the dataset's ``meta/info.json``) declares, other
    than its videos, each with the declared shape (every list length, fixed or not) and dtype. Reads the file's
    schema (its footer), and only for a column stored as lists of varying length, that column's lengths.

    Args:
        path: a parquet data file of the dataset.
        info: the dataset's ``meta/info.json`` (for the message).
        features: its ``features`` (name -> ``dtype``, ``shape``).

    Raises:
        DatasetMismatchError: one line naming the file, ``info`` and the first column that disagrees (a parquet
            that does not even open: :class:`DamagedDatasetError`).
    """
    import pyarrow.parquet as pq

    try:
        schema = pq.read_schema(path)
    except Exception as exc:  # noqa: BLE001 - Arrow raises OSError, ArrowInvalid and others for a damaged file
        first = str(exc).splitlines()[0] if str(exc) else ""
        raise DamagedDatasetError(path, f"unreadable parquet file ({type(exc).__name__}: {first}); "
                                        f"{DAMAGED_ADVICE}") from exc
    declared = {name: feature for name, feature in features.items() if feature.get("dtype") != "video"}
    problem = _columns_problem(list(schema.names), list(declared))
    for name in declared:
        if problem is None:
            problem = _column_problem(path, name, schema.field(name).type, declared[name])
    if problem is not None:
        raise DatasetMismatchError(f"{path}: disagrees with {info}: {problem}; record or copy the dataset again")


def _columns_problem(held: list[str], declared: list[str]) -> str | None:
    """Which declared column the file lacks, or which column it holds that is not declared, in words; ``None``."""
    missing = [name for name in declared if name not in held]
    if missing:
        return f"the file lacks declared column(s) {missing}"
    extra = [name for name in held if name not in declared]
    return f"the file holds undeclared column(s) {extra}" if extra else None


def _column_problem(path: Path, name: str, arrow_type: Any, feature: dict) -> str | None:
    """How the column ``name`` of type ``arrow_type`` disagrees with its declared ``feature``, in words; ``None``."""
    import pyarrow as pa

    dtype, shape = str(feature.get("dtype")), tuple(int(n) for n in feature.get("shape") or ())
    if dtype == "image":
        return None if pa.types.is_struct(arrow_type) or pa.types.is_binary(arrow_type) else \
            f"column {name!r} holds {arrow_type}, declared images"
    if isinstance(arrow_type, pa.ExtensionType):  # datasets' ArrayND columns
        arrow_type = arrow_type.storage_type
    lengths, leaf = [], arrow_type
    while pa.types.is_list(leaf) or pa.types.is_large_list(leaf) or pa.types.is_fixed_size_list(leaf):
        lengths.append(leaf.list_size if pa.types.is_fixed_size_list(leaf) else None)
        leaf = leaf.value_type
    wanted = () if shape == (1,) else shape
    if len(lengths) != len(wanted) or any(n is not None and n != w for n, w in zip(lengths, wanted, strict=True)):
        held = "".join(f"{'?' if n is None else n}," for n in lengths)
        return f"column {name!r} has shape ({held}), declared {shape}"
    if None in lengths:
        varying = _varying_length(path, name, wanted)
        if varying is not None:
            return f"column {name!r} {varying}, declared shape {shape}"
    return _dtype_problem(name, leaf, dtype)


def _dtype_problem(name: str, leaf: Any, dtype: str) -> str | None:
    """How the values' Arrow type ``leaf`` disagrees with the declared ``dtype``, in words; ``None`` (also for a
    dtype Arrow has no name for)."""
    import pyarrow as pa

    try:
        wanted = pa.type_for_alias(dtype)
    except ValueError:
        return None
    if leaf == wanted or (pa.types.is_string(wanted) and pa.types.is_large_string(leaf)):
        return None
    return f"column {name!r} holds {leaf} values, declared {dtype}"


def _varying_length(path: Path, name: str, wanted: tuple[int, ...]) -> str | None:
    """For a column of ``path`` stored as lists of varying length: the first row whose list lengths are not
    ``wanted``, in words (``has 6 values in row 3``); ``None`` if every row has the declared shape."""
    import pyarrow.compute as pc
    import pyarrow.parquet as pq

    values = pq.read_table(path, columns=[name]).column(name).combine_chunks()
    for depth, size in enumerate(wanted):
        counts = np.asarray(pc.list_value_length(values).fill_null(0))
        bad = np.flatnonzero(counts != size)
        if len(bad):
            where = f"row {bad[0]}" if depth == 0 else f"a list {depth} deep, element {bad[0]}"
            return f"has {int(counts[bad[0]])} values in {where}"
        values = pc.list_flatten(values)
    return None


def read_through(path: Path, finite: Sequence[str] = ()) -> int:
    """Decode every column of the parquet file ``path`` once (every page decompressed and decoded, so flipped bytes
    in compressed data and a truncated file are found); returns its number of rows. :class:`DamagedDatasetError`
    naming the file if it does not read, or if a column of ``finite`` holds a NaN or an infinity (naming the
    column, the episode and the frame: :func:`check_finite`)."""
    import pyarrow.parquet as pq

    rows = 0
    try:
        with pq.ParquetFile(path) as reader:
            for batch in reader.iter_batches():
                check_finite(path, batch, finite, rows)
                rows += batch.num_rows
    except DamagedDatasetError:
        raise
    except Exception as exc:  # noqa: BLE001 - Arrow raises OSError, ArrowInvalid and others for a damaged file
        first = str(exc).splitlines()[0] if str(exc) else ""
        raise DamagedDatasetError(path, f"unreadable parquet file ({type(exc).__name__}: {first}); "
                                        f"{DAMAGED_ADVICE}") from exc
    return rows


def check_finite(path: Path, batch: Any, columns: Sequence[str], first_row: int = 0) -> None:
    """:class:`DamagedDatasetError` naming ``path``, the column (and the element of a vector), the episode and the
    frame of the first NaN or infinity in ``columns`` of the Arrow record ``batch`` (rows ``first_row...`` of the
    file); columns the batch lacks or that hold no floats are skipped."""
    for name in columns:
        if name not in batch.schema.names:
            continue
        found = first_non_finite(batch.column(name))
        if found is None:
            continue
        row, element, value = found
        where = f"{name}[{element}]" if element is not None else name
        episode = _cell(batch, "episode_index", row)
        frame = _cell(batch, "frame_index", row)
        raise DamagedDatasetError(path, f"{value} in column {where!r} at episode {episode}, frame {frame} (row "
                                        f"{first_row + row} of the file); a non-finite observation or action makes "
                                        "the losses NaN: fix or record the dataset again")


def _cell(batch: Any, name: str, row: int) -> Any:
    return batch.column(name)[row].as_py() if name in batch.schema.names else "?"


def first_non_finite(column: Any) -> tuple[int, int | None, float] | None:
    """``(row, element, value)`` of the first NaN or infinity in an Arrow float column (``element``: the index
    into the flattened vector of that row, ``None`` for a scalar column), or ``None``; a null counts as NaN. A column
    of lists is flattened, keeping each value's row."""
    import pyarrow as pa
    import pyarrow.compute as pc

    values, rows = column, None
    while pa.types.is_list(values.type) or pa.types.is_large_list(values.type) or \
            pa.types.is_fixed_size_list(values.type):
        parents = np.asarray(pc.list_parent_indices(values))
        values = pc.list_flatten(values)
        rows = parents if rows is None else rows[parents]
    if not pa.types.is_floating(values.type):
        return None
    array = values.to_numpy(zero_copy_only=False)
    bad = np.flatnonzero(~np.isfinite(array))
    if len(bad) == 0:
        return None
    i = int(bad[0])
    if rows is None:
        return i, None, float(array[i])
    row = int(rows[i])
    return row, i - int(np.searchsorted(rows, row)), float(array[i])


def read_video_through(path: Path, episodes: Sequence[tuple[int, float, int]] = (), fps: float = 0.0,
                       tolerance_s: float = 1e-4) -> int:
    """Decode every frame of the video file ``path`` once (with PyAV: torchcodec does not load everywhere), and check
    that it holds every frame its ``episodes`` use: ``(episode index, its start in the video in s, its number of
    frames)``, frame i at ``start + i / fps`` within ``tolerance_s`` (LeRobot's default tolerance, what it asks the
    decoder for). Returns the number of frames. :class:`DamagedDatasetError` naming the file if it does not decode
    (with the first episode and frame it lacks), holds no video, or lacks a frame: a truncated video (LeRobot writes
    its index at the front) opens and demultiplexes, and LeRobot fails with a traceback when an item past the cut
    is drawn."""
    import av

    times: list[float] = []
    error: Exception | None = None
    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                raise DamagedDatasetError(path, f"holds no video stream; {DAMAGED_ADVICE}")
            stream = container.streams.video[0]
            stream.thread_type = "AUTO"
            for frame in container.decode(stream):
                if frame.time is not None:
                    times.append(float(frame.time))
    except DamagedDatasetError:
        raise
    except Exception as exc:  # noqa: BLE001 - PyAV raises its own error classes per FFmpeg error code
        error = exc
    lacking = missing_frame(np.sort(np.asarray(times)), episodes, fps, tolerance_s)
    if error is not None:
        first = str(error).splitlines()[0] if str(error) else ""
        raise DamagedDatasetError(path, f"unreadable video file ({type(error).__name__}: {first}) after "
                                        f"{len(times)} frames{f': {lacking}' if lacking else ''}; "
                                        f"{DAMAGED_ADVICE}") from error
    if not times:
        raise DamagedDatasetError(path, f"the video holds no frames; {DAMAGED_ADVICE}")
    if lacking:
        raise DamagedDatasetError(path, f"{lacking} (truncated or damaged); {DAMAGED_ADVICE}")
    return len(times)


def missing_frame(times: np.ndarray, episodes: Sequence[tuple[int, float, int]], fps: float, tolerance_s: float
                  ) -> str | None:
    """Which frame of ``episodes`` (:func:`read_video_through`) comes first that no decoded frame time of ``times``
    (sorted) lies within ``tolerance_s`` of, in words (its episode, frame and time, and what the video holds); ``None``
    if every frame is there."""
    for episode, start, length in episodes:
        wanted = start + np.arange(length) / fps
        if len(times) == 0:
            missing = np.arange(length)
        else:
            right = np.clip(np.searchsorted(times, wanted), 0, len(times) - 1)
            left = np.clip(right - 1, 0, len(times) - 1)
            distance = np.minimum(np.abs(times[right] - wanted), np.abs(times[left] - wanted))
            missing = np.flatnonzero(distance >= tolerance_s)
        if len(missing):
            i = int(missing[0])
            held = f"from {times[0]:.3f} to {times[-1]:.3f} s" if len(times) else "none"
            return (f"episode {episode}, frame {i} (at {wanted[i]:.3f} s) is not in the video, which decodes "
                    f"{len(times)} frames ({held})")
    return None


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
