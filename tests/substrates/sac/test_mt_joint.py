"""The MT-joint oracle: every skill in one run, skills drawn uniformly per episode, results in the shared schema with
BWT 0 by definition, a kill before the evaluation resumes to the same numbers, changed settings are refused."""

from __future__ import annotations

import json
from collections import Counter

import pytest

from sr_imitation.infra.fingerprint import SettingsMismatchError
from sr_imitation.substrates.sac.config import EvalConfig
from sr_imitation.substrates.sac.mt_joint import MultiSkillEnv, run_mt_joint
from tests.substrates.sac.test_trainer import tiny_config


def test_skills_are_drawn_uniformly_and_reproducibly():
    skills = ["reach-v3", "door-open-v3"]
    with MultiSkillEnv(skills, seed=3, max_episode_steps=5) as env:
        drawn = []
        for _ in range(40):
            env.reset()
            drawn.append(env.current.skill)
        env.seed(3)
        again = []
        for _ in range(40):
            env.reset()
            again.append(env.current.skill)
    assert drawn == again and set(Counter(drawn)) == set(skills) and min(Counter(drawn).values()) >= 10


def test_mt_joint_runs_resumes_and_reports_apart(tmp_path, monkeypatch):
    cfg = tiny_config(tmp_path / "joint", eval=EvalConfig(episodes=2, videos_per_skill=0))
    results = run_mt_joint(cfg, episodes=200)  # x budget_scale 0.002 -> 1 episode
    assert results["method"] == "mt_joint" and results["memory_bytes_total"] == 0
    s = results["success_matrix"]
    assert s[0][0] == s[1][0] and results["success_after_own_wake"] == s[1]
    assert results["metrics"]["bwt"]["final"] == 0.0 and results["metrics"]["bwt_wake"]["final"] == 0.0
    progress = json.loads((tmp_path / "joint" / "progress.json").read_text())["completed"]
    assert set(progress) == {"1.train", "1.eval"} and progress["1.train"]["wake"]["episodes"] == 1
    # a run killed after training resumes at the evaluation and reaches the same numbers
    from sr_imitation.stream.rundir import RunDirectory

    real_mark = RunDirectory.mark

    def killing_mark(self, k, phase, record):
        real_mark(self, k, phase, record)
        if phase == "train":
            raise KeyboardInterrupt

    killed = tiny_config(tmp_path / "killed", eval=EvalConfig(episodes=2, videos_per_skill=0))
    monkeypatch.setattr(RunDirectory, "mark", killing_mark)
    with pytest.raises(KeyboardInterrupt):
        run_mt_joint(killed, episodes=200)
    monkeypatch.setattr(RunDirectory, "mark", real_mark)
    killed.resume = True
    assert run_mt_joint(killed, episodes=200)["success_matrix"] == s
    with pytest.raises(SettingsMismatchError, match="mt_joint_episodes"):
        run_mt_joint(killed, episodes=400)
