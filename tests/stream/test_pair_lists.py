"""The paper's pre-registered PRS pair lists live with their substrates (the core knows no benchmark)."""

from __future__ import annotations

import numpy as np
import pytest

from sr_imitation.core.metrics import prs_curve
from sr_imitation.envs.metaworld.tasks import MT5_PAIRS, STREAMS, canonical_skill
from sr_imitation.envs.needle.skills import PRS_PAIRS, SKILL_NAMES
from sr_imitation.substrates.act.report import pair_list
from sr_imitation.substrates.sac.trainer import prs_pairs


def test_paper_pair_lists_match_their_streams():
    assert len(MT5_PAIRS) == 6 and len(PRS_PAIRS) == 7
    full = np.tril(np.full((5, 5), 0.5))
    mt5 = [canonical_skill(s) for s in STREAMS["mt5"]]
    assert prs_curve(full, mt5, MT5_PAIRS)[-1] == 0.5
    assert prs_curve(full, list(SKILL_NAMES), PRS_PAIRS)[-1] == 0.5
    with pytest.raises(ValueError, match="not in the stream"):
        prs_curve(full, list(SKILL_NAMES), MT5_PAIRS)


def test_each_substrate_chooses_its_pairs():
    assert prs_pairs(list(STREAMS["mt5-reverse"])) == MT5_PAIRS
    assert len(prs_pairs(list(STREAMS["mt8"]))) == 28
    assert pair_list("surgicai", ["approach", "place", "insert"]) == [("approach", "place"), ("place", "insert"),
                                                                      ("approach", "insert")]
    assert canonical_skill("door-open-v3") == "door-open" and canonical_skill("approach") == "approach"
