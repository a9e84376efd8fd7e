"""Inputs are part of a run: a resume over other data is refused naming the skill and path, an old run
without dataset digests resumes only with the flag that says so, and a single changed byte in any file of a run
directory is refused before anything is written or leaves the results identical to an untouched run.

Before: replacing a skill's dataset between a kill and ``--resume=true`` exited 0 with other weights; a flipped
stage-1 checkpoint was found after 16 files were rewritten; ``trajectories.npz`` had no checksum.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

import sr_imitation.substrates.act.cli as cli
import sr_imitation.substrates.act.dataset_identity as identity
from sr_imitation.infra.cli_errors import run_cli
from sr_imitation.infra.fingerprint import (
    FINGERPRINT_FILE,
    SettingsFingerprint,
    read_fingerprint,
    settings_digest,
    write_fingerprint,
)
from sr_imitation.substrates.act.dataset_identity import InputsMismatchError, dataset_digest, dataset_inputs
from sr_imitation.substrates.act.trainer import ACTTrainer, train_stream
from tests.infra.test_fingerprint import tree_state
from tests.substrates.act.conftest import SKILLS
from tests.substrates.act.helpers import fake_env_factory, tiny_stream_config

STREAM = SKILLS[:2]


@pytest.fixture(scope="module")
def datasets(state_datasets, tmp_path_factory) -> Path:
    """A private copy of the tiny datasets (tests swap files in copies of it)."""
    root = tmp_path_factory.mktemp("inputs") / "data"
    shutil.copytree(state_datasets, root)
    return root


@pytest.fixture(scope="module")
def reference(datasets, tmp_path_factory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("reference") / "run"
    return out, train_stream(tiny_stream_config(datasets, out, STREAM, use_images=False), fake_env_factory)


@pytest.fixture(scope="module")
def after_stage_1(datasets, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("stage1") / "run"
    ACTTrainer(tiny_stream_config(datasets, out, STREAM, use_images=False), fake_env_factory).run(stop_after=1)
    return out


def _no_training(monkeypatch):
    def tripwire(*args, **kwargs):
        raise AssertionError("training started before the inputs were checked")

    monkeypatch.setattr("sr_imitation.substrates.act.substrate.wake_train", tripwire)


def _resume(run: Path, root: Path, **changes):
    cfg = tiny_stream_config(root, run, STREAM, use_images=False)
    cfg.resume = True
    for key, value in changes.items():
        setattr(cfg, key, value)
    return train_stream(cfg, fake_env_factory)


def _final_weights(run: Path) -> dict[str, torch.Tensor]:
    return load_file(str(run / "skill_2_place" / "sleep" / "pretrained_model" / "model.safetensors"))


def _same_as_reference(run: Path, reference) -> None:
    ref_out, ref_results = reference
    assert json.loads((run / "results.json").read_text())["metrics"] == ref_results["metrics"]
    final, ref = _final_weights(run), _final_weights(ref_out)
    assert all(torch.equal(final[k], ref[k]) for k in ref)


def test_a_resume_over_a_swapped_dataset_is_refused_naming_the_skill_and_path(datasets, after_stage_1, tmp_path,
                                                                               monkeypatch):
    root = tmp_path / "data"
    shutil.copytree(datasets, root)
    run = tmp_path / "run"
    shutil.copytree(after_stage_1, run)
    shutil.rmtree(root / "place")
    shutil.copytree(datasets / SKILLS[2], root / "place")  # same features, other demonstrations
    before = tree_state(run)
    _no_training(monkeypatch)
    with pytest.raises(InputsMismatchError) as info:
        _resume(run, root)
    message = str(info.value)
    assert "\n" not in message and f"{root / 'place'}: the dataset of skill 'place' differs" in message
    assert tree_state(run) == before


def test_a_run_resumes_over_the_same_data_moved_elsewhere(datasets, after_stage_1, reference, tmp_path):
    moved = tmp_path / "moved" / "data"
    shutil.copytree(datasets, moved)  # new paths, inodes and modification times; the same bytes
    run = tmp_path / "run"
    shutil.copytree(after_stage_1, run)
    _resume(run, moved.resolve())
    _same_as_reference(run, reference)


def test_an_old_run_without_dataset_digests_resumes_only_with_the_flag(datasets, after_stage_1, reference, tmp_path,
                                                                       monkeypatch):
    run = tmp_path / "run"
    shutil.copytree(after_stage_1, run)
    old = {k: v for k, v in read_fingerprint(run / FINGERPRINT_FILE).items() if not k.startswith("inputs.")}
    write_fingerprint(run / FINGERPRINT_FILE, SettingsFingerprint(old, settings_digest(old)))
    before = tree_state(run)
    with pytest.raises(InputsMismatchError, match="--allow_unhashed_inputs=true"):
        _resume(run, datasets)
    assert tree_state(run) == before
    _resume(run, datasets, allow_unhashed_inputs=True)
    _same_as_reference(run, reference)


def test_dataset_digests_are_cached_by_file_stat_and_follow_a_replaced_file(datasets, tmp_path, monkeypatch):
    monkeypatch.delenv("SR_DIGEST_CACHE", raising=False)  # the suite's own cache file (tests/conftest.py)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    root = tmp_path / "data"
    shutil.copytree(datasets / "approach", root / "approach")
    reads = []
    real = identity.file_digest
    monkeypatch.setattr(identity, "file_digest", lambda p: reads.append(p) or real(p))
    first = dataset_inputs(["approach"], [root / "approach"])
    n_files = len(reads)
    assert n_files >= 4 and (tmp_path / "cache" / "sr_imitation" / "file_digests.json").is_file()
    assert dataset_inputs(["approach"], [root / "approach"]) == first and len(reads) == n_files  # from the cache
    parquet = next((root / "approach" / "data").rglob("*.parquet"))
    data = bytearray(parquet.read_bytes())
    data[len(data) // 2] ^= 0xFF
    parquet.unlink()
    parquet.write_bytes(bytes(data))  # replaced: new inode and mtime
    assert dataset_inputs(["approach"], [root / "approach"]) != first and len(reads) == n_files + 1
    assert dataset_digest(root / "approach") == dataset_inputs(["approach"], [root / "approach"])["approach"]
    (root / "approach" / ".cache").mkdir()  # hidden files are not part of a dataset
    (root / "approach" / ".cache" / "x").write_text("y")
    assert dataset_digest(root / "approach") == dataset_inputs(["approach"], [root / "approach"])["approach"]


def test_the_digest_cache_keeps_only_live_entries_and_is_read_again_after_another_process_wrote_it(
        datasets, tmp_path, monkeypatch):
    """The cache does not grow with every dataset ever hashed: a write keeps only the entries that still describe a
    file as it is (a deleted dataset's and a rewritten file's go). A process re-reads the file only when it changed
    since this process read or wrote it, so another process's entries are seen."""
    cache_file = tmp_path / "digests.json"
    monkeypatch.setenv("SR_DIGEST_CACHE", str(cache_file))
    for name in ("a", "b"):
        shutil.copytree(datasets / "approach", tmp_path / name)
    dataset_inputs(["a"], [tmp_path / "a"])
    n_a = len(json.loads(cache_file.read_text()))
    dataset_inputs(["b"], [tmp_path / "b"])
    assert len(json.loads(cache_file.read_text())) == 2 * n_a
    shutil.rmtree(tmp_path / "a")
    shutil.copytree(datasets / "place", tmp_path / "c")
    dataset_inputs(["c"], [tmp_path / "c"])  # a write: a's entries are dead
    kept = json.loads(cache_file.read_text())
    assert not any(str(tmp_path / "a") in key for key in kept) and len(kept) >= n_a + 1
    assert all(str(tmp_path / "b") in key or str(tmp_path / "c") in key for key in kept)
    # another process rewrites the file (a foreign entry, whose file exists as recorded): this process reads it
    probe = tmp_path / "probe"
    probe.write_text("x")
    st = probe.stat()
    foreign = {**kept, str(probe): {"stat": [st.st_size, st.st_mtime_ns, st.st_ino], "sha256": "0" * 64}}
    cache_file.write_text(json.dumps(foreign))
    assert identity._load_cache(cache_file) == foreign
    reads = []
    real = identity.file_digest
    monkeypatch.setattr(identity, "file_digest", lambda p: reads.append(p) or real(p))
    dataset_inputs(["b", "c"], [tmp_path / "b", tmp_path / "c"])
    assert reads == []  # every file of b and c from the cache


