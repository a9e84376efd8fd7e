"""ACT-SR LeRobot policy plugin (Sleeping Robots on LeRobot's ACT).

LeRobot 0.4.4 imports this package automatically (distribution name prefix ``lerobot_policy_``) before it parses
``--policy.type``; importing it registers ``act_sr``. It also registers this package's environments,
``--env.type=needle`` and ``--env.type=sr_meta_world`` (LeRobot 0.4.4 has no auto-discovery for environments, so the
plugin does it).
"""

import sr_imitation.envs.metaworld.lerobot_config  # noqa: F401  (registers --env.type=sr_meta_world with LeRobot)
import sr_imitation.envs.needle.lerobot_config  # noqa: F401  (registers --env.type=needle with LeRobot)
from lerobot_policy_act_sr.configuration_act_sr import ACTSRConfig
from lerobot_policy_act_sr.modeling_act_sr import ACTSRPolicy
from lerobot_policy_act_sr.processor_act_sr import make_act_sr_pre_post_processors

__version__ = "0.1.0"
__all__ = ["ACTSRConfig", "ACTSRPolicy", "make_act_sr_pre_post_processors"]
