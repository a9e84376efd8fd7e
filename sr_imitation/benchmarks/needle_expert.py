"""Scripted-expert success rates: N seeded episodes per skill and threshold preset.

    python -m sr_imitation.benchmarks.needle_expert --episodes=100

The targets: >= 95% with the ``learnable`` (default) thresholds and >= 90% with ``surgicai``.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sr_imitation.envs.needle import SKILL_NAMES, THRESHOLD_PRESETS, NeedleEnv
from sr_imitation.envs.needle.chained import run_chained_episode
from sr_imitation.envs.needle.expert import run_expert_episode
from sr_imitation.infra.cli_errors import run_cli
from sr_imitation.infra.cli_parsing import parse_command

PROG = "python -m sr_imitation.benchmarks.needle_expert"
"""The command as a user types it (usage errors and ``--help`` name it)."""


@dataclass
class ExpertBenchConfig:
    """Options.

    Args:
        episodes: seeded episodes per skill and preset (seeds ``seed .. seed + episodes - 1``).
        presets: threshold presets to evaluate.
        chained_episodes: also run this many chained (all five skills) episodes per preset.
        seed: first seed.
        output: optional JSON file for the numbers.
    """

    episodes: int = 100
    presets: list[str] = field(default_factory=lambda: ["learnable", "surgicai"])
    chained_episodes: int = 20
    seed: int = 0
    output: Path | None = None

    def __post_init__(self) -> None:
        if self.episodes < 1 or self.chained_episodes < 0:
            raise ValueError("episodes must be >= 1 and chained_episodes >= 0")
        unknown = set(self.presets) - set(THRESHOLD_PRESETS)
        if unknown:
            raise ValueError(f"unknown presets {sorted(unknown)}; expected {sorted(THRESHOLD_PRESETS)}")


def main(args: list[str] | None = None) -> dict:
    cfg = parse_command(ExpertBenchConfig, args, prog=PROG)
    results: dict = {}
    t0 = time.perf_counter()
    for preset in cfg.presets:
        rows = {}
        for skill in SKILL_NAMES:
            env = NeedleEnv(skill=skill, thresholds=preset, obs_type="agent_pos")
            runs = [run_expert_episode(env, seed=s) for s in range(cfg.seed, cfg.seed + cfg.episodes)]
            steps = np.array([r["steps"] for r in runs])
            rows[skill] = {
                "success_rate": float(np.mean([r["success"] for r in runs])),
                "steps_mean": float(steps.mean()),
                "steps_min": int(steps.min()),
                "steps_max": int(steps.max()),
            }
        if cfg.chained_episodes:
            seeds = range(cfg.seed, cfg.seed + cfg.chained_episodes)
            chained = [run_chained_episode(s, preset)[0] for s in seeds]
            rows["chained"] = {
                "success_rate": float(np.mean([c.all_success for c in chained])),
                "steps_mean": float(np.mean([sum(c.steps.values()) for c in chained])),
            }
        results[preset] = rows
    results["wall_s"] = time.perf_counter() - t0
    for preset in cfg.presets:
        print(f"\n{preset} thresholds, {cfg.episodes} episodes per skill (seeds {cfg.seed}..)")
        print("| skill | success | steps mean (min-max) |\n| --- | --- | --- |")
        for skill, row in results[preset].items():
            span = f" ({row['steps_min']}-{row['steps_max']})" if "steps_min" in row else ""
            print(f"| {skill} | {row['success_rate']:.0%} | {row['steps_mean']:.1f}{span} |")
    if cfg.output is not None:
        from sr_imitation.io import atomic_write_json

        atomic_write_json(cfg.output, results)
    else:
        print(json.dumps(results))
    return results


if __name__ == "__main__":
    run_cli(PROG, main)  # usage errors: one line
