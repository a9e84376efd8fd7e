"""LeRobot ``EnvConfig`` for the needle environment: ``lerobot-eval --env.type=needle --env.task=<skill>``.

LeRobot 0.6 imports it through the env plugin ``lerobot_env_sr`` (auto-discovered by its ``lerobot_env_`` prefix).
Observation keys map as ``pixels/wrist -> observation.images.wrist`` and ``agent_pos -> observation.state``,
matching the datasets written by ``sr-record``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig
from lerobot.utils.constants import ACTION, OBS_IMAGES, OBS_STATE

from sr_imitation.envs.needle import GYM_NAMESPACE, MAX_EPISODE_STEPS
from sr_imitation.envs.needle.env import OBS_TYPES, STATE_DIM, NeedleEnvSettings
from sr_imitation.envs.needle.skills import SKILL_NAMES

WRIST_IMAGE_KEY = f"{OBS_IMAGES}.wrist"


@EnvConfig.register_subclass("needle")
@dataclass
class NeedleEnvConfig(EnvConfig):
    """LeRobot view of :class:`~sr_imitation.envs.needle.env.NeedleEnv`.

    Args:
        task: skill name (``approach, place, insert, regrasp, pullout``).
        fps: frame rate used for eval videos and recorded datasets.
        episode_length: truncation horizon (SurgicAI: 300).
        obs_type: ``pixels_agent_pos`` or ``agent_pos``.
        observation_height, observation_width: wrist image size.
        thresholds: success preset, ``learnable`` or ``surgicai``.
        reward_type: ``dense`` or ``sparse``.
        visualization_height, visualization_width: size of the scene-camera frames in eval videos.
    """

    task: str | None = "approach"
    fps: int = 30
    episode_length: int = MAX_EPISODE_STEPS
    obs_type: str = "pixels_agent_pos"
    observation_height: int = 96
    observation_width: int = 96
    thresholds: str = "learnable"
    reward_type: str = "dense"
    render_mode: str = "rgb_array"
    visualization_height: int = 240
    visualization_width: int = 320
    features: dict[str, PolicyFeature] = field(
        default_factory=lambda: {
            ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(7,)),
            "agent_pos": PolicyFeature(type=FeatureType.STATE, shape=(STATE_DIM,)),
        }
    )
    features_map: dict[str, str] = field(
        default_factory=lambda: {ACTION: ACTION, "agent_pos": OBS_STATE, "pixels/wrist": WRIST_IMAGE_KEY}
    )

    def __post_init__(self) -> None:
        if self.task not in SKILL_NAMES:
            raise ValueError(f"env.task must be one of {list(SKILL_NAMES)}, got {self.task!r}")
        if self.obs_type not in OBS_TYPES:
            raise ValueError(f"env.obs_type must be one of {OBS_TYPES}, got {self.obs_type!r}")
        if self.episode_length < 1:
            raise ValueError(f"env.episode_length must be >= 1, got {self.episode_length}")
        if self.fps < 1:
            raise ValueError(f"env.fps must be >= 1, got {self.fps}")
        NeedleEnvSettings(**self._env_kwargs())  # validates the remaining options
        if self.obs_type == "pixels_agent_pos":
            self.features["pixels/wrist"] = PolicyFeature(
                type=FeatureType.VISUAL, shape=(self.observation_height, self.observation_width, 3)
            )

    @property
    def package_name(self) -> str:
        return "sr_imitation.envs.needle"

    @property
    def gym_id(self) -> str:
        return f"{GYM_NAMESPACE}/{self.task}"

    def _env_kwargs(self) -> dict:
        return {
            "skill": self.task,
            "thresholds": self.thresholds,
            "reward_type": self.reward_type,
            "obs_type": self.obs_type,
            "image_height": self.observation_height,
            "image_width": self.observation_width,
            "render_mode": self.render_mode,
            "render_height": self.visualization_height,
            "render_width": self.visualization_width,
            "step_limit": self.episode_length,
            "camera_dict": True,
        }

    @property
    def gym_kwargs(self) -> dict:
        # ``max_episode_steps`` is consumed by gym.make (TimeLimit); the rest goes to NeedleEnv.
        return {**self._env_kwargs(), "max_episode_steps": self.episode_length}
