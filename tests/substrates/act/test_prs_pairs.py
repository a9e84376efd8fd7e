"""``--stream.pairs``: an unknown name is refused when the config is built (not at the report, after the whole
stream), and a list with no pair of the stream's skills is named before the run (PRS would be n/a)."""

from __future__ import annotations

import pytest

from sr_imitation.substrates.act.config import StreamConfig
from sr_imitation.substrates.act.report import no_pairs_warning, pair_list

MT5 = ["reach-v3", "door-open-v3", "drawer-open-v3", "window-close-v3", "button-press-topdown-v3"]


def test_an_unknown_pair_list_is_one_line_naming_the_key():
    with pytest.raises(ValueError, match=r"^stream\.pairs must be one of \('surgicai', 'mt5', 'all', 'adjacent'\), "
                                         r"got 'mt8'$"):
        StreamConfig(skills=MT5, pairs="mt8")


def test_a_pair_list_without_a_pair_of_the_stream_is_named_with_the_lists_that_have_one():
    assert pair_list("surgicai", MT5) == []
    why = no_pairs_warning("surgicai", MT5)
    assert why is not None and why.startswith("--stream.pairs=surgicai names no pair of the skills ['reach-v3'")
    assert "PRS (Eq. 5) will be n/a; --stream.pairs=mt5" in why
    assert len(pair_list("mt5", MT5)) == 6 and no_pairs_warning("mt5", MT5) is None
    assert no_pairs_warning("surgicai", MT5[:1]) is None  # one skill: PRS is n/a by definition, nothing to choose
    assert no_pairs_warning("adjacent", ["a", "b"]) is None
