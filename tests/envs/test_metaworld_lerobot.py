"""``--env.type=sr_meta_world``: stock LeRobot (``make_env``, ``lerobot-eval``) builds this package's Meta-World view
(the 39-number observation ``sr-record --env=metaworld`` records), not LeRobot's own 4-number ``metaworld`` type."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import draccus
import numpy as np
import pytest
from lerobot.envs.configs import EnvConfig
from lerobot.envs.factory import make_env
from lerobot.envs.utils import env_to_policy_features, preprocess_observation

from sr_imitation.envs.metaworld.env import MetaWorldEnv
from sr_imitation.envs.metaworld.lerobot_config import MetaWorldStateEnvConfig
from sr_imitation.envs.metaworld.tasks import scripted_policy


@dataclass
class _Cli:
    env: EnvConfig


def test_draccus_parses_the_env_type_and_checks_the_task():
    cfg = draccus.parse(_Cli, args=["--env.type=sr_meta_world", "--env.task=door-open-v3",
                                    "--env.episode_length=300"]).env
    assert isinstance(cfg, MetaWorldStateEnvConfig)
    assert cfg.gym_id == "sr_meta_world/door-open-v3"
    assert cfg.gym_kwargs["episode_length"] == cfg.gym_kwargs["max_episode_steps"] == 300
    with pytest.raises(ValueError, match=r"^env\.task: 'reach-v2' is not a Meta-World v3 task; did you mean "
                                         r"'reach-v3'\?$"):
        MetaWorldStateEnvConfig(task="reach-v2")
    with pytest.raises(ValueError, match=r"^env\.camera must be one of"):
        MetaWorldStateEnvConfig(camera="front")
    with pytest.raises(ValueError, match=r"^env\.obs_type must be one of"):
        MetaWorldStateEnvConfig(obs_type="pixels")


def test_lerobots_make_env_builds_our_env_and_the_scripted_policy_succeeds_as_lerobot_eval_reads_it():
    cfg = MetaWorldStateEnvConfig(task="reach-v3", episode_length=150)
    assert env_to_policy_features(cfg)["observation.state"].shape == (39,)
    vec = make_env(cfg, n_envs=2)["sr_meta_world"][0]  # LeRobot routes types naming "metaworld" to its own env
    try:
        assert isinstance(vec.envs[0].unwrapped, MetaWorldEnv)
        assert list(vec.call("_max_episode_steps")) == [150, 150]
        assert vec.envs[0].unwrapped._skill.max_episode_steps == 150  # the env's own limit follows the config
        obs, _ = vec.reset(seed=[0, 1])
        assert preprocess_observation(obs)["observation.state"].shape == (2, 39)
        act, succeeded = scripted_policy("reach-v3"), np.zeros(2, dtype=bool)
        for _ in range(150):
            obs, _, terminated, _, info = vec.step(np.stack([act(o) for o in obs["agent_pos"]]).astype(np.float32))
            if "final_info" in info:  # lerobot-eval reads success where the vector env ends an episode
                succeeded |= info["final_info"]["is_success"] & terminated
            if succeeded.all():
                break
        assert succeeded.all()
        assert vec.envs[0].render().shape == (240, 320, 3)
    finally:
        vec.close()


def test_a_camera_image_maps_to_the_key_sr_record_writes():
    cfg = MetaWorldStateEnvConfig(task="drawer-open-v3", obs_type="pixels_agent_pos", observation_height=16,
                                  observation_width=16)
    assert env_to_policy_features(cfg)["observation.images.corner2"].shape == (3, 16, 16)
    vec = make_env(cfg, n_envs=1)["sr_meta_world"][0]
    try:
        obs, _ = vec.reset(seed=[3])
        batch = preprocess_observation(obs)
        assert batch["observation.images.corner2"].shape == (1, 3, 16, 16)
        assert batch["observation.state"].shape == (1, 39)
    finally:
        vec.close()


@pytest.mark.slow
def test_stock_lerobot_eval_evaluates_a_meta_world_checkpoint(tmp_path_factory):
    """A tiny one-skill stream trained on ``sr-record --env=metaworld`` data, evaluated by stock ``lerobot-eval``
    (a real subprocess) in ``--env.type=sr_meta_world``, headless with no ``MUJOCO_GL`` set (the plugin's import
    chooses EGL)."""
    from sr_imitation.recorders.metaworld import MetaWorldRecordConfig, record
    from sr_imitation.substrates.act.evaluate import EvalConfig
    from sr_imitation.substrates.act.trainer import train_stream
    from tests.substrates.act.helpers import tiny_stream_config

    root = tmp_path_factory.mktemp("mw_lerobot_eval")
    record(MetaWorldRecordConfig(skills=["reach-v3"], num_episodes=2, root=root))
    cfg = tiny_stream_config(root, root / "run", ["reach-v3"], use_images=False)
    cfg.eval = EvalConfig(env="none")
    train_stream(cfg)
    checkpoint = next((root / "run").rglob("pretrained_model/config.json")).parent
    out = root / "eval"
    cmd = [str(Path(sys.executable).parent / "lerobot-eval"), f"--policy.path={checkpoint}",
           "--env.type=sr_meta_world", "--env.task=reach-v3", "--env.episode_length=5", "--eval.n_episodes=1",
           "--eval.batch_size=1", "--policy.device=cpu", f"--output_dir={out}"]
    headless = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM", "DISPLAY")}
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=headless)  # as a user types it
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr and "Exception ignored" not in proc.stderr, proc.stderr[-3000:]
    info = json.loads((out / "eval_info.json").read_text())
    assert info["overall"]["n_episodes"] == 1 and len(info["overall"]["video_paths"]) == 1
