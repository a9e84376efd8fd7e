"""LeRobot env plugin: registers ``--env.type=needle`` and ``--env.type=sr_meta_world`` with LeRobot.

LeRobot 0.6 imports this package by itself (distribution name prefix ``lerobot_env_``) in ``lerobot-train``,
``lerobot-eval`` and its other scripts, before it parses ``--env.type``. LeRobot's own ``--env.type=metaworld`` is not
used for MT5: it gives a policy 4 of Meta-World's 39 numbers (hand and gripper; its ``state`` mode is not
implemented), while our MT5 datasets and the policies trained on them read all 39, so ``sr_meta_world`` evaluates
them (:mod:`sr_imitation.envs.metaworld.lerobot_config`).
"""

from sr_imitation.envs.metaworld.lerobot_config import MetaWorldStateEnvConfig
from sr_imitation.envs.needle.lerobot_config import NeedleEnvConfig
from sr_imitation.infra.torchcodec_notice import quiet_torchcodec

__version__ = "0.2.0"

quiet_torchcodec()  # stock lerobot-* imports this plugin first: a missing FFmpeg is one line there too
__all__ = ["MetaWorldStateEnvConfig", "NeedleEnvConfig"]
