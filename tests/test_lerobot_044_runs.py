"""Runs, checkpoints and datasets made with LeRobot 0.4.4 (tag v0.1.0) under LeRobot 0.6: the checkpoints and the
datasets are read without complaint (sr-sleep, LeRobot's loaders, a new stream), a resume is refused in one line
naming both versions and the tag. The fixture was made by tests/fixtures/lerobot_044/make.py at v0.1.0."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import pytest
import torch
from lerobot.configs.policies import PreTrainedConfig
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.policies.factory import get_policy_class, make_pre_post_processors

from sr_imitation.infra.fingerprint import FINGERPRINT_FILE, StackMismatchError, read_fingerprint
from sr_imitation.lerobot_compat import LEGACY_TAG, lerobot_version
from sr_imitation.substrates.act.cli import sleep_main
from sr_imitation.substrates.act.offline_sleep import SleepFailedError
from sr_imitation.substrates.act.trainer import ACTTrainer
from tests.substrates.act.helpers import fake_env_factory, tiny_stream_config

FIXTURE = Path(__file__).resolve().parent / "fixtures" / "lerobot_044"
WAKE = Path("skill_1_approach") / "wake"
SKILLS = ["approach", "place"]


@pytest.fixture
def legacy(tmp_path) -> tuple[Path, Path]:
    """A copy of the 0.4.4 run (stopped after stage 1) and of its datasets."""
    shutil.copytree(FIXTURE / "datasets", tmp_path / "datasets")
    shutil.copytree(FIXTURE / "run", tmp_path / "run")
    return tmp_path / "run", tmp_path / "datasets"


def _tree(path: Path) -> dict[str, bytes]:
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


def test_the_fixture_is_a_lerobot_0_4_4_run_without_a_recorded_stack():
    settings = read_fingerprint(FIXTURE / "run" / FINGERPRINT_FILE)
    assert not any(k.startswith("stack.") for k in settings)  # 0.4.4's code recorded no versions
    assert "policy.pretrained_revision" not in settings  # a field 0.6 added


def test_resuming_a_lerobot_0_4_4_run_is_refused_in_one_line_naming_both_versions_and_the_tag(legacy):
    run, datasets = legacy
    before = _tree(run)
    cfg = tiny_stream_config(datasets, run, SKILLS, use_images=False)
    cfg.resume = True
    with pytest.raises(StackMismatchError) as refused:
        ACTTrainer(cfg, fake_env_factory).run()
    message = str(refused.value)
    assert "\n" not in message and str(run / FINGERPRINT_FILE) in message
    assert "lerobot 0.4.4" in message and f"lerobot {lerobot_version()}" in message and LEGACY_TAG in message
    assert _tree(run) == before  # nothing written


def test_a_new_run_on_lerobot_0_4_4_datasets_trains_its_first_stage(legacy, tmp_path, caplog):
    _, datasets = legacy
    cfg = tiny_stream_config(datasets, tmp_path / "new", SKILLS, use_images=False)
    with caplog.at_level(logging.WARNING):
        ACTTrainer(cfg, fake_env_factory).run(stop_after=1)
    assert (tmp_path / "new" / WAKE / "pretrained_model" / "model.safetensors").is_file()
    assert read_fingerprint(tmp_path / "new" / FINGERPRINT_FILE)["stack.lerobot"] == lerobot_version()
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING and "lerobot" in r.name]


def test_a_lerobot_0_4_4_video_dataset_decodes():
    dataset = LeRobotDataset("local/sr_needle_approach", root=FIXTURE / "datasets" / "video" / "approach",
                             video_backend="pyav")
    frame = dataset[3]["observation.images.wrist"]
    assert frame.shape == (3, 16, 16) and torch.isfinite(frame).all() and float(frame.std()) > 0


def test_a_lerobot_0_4_4_checkpoint_loads_as_lerobot_eval_loads_it(caplog):
    path = FIXTURE / "run" / WAKE / "pretrained_model"
    with caplog.at_level(logging.WARNING):
        config = PreTrainedConfig.from_pretrained(path)
        config.device = "cpu"
        policy = get_policy_class(config.type).from_pretrained(path, config=config)
        pre, post = make_pre_post_processors(config, pretrained_path=str(path),
                                             preprocessor_overrides={"device_processor": {"device": "cpu"}})
    assert config.type == "act_sr" and config.pretrained_revision is None
    batch = pre({"observation.state": torch.zeros(6)})
    action = post(policy.select_action(batch))
    assert action.shape == (1, 7) and torch.isfinite(action).all()
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]


def test_sr_sleep_reads_a_lerobot_0_4_4_checkpoint_as_the_function_its_memory_stored(legacy, tmp_path):
    """The memory 0.4.4 wrote holds the checkpoint's own action chunks on the stored observations: under 0.6 sr-sleep
    loads both and finds the memory's loss exactly 0 (the checkpoint computes what it computed under 0.4.4), so it
    refuses the sleep as one that would change nothing, and writes nothing."""
    run, _ = legacy
    with pytest.raises(SleepFailedError, match="memory loss 0 before and after"):
        sleep_main([f"--policy.path={run / WAKE / 'pretrained_model'}",
                    f"--memories=[{run / 'memories' / 'skill_1_approach.safetensors'}]",
                    f"--output_dir={tmp_path / 'slept'}", "--sleep.max_iterations=3", "--sleep.batch_size=4",
                    "--sleep.early_stop_window=2", "--progress=false"])
    assert not (tmp_path / "slept").exists()
