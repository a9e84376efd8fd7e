"""A stream dataset's files read through before training, so that a missing, damaged or mismatching file is one line
naming it (metadata, parquet pages and schema, non-finite values, video frames)."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from lerobot.datasets.dataset_metadata import LeRobotDatasetMetadata
from lerobot.utils.constants import ACTION

from sr_imitation.io import CorruptFileError


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
