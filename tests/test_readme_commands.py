"""README's stock LeRobot route parses as LeRobot parses it (issue 60: "run as written").

The commands are read from README.md by the same extractor ``tools/check_readme_routes.py`` uses to run them on a fresh
clone (that whole run is an hour of CPU and lives outside the suite; these checks catch a flag LeRobot refuses, as
``--eval.n_episodes=10`` under LeRobot's default eval batch of 50 was, in seconds)."""

from __future__ import annotations

import shlex
from pathlib import Path

import draccus
import pytest

from tests.tool_loader import load_tool

ROOT = Path(__file__).resolve().parents[1]


def _routes():
    return load_tool("check_readme_routes")


@pytest.fixture(scope="module")
def stock_route() -> list[list[str]]:
    (block,) = _routes().bash_blocks_after((ROOT / "README.md").read_text(), "**The LeRobot workflow", 1)
    return [shlex.split(command) for command in block]


def test_the_stock_route_is_the_whole_workflow(stock_route):
    assert [argv[0] for argv in stock_route] == ["sr-record", "lerobot-train", "lerobot-train", "sr-sleep",
                                                 "lerobot-eval"]


def test_lerobot_eval_accepts_the_stock_routes_evaluation_flags(stock_route):
    from lerobot.configs.default import EvalConfig

    for argv in stock_route:
        if argv[0] == "lerobot-eval":
            flags = ["--" + a.removeprefix("--eval.") for a in argv[1:] if a.startswith("--eval.")]
            cfg = draccus.parse(EvalConfig, args=flags)  # LeRobot's own checks run in its __post_init__
            assert cfg.batch_size <= cfg.n_episodes


def test_lerobot_train_parses_the_first_wake_as_the_cpu_presets_small_act(stock_route):
    from lerobot.configs.train import TrainPipelineConfig

    from lerobot_policy_act_sr import ACTSRConfig  # registers act_sr, as LeRobot's plugin discovery does

    first = next(argv for argv in stock_route if argv[0] == "lerobot-train")
    cfg = draccus.parse(TrainPipelineConfig, args=first[1:])
    assert isinstance(cfg.policy, ACTSRConfig) and cfg.policy.sleep and not cfg.policy.use_images
    assert (cfg.policy.dim_model, cfg.batch_size, cfg.steps) == (128, 32, 2000)
