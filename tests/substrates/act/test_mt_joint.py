"""The imitation MT-Joint oracle: one ACT on the union of every skill's demos (built in our data layer), every skill
evaluated, results in the shared schema with BWT 0 by definition; a kill after training resumes to the same
numbers; changed settings are refused before anything is written."""

from __future__ import annotations

import json

import pytest
import torch
from safetensors.torch import load_file

from sr_imitation.infra.fingerprint import SettingsMismatchError
from sr_imitation.stream.rundir import RunDirectory
from sr_imitation.substrates.act.data import load_skill_data
from sr_imitation.substrates.act.mt_joint import JointSubstrate, joint_wake, run_mt_joint, union_data
from tests.substrates.act.conftest import SKILLS
from tests.substrates.act.helpers import fake_env_factory, tiny_stream_config


def test_the_union_holds_every_skills_frames_split_as_each_wake_splits_them(state_datasets, tmp_path):
    cfg = tiny_stream_config(state_datasets, tmp_path / "u", SKILLS, use_images=False)
    substrate = JointSubstrate(cfg, fake_env_factory)
    substrate.out.mkdir(parents=True)
    substrate.setup()
    union = union_data(substrate)
    parts = [load_skill_data(s, cfg.stream.dataset_path(i), cfg.stream.repo_id(i), substrate.policy_cfg,
                             cfg.wake.val_fraction, substrate.phase_seed(i, "wake")) for i, s in enumerate(SKILLS)]
    assert len(union.dataset) == sum(len(p.dataset) for p in parts)
    assert len(union.train_indices) == sum(len(p.train_indices) for p in parts)
    assert len(union.val_indices) == sum(len(p.val_indices) for p in parts) > 0
    offset = len(parts[0].dataset) + len(parts[1].dataset)  # the third skill's first training frame
    first = union.dataset[offset + parts[2].train_indices[0]]
    assert torch.equal(first["observation.state"], parts[2].dataset[parts[2].train_indices[0]]["observation.state"])
    assert joint_wake(cfg).max_steps_per_epoch == cfg.wake.max_steps_per_epoch * len(SKILLS)


def test_mt_joint_runs_resumes_and_reports_apart(state_datasets, tmp_path, monkeypatch):
    cfg = tiny_stream_config(state_datasets, tmp_path / "joint", SKILLS[:2], use_images=False)
    results = run_mt_joint(cfg, fake_env_factory)
    assert results["method"] == "mt_joint" and results["memory_bytes_total"] == 0
    s = results["success_matrix"]
    assert s[0][0] == s[1][0] and results["success_after_own_wake"] == s[1] and s[0][1] is None
    assert results["metrics"]["bwt"]["final"] == 0.0 and results["metrics"]["bwt_wake"]["final"] == 0.0
    progress = json.loads((tmp_path / "joint" / "progress.json").read_text())["completed"]
    assert set(progress) == {"1.wake", "1.wake.eval"}
    assert progress["1.wake"]["steps"] == 2 * 2 * 2  # max_epochs x (steps per epoch x skills)
    weights = load_file(tmp_path / "joint" / "mt_joint" / "wake" / "pretrained_model" / "model.safetensors")

    real_mark = RunDirectory.mark

    def killing_mark(self, k, phase, record):
        real_mark(self, k, phase, record)
        if phase == "wake":
            raise KeyboardInterrupt

    killed = tiny_stream_config(state_datasets, tmp_path / "killed", SKILLS[:2], use_images=False)
    monkeypatch.setattr(RunDirectory, "mark", killing_mark)
    with pytest.raises(KeyboardInterrupt):
        run_mt_joint(killed, fake_env_factory)
    monkeypatch.setattr(RunDirectory, "mark", real_mark)
    killed.resume = True
    assert run_mt_joint(killed, fake_env_factory)["success_matrix"] == s
    again = load_file(tmp_path / "killed" / "mt_joint" / "wake" / "pretrained_model" / "model.safetensors")
    assert all(torch.equal(weights[n], again[n]) for n in weights)
    killed.wake.max_epochs = 3
    with pytest.raises(SettingsMismatchError, match="wake.max_epochs"):
        run_mt_joint(killed, fake_env_factory)
