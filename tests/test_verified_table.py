"""docs/COMMANDS.md's "What is verified" table says what is checked and what is not (issue 87 item 6); each row's
claim, the weak spots included, is checked here, and a row added without a test here fails."""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from sr_imitation.infra.folder_lock import FolderBusyError, hold_folder
from sr_imitation.io import CorruptFileError, read_checked_json, staged_directory, verify_checkpoint, write_checked_json
from sr_imitation.substrates.act.dataset_identity import dataset_inputs
from tests.act_helpers import make_skill_dataset

DOC = Path(__file__).resolve().parents[1] / "docs" / "COMMANDS.md"
ROWS = {
    "datasets by content digest": "test_a_changed_dataset_changes_its_digest",
    "the digest cache": "test_the_digest_cache_misses_an_in_place_edit_with_the_mtime_restored_unless_switched_off",
    "data against metadata": "test_a_parquet_that_disagrees_with_its_info_json_is_refused",
    "checkpoints by `checksums.json`": "test_a_sealed_checkpoint_is_verified_and_a_copied_one_is_named_unverified",
    "results by seals": "test_an_edited_sealed_file_is_refused",
    "run folders by lock": "test_a_second_writer_is_refused",
    "values by type": "test_a_boolean_for_a_number_is_refused",
    "leftovers of a killed command": "test_leftovers_are_removed_by_the_next_run",
}
"""Each row of the table (its first cell) and the test here that checks its claim."""


def table_rows() -> list[str]:
    """The first cells of the "What is verified" table."""
    text = DOC.read_text().split("## What is verified", 1)[1].split("\n## ", 1)[0]
    return [line.split("|")[1].strip() for line in text.splitlines()
            if line.startswith("| ") and not line.startswith(("| what", "| ---"))]


def test_every_row_has_its_test_and_the_readme_points_at_the_table():
    assert table_rows() == list(ROWS)
    for test in ROWS.values():
        assert callable(globals().get(test)), test
    assert "docs/COMMANDS.md" in (DOC.parents[1] / "README.md").read_text()


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    os.environ.setdefault("HF_HOME", str(tmp_path_factory.mktemp("hf_home")))
    return make_skill_dataset(tmp_path_factory.mktemp("verified"), "approach", 0, image=False)


def _copy(dataset: Path, tmp_path: Path) -> Path:
    copy = tmp_path / "approach"
    shutil.copytree(dataset, copy)
    return copy


def test_a_changed_dataset_changes_its_digest(dataset, tmp_path, monkeypatch):
    monkeypatch.setenv("SR_DIGEST_CACHE", str(tmp_path / "cache.json"))
    copy = _copy(dataset, tmp_path)
    before = dataset_inputs(["approach"], [copy])
    (copy / "meta" / "info.json").write_text((copy / "meta" / "info.json").read_text() + " ")
    assert dataset_inputs(["approach"], [copy]) != before


