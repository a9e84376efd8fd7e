"""LeRobot integration: `--env.type=needle` parses, make_env builds it, observation keys map correctly."""

from dataclasses import dataclass

import draccus
import numpy as np
import pytest
from lerobot.envs.configs import EnvConfig
from lerobot.envs.factory import make_env
from lerobot.envs.utils import env_to_policy_features, preprocess_observation

from sr_imitation.envs.needle.lerobot_config import NeedleEnvConfig


@dataclass
class _Cli:
    env: EnvConfig


def test_draccus_parses_env_type_needle():
    cfg = draccus.parse(
        _Cli, args=["--env.type=needle", "--env.task=insert", "--env.thresholds=surgicai"]
    ).env
    assert isinstance(cfg, NeedleEnvConfig)
    assert cfg.gym_id == "sr_needle/insert" and cfg.gym_kwargs["thresholds"] == "surgicai"


def test_make_env_and_policy_features():
    cfg = NeedleEnvConfig(task="regrasp", observation_height=32, observation_width=32)
    features = env_to_policy_features(cfg)
    assert features["observation.images.wrist"].shape == (3, 32, 32)
    assert features["observation.state"].shape == (35,)
    assert features["action"].shape == (7,)
    vec = make_env(cfg, n_envs=2)["needle"][0]
    try:
        obs, _ = vec.reset(seed=[0, 1])
        batch = preprocess_observation(obs)
        assert batch["observation.images.wrist"].shape == (2, 3, 32, 32)
        assert batch["observation.state"].shape == (2, 35)
        assert list(vec.call("task_description")) == ["regrasp", "regrasp"]
        assert list(vec.call("_max_episode_steps")) == [300, 300]
        _, _, _, _, info = vec.step(np.zeros((2, 7), dtype=np.float32))
        assert "is_success" in info
        assert vec.envs[0].render().shape == (240, 320, 3)
    finally:
        vec.close()


def test_invalid_task_rejected():
    with pytest.raises(ValueError, match="env.task"):
        NeedleEnvConfig(task="suture")
