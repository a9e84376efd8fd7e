"""ACT-SR processors: exactly ACT's (normalize, batch, device / unnormalize).

LeRobot 0.4.4 routes every ``ACTConfig`` subclass to ACT's processor factory (an ``isinstance`` check in
``lerobot.policies.factory.make_pre_post_processors``), so this function exists to honour the plugin naming
contract and for direct use. What ACT-SR adds is a *policy* for the statistics: the stream trainer fixes one
set of statistics for the whole stream (see ``sr_imitation.substrates.act.data.stream_stats``).
"""

from __future__ import annotations

from typing import Any

import torch
from lerobot.policies.act.processor_act import make_act_pre_post_processors

from lerobot_policy_act_sr.configuration_act_sr import ACTSRConfig


def make_act_sr_pre_post_processors(
    config: ACTSRConfig, dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None
) -> tuple[Any, Any]:
    """ACT's pre/post-processing pipelines for an ACT-SR config."""
    return make_act_pre_post_processors(config, dataset_stats=dataset_stats)