def test_the_digest_cache_misses_an_in_place_edit_with_the_mtime_restored_unless_switched_off(dataset, tmp_path,
                                                                                              monkeypatch):
    monkeypatch.setenv("SR_DIGEST_CACHE", str(tmp_path / "cache.json"))
    copy = _copy(dataset, tmp_path)
    before = dataset_inputs(["approach"], [copy])
    parquet = next((copy / "data").rglob("*.parquet"))
    stat = parquet.stat()
    with parquet.open("r+b") as f:  # in place: same inode, same size
        f.seek(stat.st_size // 2)
        byte = f.read(1)
        f.seek(stat.st_size // 2)
        f.write(bytes([byte[0] ^ 0xFF]))
    os.utime(parquet, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert dataset_inputs(["approach"], [copy]) == before  # the weak spot the table states
    monkeypatch.setenv("SR_NO_DIGEST_CACHE", "1")
    assert dataset_inputs(["approach"], [copy]) != before


def test_a_parquet_that_disagrees_with_its_info_json_is_refused(dataset, tmp_path):
    from sr_imitation.substrates.act.data import DatasetMismatchError, check_data_files, load_metadata
    from tests.test_dataset_schema import one_shorter_fixed, rewrite_column

    copy = _copy(dataset, tmp_path)
    parquet = next((copy / "data").rglob("*.parquet"))
    rewrite_column(parquet, "action", one_shorter_fixed)
    with pytest.raises(DatasetMismatchError, match=re.escape(f"{parquet}: disagrees with {copy}/meta/info.json")):
        check_data_files(load_metadata(copy, "local/approach"))  # the stream's check (at start-up, on resume:
        # tests/test_dataset_schema.py)


def test_a_sealed_checkpoint_is_verified_and_a_copied_one_is_named_unverified(tmp_path, caplog):
    with staged_directory(tmp_path / "stage") as tmp:
        (tmp / "pretrained_model").mkdir()
        (tmp / "pretrained_model" / "model.safetensors").write_bytes(b"weights")
    pretrained = tmp_path / "stage" / "pretrained_model"
    assert verify_checkpoint(pretrained)
    copied = tmp_path / "elsewhere" / "pretrained_model"
    shutil.copytree(pretrained, copied)
    caplog.set_level(logging.WARNING)
    assert not verify_checkpoint(copied, "policy.path")
    assert [r.getMessage() for r in caplog.records] == [
        f"{copied}: policy.path is not verified: no {copied.parent / 'checksums.json'} one level up (it is written "
        "beside pretrained_model/ by sr-train and sr-sleep; copy the folder holding both to keep the check)"]
    (pretrained / "model.safetensors").write_bytes(b"weightz")
    with pytest.raises(CorruptFileError, match="contents differ from checksums.json"):
        verify_checkpoint(pretrained)


def test_sr_eval_and_sr_sleep_warn_about_a_copied_checkpoint(tmp_path, caplog):
    from sr_imitation.substrates.act import cli

    copied = tmp_path / "copy" / "pretrained_model"
    copied.mkdir(parents=True)
    for name in ("config.json", "policy_preprocessor.json", "policy_postprocessor.json"):
        (copied / name).write_text("{}")  # enough to be looked at; loading them fails afterwards
    (copied / "model.safetensors").write_bytes(b"")
    caplog.set_level(logging.WARNING)
    for main, flags in ((cli.eval_main, ["--skills=[approach]", f"--output_dir={tmp_path / 'eval'}"]),
                        (cli.sleep_main, [f"--memories=[{tmp_path / 'm.safetensors'}]",
                                          f"--output_dir={tmp_path / 'slept'}"])):
        caplog.clear()
        with pytest.raises(Exception):  # noqa: B017, PT011 - the dummy checkpoint does not load; the warning came first
            main([f"--policy.path={copied}", *flags])
        assert any("is not verified: no" in r.getMessage() for r in caplog.records), main.__name__


def test_an_edited_sealed_file_is_refused(tmp_path):
    path = write_checked_json(tmp_path / "results.json", {"afsr": 0.5})
    assert read_checked_json(path) == {"afsr": 0.5}
    path.write_text(path.read_text().replace("0.5", "0.9"))
    with pytest.raises(CorruptFileError, match="results.json"):
        read_checked_json(path)


HOLDER = textwrap.dedent("""
    import sys, time
    from sr_imitation.infra.folder_lock import hold_folder
    with hold_folder(sys.argv[1], "sr-train"):
        print("held", flush=True)
        time.sleep(300)
""")


def test_a_second_writer_is_refused(tmp_path):
    holder = subprocess.Popen([sys.executable, "-c", HOLDER, str(tmp_path / "run")], stdout=subprocess.PIPE,
                              text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(FolderBusyError, match=rf"run: in use by sr-train \(pid {holder.pid} "), \
                hold_folder(tmp_path / "run"):
            pass
    finally:
        holder.kill()
        holder.wait()
    with hold_folder(tmp_path / "run"):  # a killed holder's lock is released by the OS
        pass


def test_a_boolean_for_a_number_is_refused(tmp_path):
    from sr_imitation.substrates.act import cli

    config = tmp_path / "c.json"
    config.write_text(json.dumps({"wake": {"max_epochs": True}}))
    for args in (["--sleep.lr=true"], [f"--config_path={config}"]):
        with pytest.raises(ValueError, match=r"(sleep\.lr|max_epochs)"):
            cli.train_main([*args, f"--output_dir={tmp_path / 'run'}"])
    assert not (tmp_path / "run").exists()


def test_leftovers_are_removed_by_the_next_run(tmp_path):
    from sr_imitation.infra.folder_lock import remove_staging_beside

    staging = tmp_path / ".slept.abcd1234"
    staging.mkdir()
    with hold_folder(tmp_path / "slept"):
        assert remove_staging_beside(tmp_path / "slept", "sr-sleep") == [staging]
    assert not staging.exists()  # the commands that do it: tests/test_staging_leftovers.py
