"""LeRobot ``EnvConfig`` for this package's Meta-World view: ``lerobot-eval --env.type=sr_meta_world
--env.task=reach-v3 --policy.path=...``.

LeRobot's own ``--env.type=metaworld`` gives a policy the hand and gripper only (``agent_pos`` = the first 4 of
Meta-World's 39 numbers) and a 480 x 480 image; the datasets ``sr-record --env=metaworld`` writes, and so the
policies trained on them, read Meta-World's whole 39-number observation (goal visible, as its MT benchmarks give it):
this type evaluates them with stock ``lerobot-eval`` in exactly the environment ``sr-train --eval.env=metaworld``
uses (:class:`~sr_imitation.envs.metaworld.env.MetaWorldEnv`: configurations the scripted policy solves, success =
Meta-World's ``info["success"]``, the episode ending at the first success). LeRobot 0.6 imports it through the env
plugin ``lerobot_env_sr``.

Observation keys map as ``agent_pos -> observation.state`` and ``pixels/<camera> -> observation.images.<camera>``,
matching ``sr-record --env=metaworld`` (``--camera=<camera>`` for images). The gym id ``sr_meta_world/<task>`` is
registered when a config is built (the task is checked against Meta-World's names first, a close one suggested).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig
from lerobot.utils.constants import ACTION, OBS_IMAGES, OBS_STATE

from sr_imitation.envs.metaworld.env import DEFAULT_CAMERA, OBS_TYPES, MetaWorldEnv
from sr_imitation.envs.metaworld.tasks import ACT_DIM, OBS_DIM, check_task

ENV_TYPE = "sr_meta_world"
"""``--env.type`` and the gym namespace (``sr_meta_world/<task>``)."""


def gym_id(task: str) -> str:
    """The gym id of ``task``: ``sr_meta_world/reach-v3``."""
    return f"{ENV_TYPE}/{task}"


def make_env(task: str, episode_length: int = 200, **kwargs: Any) -> MetaWorldEnv:
    """The gym entry point of ``sr_meta_world/<task>``: a :class:`MetaWorldEnv` whose own time limit is the
    config's ``episode_length`` (``gym.make`` consumes ``max_episode_steps`` for its TimeLimit wrapper)."""
    return MetaWorldEnv(task, max_episode_steps=episode_length, **kwargs)


def register(task: str) -> str:
    """Register ``sr_meta_world/<task>`` with gymnasium (once) and return the id."""
    name = gym_id(task)
    if name not in gym.registry:
        gym.register(id=name, entry_point=f"{__name__}:make_env", kwargs={"task": task})
    return name


@EnvConfig.register_subclass(ENV_TYPE)
@dataclass
class MetaWorldStateEnvConfig(EnvConfig):
    """LeRobot view of :class:`~sr_imitation.envs.metaworld.env.MetaWorldEnv` (module docstring).

    Args:
        task: a Meta-World v3 task with a scripted policy (``reach-v3``, ``door-open-v3``, ...).
        fps: frame rate of the evaluation videos (Meta-World's 80).
        episode_length: time limit in steps (``sr-train``'s ``--eval.max_steps`` default, 200).
        obs_type: ``agent_pos`` (the 39 numbers) or ``pixels_agent_pos`` (also a camera image, as
            ``sr-record --camera``).
        camera: the Meta-World camera of the image and of the evaluation videos.
        observation_height, observation_width: camera image size (``sr-record --image_size``).
        visualization_height, visualization_width: size of the evaluation video frames.
        task_seed: ``metaworld.MT1(task, seed=task_seed)``'s configurations (``sr-record``'s 0).
        demonstrable_only: draw only configurations Meta-World's scripted policy solves (``sr-train``'s evaluation).
    """

    task: str | None = "reach-v3"
    fps: int = 80
    episode_length: int = 200
    obs_type: str = "agent_pos"
    camera: str = DEFAULT_CAMERA
    observation_height: int = 64
    observation_width: int = 64
    visualization_height: int = 240
    visualization_width: int = 320
    task_seed: int = 0
    demonstrable_only: bool = True
    render_mode: str = "rgb_array"
    features: dict[str, PolicyFeature] = field(
        default_factory=lambda: {
            ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(ACT_DIM,)),
            "agent_pos": PolicyFeature(type=FeatureType.STATE, shape=(OBS_DIM,)),
        }
    )
    features_map: dict[str, str] = field(default_factory=lambda: {ACTION: ACTION, "agent_pos": OBS_STATE})

    def __post_init__(self) -> None:
        if self.task is None:
            raise ValueError("env.task: give a Meta-World v3 task, e.g. reach-v3")
        try:
            check_task(self.task)
        except ValueError as exc:
            raise ValueError(f"env.task: {exc}") from None
        if self.obs_type not in OBS_TYPES:
            raise ValueError(f"env.obs_type must be one of {OBS_TYPES}, got {self.obs_type!r}")
        for name in ("episode_length", "fps", "observation_height", "observation_width", "visualization_height",
                     "visualization_width"):
            if getattr(self, name) < 1:
                raise ValueError(f"env.{name} must be >= 1, got {getattr(self, name)}")
        from sr_imitation.envs.metaworld.video import CAMERAS

        if self.camera not in CAMERAS:
            raise ValueError(f"env.camera must be one of {list(CAMERAS)}, got {self.camera!r}")
        if self.obs_type == "pixels_agent_pos":
            pixels = f"pixels/{self.camera}"
            self.features[pixels] = PolicyFeature(
                type=FeatureType.VISUAL, shape=(self.observation_height, self.observation_width, 3))
            self.features_map[pixels] = f"{OBS_IMAGES}.{self.camera}"
        register(self.task)

    @property
    def package_name(self) -> str:
        return __name__

    @property
    def gym_id(self) -> str:
        return gym_id(self.task)

    @property
    def gym_kwargs(self) -> dict:
        # ``max_episode_steps`` goes to gym.make's TimeLimit; the rest to make_env and MetaWorldEnv.
        return {"episode_length": self.episode_length, "max_episode_steps": self.episode_length,
                "obs_type": self.obs_type, "camera": self.camera, "image_height": self.observation_height,
                "image_width": self.observation_width, "render_mode": self.render_mode,
                "render_height": self.visualization_height, "render_width": self.visualization_width,
                "task_seed": self.task_seed, "demonstrable_only": self.demonstrable_only}
