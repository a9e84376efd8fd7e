"""Stream trainer: end-to-end on a tiny 2-skill stream, resume after a kill, output-dir safety, CLI configs."""

from __future__ import annotations

import json
from pathlib import Path

import draccus
import pytest

from sr_imitation.core.io import CorruptFileError
from sr_imitation.core.sleep import SleepConfig
from sr_imitation.rl.config import CriticMemoryConfig, EvalConfig, RLTrainConfig, SACConfig, WakeConfig
from sr_imitation.rl.report import summarize
from sr_imitation.rl.trainer import StreamTrainer

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def tiny_config(out: Path, **overrides) -> RLTrainConfig:
    base = {
        "output_dir": out, "seed": 3, "skills": ["reach-v3", "door-open-v3"], "max_episode_steps": 30,
        "sac": SACConfig(hidden_dim=32, batch_size=16, utd_ratio=0.5, warmup_steps=40, buffer_size=5000),
        "wake": WakeConfig(budget_scale=0.002),
        "sleep": SleepConfig.mt5(max_iterations=12, early_stop_window=5, fw_iterations=5, batch_size=16),
        "memory": CriticMemoryConfig(buffer_size=32, validation_chunk=5, validation_max_rounds=1),
        "eval": EvalConfig(episodes=2, video_height=64, video_width=64), "progress": False, "plots": False,
    }
    base.update(overrides)
    return RLTrainConfig(**base)


class SimulatedKillError(RuntimeError):
    pass


def test_stream_end_to_end_and_resume_after_kill(tmp_path):
    full = StreamTrainer(tiny_config(tmp_path / "full", plots=True)).run()
    assert full["skills"] == ["reach", "door-open"]
    assert len(full["success_matrix"]) == 2 and full["success_matrix"][0][1] is None
    assert set(full["metrics"]) >= {"afsr", "prs", "bwt", "spi"}
    assert "sleep" in full["stages"][1] and "sleep" not in full["stages"][0]
    assert len(full["stages"][1]["sleep"]["frozen_critic_value_change"]) == 2
    assert (tmp_path / "full" / "plots" / "success_matrix.png").is_file()
    assert (tmp_path / "full" / "report.md").is_file()
    assert "| full | sleeping_robots | 3 |" in summarize([tmp_path / "full"])
    videos = [[row["videos"] for row in stage["eval"]] for stage in full["stages"]]  # one per learned skill
    assert [[len(v) for v in stage] for stage in videos] == [[1], [1, 1]]
    assert videos[1][0][0].startswith("videos/stage_02_door-open/reach_episode0_")
    assert all((tmp_path / "full" / v[0]).stat().st_size > 1000 for stage in videos for v in stage)

    def kill_after_first(stage):
        if stage == 0:
            raise SimulatedKillError

    with pytest.raises(SimulatedKillError):
        StreamTrainer(tiny_config(tmp_path / "killed"), after_stage=kill_after_first).run()
    assert not (tmp_path / "killed" / "results.json").exists()
    resumed = StreamTrainer(tiny_config(tmp_path / "killed", resume=True)).run()
    for key in ("success_matrix", "metrics"):
        assert resumed[key] == full[key], key
    strip = lambda r: {k: v for k, v in r.items() if k != "seconds"}  # noqa: E731
    assert strip(resumed["stages"][1]["sleep"]) == strip(full["stages"][1]["sleep"])
    assert resumed["stages"][1]["wake"]["final_train_reward"] == full["stages"][1]["wake"]["final_train_reward"]


def test_output_dir_safety_and_loud_failures(tmp_path):
    out = tmp_path / "run"
    cfg = tiny_config(out, skills=["reach-v3"], eval=EvalConfig(episodes=1))
    StreamTrainer(cfg).run()
    with pytest.raises(FileExistsError, match="--resume"):
        StreamTrainer(tiny_config(out, skills=["reach-v3"])).run()
    with pytest.raises(CorruptFileError, match="seed"):
        StreamTrainer(tiny_config(out, skills=["reach-v3"], seed=4, resume=True)).run()
    ckpt = out / "stages" / "01_reach" / "agent.safetensors"
    ckpt.write_bytes(ckpt.read_bytes()[:-10])
    with pytest.raises(CorruptFileError, match="agent.safetensors"):
        StreamTrainer(tiny_config(out, skills=["reach-v3"], eval=EvalConfig(episodes=1), resume=True)).run()
    StreamTrainer(tiny_config(out, skills=["reach-v3"], eval=EvalConfig(episodes=1), overwrite=True)).run()
    assert json.loads((out / "results.json").read_text())["skills"] == ["reach"]
    with pytest.raises(ValueError, match="mutually exclusive"):
        tiny_config(out, resume=True, overwrite=True)


@pytest.mark.parametrize("name", ["sac_mt5_paper.json", "sac_mt5_cpu.json"])
def test_shipped_configs_parse(name):
    cfg = draccus.parse(RLTrainConfig, config_path=CONFIGS / name, args=["--seed=7"])
    assert cfg.seed == 7 and cfg.stream_skills[0] == "reach-v3"
    assert cfg.sleep.fw_iterations == 50 and cfg.sleep.max_iterations == 4000 and cfg.sleep.lr == 5e-4
    assert cfg.excitability.e_min == 0.1 and cfg.excitability.e_max == 5.0
    assert cfg.sac.target_entropy == -2.0 and cfg.sac.hidden_dim == 256