def _flip_candidates(run: Path) -> list[Path]:
    return sorted(p for p in run.rglob("*") if p.is_file())


def test_any_single_byte_change_is_refused_before_writing_or_changes_nothing(after_stage_1, datasets, reference,
                                                                              tmp_path, monkeypatch, capsys):
    """Every file of a run stopped after stage 1, one byte flipped in its middle (a copy per file): the resume
    through ``sr-train`` either refuses before writing anything or finishes exactly as the untouched run."""
    monkeypatch.setattr(cli, "train_stream", lambda cfg: train_stream(cfg, fake_env_factory))
    outcomes = {}
    for original in _flip_candidates(after_stage_1):
        rel = original.relative_to(after_stage_1)
        run = tmp_path / str(len(outcomes)) / "run"
        shutil.copytree(after_stage_1, run)
        data = bytearray((run / rel).read_bytes())
        if not data:
            continue
        data[len(data) // 2] ^= 0x01
        (run / rel).write_bytes(bytes(data))
        before = tree_state(run)
        capsys.readouterr()
        try:
            run_cli("sr-train", cli.train_main, [f"--config_path={run / 'train_config.json'}", "--resume=true",
                                                 f"--stream.dataset_root={datasets}"])
        except SystemExit as exc:  # a one-line user error (a bug would keep its traceback and fail the test)
            err = capsys.readouterr().err
            assert exc.code == 2 and err.count("\n") == 1 and err.startswith("sr-train: error: "), (rel, err)
            assert tree_state(run) == before, (rel, err)
            outcomes[str(rel)] = "refused"
        else:
            _same_as_reference(run, reference)
            outcomes[str(rel)] = "identical"
        shutil.rmtree(run.parent)
    # the stage-1 state a resume reads is sealed: checkpoint, memory, evaluations, statistics, progress, fingerprint
    for must_refuse in ("skill_1_approach/wake/pretrained_model/model.safetensors", "progress.json",
                        "stream_stats.safetensors", FINGERPRINT_FILE, "skill_1_approach/wake/eval.json",
                        "skill_1_approach/wake/trajectories.safetensors", "skill_1_approach/wake/checksums.json"):
        assert outcomes.get(must_refuse) == "refused", (must_refuse, outcomes)
    assert any(k.startswith("memories/") and v == "refused" for k, v in outcomes.items()), outcomes
    assert len(outcomes) >= 15, outcomes


def test_a_run_logged_to_wandb_resumes_into_the_same_wandb_run(datasets, reference, tmp_path, monkeypatch):
    """wandb's own files in the run directory are not ours to verify (unsealed by design): a run with wandb resumes,
    continues the same wandb run, and ends as the untouched run does."""
    from sr_imitation.infra.runlog import WANDB_ID_FILE, WandbConfig

    monkeypatch.setenv("WANDB_SILENT", "true")
    run = tmp_path / "run"
    cfg = tiny_stream_config(datasets, run, STREAM, use_images=False)
    cfg.wandb = WandbConfig(enable=True, mode="offline")
    ACTTrainer(cfg, fake_env_factory).run(stop_after=1)
    first = json.loads((run / WANDB_ID_FILE).read_text())["id"]
    assert any(p.is_file() for p in (run / "wandb").rglob("*"))  # wandb's own files, unsealed
    _resume(run, datasets, wandb=WandbConfig(enable=True, mode="offline"))
    assert json.loads((run / WANDB_ID_FILE).read_text())["id"] == first
    _same_as_reference(run, reference)
