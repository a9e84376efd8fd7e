"""MuJoCo rebuild of SurgicAI's five-skill needle-suturing stream (``shared/notes/surgicai-needle-spec.md``).

Importing this package registers one gymnasium id per skill, ``sr_needle/<skill>``,
with SurgicAI's 300-step limit. It does not import LeRobot; the LeRobot ``EnvConfig`` is in
:mod:`sr_imitation.envs.needle.lerobot_config`.
"""

import gymnasium as gym

from sr_imitation.envs.needle.env import NeedleEnv, NeedleEnvSettings
from sr_imitation.envs.needle.skills import SKILL_NAMES, SKILLS, THRESHOLD_PRESETS, Skill

GYM_NAMESPACE = "sr_needle"
MAX_EPISODE_STEPS = 300


def gym_id(skill: str) -> str:
    """Gymnasium id of a skill, e.g. ``sr_needle/approach``."""
    return f"{GYM_NAMESPACE}/{skill}"


for _name in SKILL_NAMES:
    if gym_id(_name) not in gym.registry:
        gym.register(
            id=gym_id(_name),
            entry_point="sr_imitation.envs.needle.env:NeedleEnv",
            max_episode_steps=MAX_EPISODE_STEPS,
            kwargs={"skill": _name},
        )

__all__ = ["NeedleEnv", "NeedleEnvSettings", "Skill", "SKILLS", "SKILL_NAMES", "THRESHOLD_PRESETS", "gym_id"]
