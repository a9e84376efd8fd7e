"""ACT-SR processors: exactly ACT's (normalize, batch, device / unnormalize).

LeRobot 0.6 finds this function by its name (``make_<type>_pre_post_processors`` in the policy's ``processor_*``
module, ``lerobot.policies.factory``), so it is what ``lerobot-train`` and ``lerobot-eval`` build ``act_sr``'s
processors with (0.4.4 routed every ``ACTConfig`` subclass to ACT's factory instead; the result is the same).
What ACT-SR adds is a *policy* for the statistics: the stream trainer fixes one set of statistics for the whole
stream (see ``sr_imitation.substrates.act.data.stream_stats``).
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
