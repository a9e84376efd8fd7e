"""ACT-SR LeRobot policy plugin (Sleeping Robots on LeRobot's ACT).

LeRobot imports this package automatically (distribution name prefix ``lerobot_policy_``) before it parses
``--policy.type``; importing it registers ``act_sr``. The environments (``--env.type=needle``,
``--env.type=sr_meta_world``) are the env plugin's, ``lerobot_env_sr`` (LeRobot 0.6 discovers ``lerobot_env_*``).
"""

from lerobot_policy_act_sr.configuration_act_sr import ACTSRConfig
from lerobot_policy_act_sr.modeling_act_sr import ACTSRPolicy
from lerobot_policy_act_sr.processor_act_sr import make_act_sr_pre_post_processors
from sr_imitation.infra.torchcodec_notice import quiet_torchcodec

__version__ = "0.2.0"

quiet_torchcodec()  # stock lerobot-* imports this plugin first: a missing FFmpeg is one line there too
__all__ = ["ACTSRConfig", "ACTSRPolicy", "make_act_sr_pre_post_processors"]
