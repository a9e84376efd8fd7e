"""A dataset's data agrees with its own ``meta/info.json`` before the first gradient (issue 87 item 3): a parquet
data file whose columns, list lengths or dtypes are not those info.json declares is refused at start-up and on
resume, in one line naming the file and the info.json, before any stage folder exists.

Before: the action column one shorter (info.json untouched) trained stage 1, was evaluated, wrote 18 files, then
failed with a 115-line ``DatasetGenerationError`` naming no dataset."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

import sr_imitation.substrates.act.cli as cli
import sr_imitation.substrates.act.trainer as trainer
from sr_imitation.infra.cli_errors import run_cli
from sr_imitation.substrates.act.config import stored_config_dict
from sr_imitation.substrates.act.data import DatasetMismatchError, check_parquet_schema
from sr_imitation.substrates.act.trainer import ACTTrainer, train_stream
from tests.act_helpers import fake_env_factory, make_skill_dataset, tiny_stream_config

SKILLS = ["approach", "place"]


@pytest.fixture(scope="module")
def datasets(tmp_path_factory) -> Path:
    """Two tiny state-only skill datasets (made once for this file)."""
    os.environ.setdefault("HF_HOME", str(tmp_path_factory.mktemp("hf_home")))
    root = tmp_path_factory.mktemp("schema") / "data"
    for i, skill in enumerate(SKILLS):
        make_skill_dataset(root, skill, i, image=False)
    return root


def _data_file(root: Path, skill: str) -> Path:
    return next((root / skill / "data").rglob("*.parquet"))


def rewrite_column(path: Path, name: str, change) -> None:
    """Rewrite the parquet file ``path`` with its column ``name`` replaced by ``change(column)`` (an Arrow array)."""
    table = pq.read_table(path)
    i = table.schema.get_field_index(name)
    table = table.set_column(i, name, change(table.column(name).combine_chunks()))
    pq.write_table(table.replace_schema_metadata(None), path)


def one_shorter_fixed(column):
    values = np.asarray(column.flatten()).reshape(len(column), -1)[:, :-1]
    return pa.FixedSizeListArray.from_arrays(pa.array(values.ravel(), pa.float32()), values.shape[1])


def one_shorter_in_row_3(column):
    rows = [list(r) for r in column.to_pylist()]
    rows[3] = rows[3][:-1]
    return pa.array(rows, pa.list_(pa.float32()))


def as_float64(column):
    return pa.array(column.to_pylist(), pa.list_(pa.float64(), column.type.list_size))


def _config(root: Path, out: Path, tmp: Path) -> Path:
    path = tmp / "train_config.json"
    path.write_text(json.dumps(stored_config_dict(tiny_stream_config(root, out, SKILLS, use_images=False))))
    return path


def _one_line_error(args: list[str], capsys) -> str:
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        run_cli("sr-train", cli.train_main, args)
    err = capsys.readouterr().err
    assert exc.value.code == 2 and err.count("\n") == 1 and err.startswith("sr-train: error: "), err
    return err


@pytest.mark.parametrize("change, problem", [
    (one_shorter_fixed, "column 'action' has shape (6,), declared (7,)"),
    (one_shorter_in_row_3, "column 'action' has 6 values in row 3, declared shape (7,)"),
    (as_float64, "column 'action' holds double values, declared float32"),
])
def test_a_parquet_that_disagrees_with_its_info_json_is_refused_before_any_stage(datasets, tmp_path, monkeypatch,
                                                                                 capsys, change, problem):
    root = tmp_path / "data"
    shutil.copytree(datasets, root)
    parquet = _data_file(root, "place")  # the second skill's: every skill's files are checked, not the first only
    rewrite_column(parquet, "action", change)
    monkeypatch.setattr(cli, "train_stream", lambda cfg: train_stream(cfg, fake_env_factory))
    monkeypatch.setattr("sr_imitation.substrates.act.substrate.wake_train", lambda *a, **k: pytest.fail("trained"))
    out = tmp_path / "run"
    err = _one_line_error([f"--config_path={_config(root, out, tmp_path)}", f"--output_dir={out}"], capsys)
    info = root / "place" / "meta" / "info.json"
    assert f"{parquet}: disagrees with {info}: {problem}" in err
    assert not out.exists()  # no stage folder, nothing at all


def test_on_resume_too(datasets, tmp_path, monkeypatch, capsys):
    """A run stopped after stage 1 whose next skill's data file changed so that its content digest still matches
    (as an in-place edit with the size and mtime restored does under the digest cache: simulated here) is refused
    by the schema check before stage 2's folder exists."""
    root = tmp_path / "data"
    shutil.copytree(datasets, root)
    out = tmp_path / "run"
    ACTTrainer(tiny_stream_config(root, out, SKILLS, use_images=False), fake_env_factory).run(stop_after=1)
    digests = trainer.stream_inputs(tiny_stream_config(root, out, SKILLS, use_images=False))
    rewrite_column(_data_file(root, "place"), "action", one_shorter_fixed)
    monkeypatch.setattr(trainer, "stream_inputs", lambda cfg: digests)  # the digests a stale cache would give
    monkeypatch.setattr(cli, "train_stream", lambda cfg: train_stream(cfg, fake_env_factory))
    before = sorted(str(p.relative_to(out)) for p in out.rglob("*"))
    err = _one_line_error([f"--config_path={out / 'train_config.json'}", "--resume=true",
                           f"--stream.dataset_root={root}"], capsys)
    assert f"{_data_file(root, 'place')}: disagrees with {root / 'place' / 'meta' / 'info.json'}" in err
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*")) == before
    assert not any(p.name.startswith("skill_2") for p in out.iterdir())


def test_columns_lacking_or_undeclared_are_named(datasets, tmp_path):
    parquet = tmp_path / "file.parquet"
    shutil.copy(_data_file(datasets, "approach"), parquet)
    features = json.loads((datasets / "approach" / "meta" / "info.json").read_text())["features"]
    check_parquet_schema(parquet, Path("info.json"), features)  # as recorded: agrees
    with pytest.raises(DatasetMismatchError, match=r"the file holds undeclared column\(s\) \['action'\]"):
        check_parquet_schema(parquet, Path("info.json"), {k: v for k, v in features.items() if k != "action"})
    with pytest.raises(DatasetMismatchError, match=r"the file lacks declared column\(s\) \['reward'\]"):
        check_parquet_schema(parquet, Path("info.json"), {**features, "reward": {"dtype": "float32", "shape": [1]}})
    video = {**features, "observation.images.top": {"dtype": "video", "shape": [16, 16, 3]}}
    check_parquet_schema(parquet, Path("info.json"), video)  # videos live outside the parquet
