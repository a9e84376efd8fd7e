"""Tiny synthetic stream for ACT-SR tests: LeRobot datasets made here and a fake needle-like environment."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np

from lerobot_policy_act_sr import ACTSRConfig
from sr_imitation.lerobot_compat import create_dataset
from sr_imitation.substrates.act.config import SurgicAISleepConfig
from sr_imitation.substrates.act.evaluate import EvalConfig
from sr_imitation.substrates.act.trainer import MemoryConfig, StreamConfig, TrainStreamConfig
from sr_imitation.substrates.act.wake import WakeConfig

IMAGE = 16
STATE_DIM = 6
ACTION_DIM = 7


def features(image: bool = True, state_dim: int = STATE_DIM, action_dim: int = ACTION_DIM,
             video: bool = False) -> dict:
    out = {
        "observation.state": {"dtype": "float32", "shape": (state_dim,), "names": None},
        "action": {"dtype": "float32", "shape": (action_dim,), "names": None},
    }
    if image:
        out["observation.images.wrist"] = {"dtype": "video" if video else "image", "shape": (IMAGE, IMAGE, 3),
                                           "names": ["height", "width", "channels"]}
    return out


def make_skill_dataset(root: Path, skill: str, index: int, episodes: int = 3, frames: int = 10,
                       image: bool = True, state_dim: int = STATE_DIM, action_dim: int = ACTION_DIM,
                       constant: dict[str, dict[int, float]] | None = None, offset: float | None = None,
                       video: bool = False) -> Path:
    """A dataset whose action is a fixed linear function of the state, different per skill; ``constant`` holds
    dimensions of ``observation.state`` / ``action`` at a fixed value (a gripper that never moves: std 0),
    ``offset`` shifts the state (default ``index``); ``video``: the camera stored as an h264 video, as
    ``sr-record --video=true`` stores it (the episodes of a skill in one mp4 file)."""
    rng = np.random.default_rng(index)
    weights = rng.normal(size=(state_dim, action_dim)).astype(np.float32) * 0.3
    ds = create_dataset(repo_id=f"local/sr_needle_{skill}", fps=10, root=root / skill, robot_type="sim",
                        use_videos=video, features=features(image, state_dim, action_dim, video), vcodec="h264")
    for _ in range(episodes):
        for _ in range(frames):
            state = rng.normal(size=state_dim).astype(np.float32) + (index if offset is None else offset)
            frame = {"observation.state": state, "action": np.tanh(state @ weights), "task": skill}
            for key, dims in (constant or {}).items():
                for dim, value in dims.items():
                    frame[key][dim] = value
            if image:
                frame["observation.images.wrist"] = rng.integers(0, 255, (IMAGE, IMAGE, 3), dtype=np.uint8)
            ds.add_frame(frame)
        ds.save_episode()
    ds.finalize()
    return root / skill


def damage(path: Path, how: str) -> None:
    """Damage a file as a failing disk or a bad copy does: ``inverted``, 64 bytes in the middle; ``truncated``, its
    last third cut off."""
    data = bytearray(path.read_bytes())
    if how == "inverted":
        mid = len(data) // 2
        data[mid : mid + 64] = bytes(b ^ 0xFF for b in data[mid : mid + 64])
    else:
        data = data[: len(data) * 2 // 3]
    path.write_bytes(bytes(data))


class FakeNeedleEnv(gym.Env):
    """Needle-like interface (``pixels/wrist``, ``agent_pos``, ``info['is_success']``), trivial dynamics."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, skill: str, render: bool = False) -> None:
        self.skill = skill
        self.observation_space = gym.spaces.Dict({
            "pixels": gym.spaces.Dict({"wrist": gym.spaces.Box(0, 255, (IMAGE, IMAGE, 3), np.uint8)}),
            "agent_pos": gym.spaces.Box(-np.inf, np.inf, (STATE_DIM,), np.float32),
        })
        self.action_space = gym.spaces.Box(-1, 1, (ACTION_DIM,), np.float32)
        self.render_mode = "rgb_array" if render else None
        self._state = np.zeros(STATE_DIM, np.float32)
        self.steps = 0

    def _obs(self) -> dict:
        img = np.full((IMAGE, IMAGE, 3), int(abs(self._state[0]) * 40) % 255, np.uint8)
        return {"pixels": {"wrist": img}, "agent_pos": self._state.copy()}

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self._state = self.np_random.normal(size=STATE_DIM).astype(np.float32)
        self.steps = 0
        return self._obs(), {"is_success": False}

    def step(self, action):
        action = np.asarray(action, dtype=np.float32)
        self._state = self._state + 0.1 * np.resize(action, STATE_DIM)
        self.steps += 1
        success = bool(self._state[0] > 1.0)
        return self._obs(), 0.0, success, False, {"is_success": success}

    def render(self):
        return np.zeros((16, 16, 3), np.uint8)


def fake_env_factory(skill: str, render: bool) -> gym.Env:
    return FakeNeedleEnv(skill, render)


def tiny_policy(**overrides) -> ACTSRConfig:
    base = dict(device="cpu", dim_model=32, n_heads=2, dim_feedforward=64, n_encoder_layers=1,
                n_vae_encoder_layers=1, chunk_size=4, n_action_steps=4, distill_batch_size=4)
    base.update(overrides)
    return ACTSRConfig(**base)


def tiny_sleep(**overrides) -> SurgicAISleepConfig:
    """Three sleep iterations on batches of 4 (a plateau window of 2 cannot fire before the budget ends)."""
    return SurgicAISleepConfig(**{"max_iterations": 3, "batch_size": 4, "early_stop_window": 2, **overrides})


def tiny_stream_config(
    dataset_root: Path, output_dir: Path, skills: list[str], sleep: dict | None = None, stats: str = "first",
    **policy_overrides
) -> TrainStreamConfig:
    """A tiny ACT-SR stream; ``sleep`` overrides :func:`tiny_sleep`'s settings, the keywords the policy's; ``stats``
    is ``--stream.stats`` (``first`` here, as these tests were written: tests of ``seen`` say so)."""
    return TrainStreamConfig(
        policy=tiny_policy(**policy_overrides),
        stream=StreamConfig(skills=skills, dataset_root=dataset_root, stats=stats),
        memory=MemoryConfig(buffer_size=16),
        sleep=tiny_sleep(**(sleep or {})),
        wake=WakeConfig(max_epochs=2, min_epochs=1, patience=1, batch_size=4, max_steps_per_epoch=2),
        eval=EvalConfig(episodes=2, seeds=[0, 1], max_steps=6, videos_per_skill=1),
        output_dir=output_dir,
        seed=7,
        progress=False,
    )
