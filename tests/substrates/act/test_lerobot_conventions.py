"""LeRobot's conventions where a user expects them: ``--policy.*`` flags imply ``--policy.type=act_sr`` on
sr-train, ``--wake.max_epochs`` below ``--wake.min_epochs`` is answered with what to change."""

from __future__ import annotations

import pytest

from sr_imitation.substrates.act.cli import parse_train_args
from sr_imitation.substrates.act.wake import WakeConfig


def test_policy_flags_alone_imply_act_sr(tmp_path):
    cfg = parse_train_args(["--policy.dim_model=32", f"--output_dir={tmp_path / 'run'}"])
    assert cfg.policy.type == "act_sr" and cfg.policy.dim_model == 32


def test_max_epochs_below_min_epochs_says_what_to_change():
    with pytest.raises(ValueError, match=r"^wake.max_epochs=1 is below wake.min_epochs=30 .* give "
                                         r"--wake.min_epochs=1 too, or a wake.max_epochs >= 30$"):
        WakeConfig(max_epochs=1)
    with pytest.raises(ValueError, match="wake.min_epochs must be >= 1, got 0"):
        WakeConfig(min_epochs=0)
