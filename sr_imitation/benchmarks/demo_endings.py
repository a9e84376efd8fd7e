"""Where the scripted expert's demonstrations end, per skill and recording setting.

    python -m sr_imitation.benchmarks.demo_endings --episodes=40

For each setting (``sr-record``'s ``demo_threshold_scale`` and ``expert_jaw_close_mm``) and skill: expert success,
mean demo length, the mean final position and rotation error (a demo ends on the step success is first reached, so
these say how far inside the success region its last frames are) and, for the jaw skills, the mean position error
at the step the expert starts closing the jaw. Seeds ``0 .. episodes - 1``; no rendering.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np

from sr_imitation.envs.needle import SKILL_NAMES, NeedleEnv
from sr_imitation.envs.needle.expert import ExpertSettings, NeedleExpert
from sr_imitation.infra.cli_errors import run_cli
from sr_imitation.infra.cli_parsing import parse_command

PROG = "python -m sr_imitation.benchmarks.demo_endings"
"""The command as a user types it (usage errors and ``--help`` name it)."""


@dataclass
class DemoEndingsConfig:
    episodes: int = 40
    """Seeded expert episodes per skill and setting."""
    settings: list[list[float]] = field(default_factory=lambda: [[1.0, 1.5], [0.5, 0.5]])
    """(demo_threshold_scale, expert_jaw_close_mm) pairs; the first is SurgicAI's demos."""


def demo_ending(skill: str, scale: float, jaw_close_mm: float, seed: int) -> dict[str, float]:
    env = NeedleEnv(skill=skill, obs_type="agent_pos", threshold_scale=scale)
    env.reset(seed=seed)
    expert = NeedleExpert(env, seed=seed, settings=ExpertSettings(jaw_close_cm=jaw_close_mm / 10.0))
    expert.reset()
    close_mm, steps = float("nan"), 0
    while True:
        action = expert.act()
        if action[6] < 0 and np.isnan(close_mm):
            close_mm = 1000.0 * float(np.linalg.norm(env.setpoints[env.active_arm][:3] - env.goal[:3]))
        _, _, terminated, truncated, info = env.step(action)
        steps += 1
        if terminated or truncated:
            return {"success": float(info["is_success"]), "steps": steps, "position_mm": info["position_error_mm"],
                    "rotation_deg": info["rotation_error_deg"], "jaw_close_at_mm": close_mm}


def main(args: list[str] | None = None) -> None:
    cfg = parse_command(DemoEndingsConfig, args, prog=PROG)
    rows = []
    print("| demo_threshold_scale | expert_jaw_close_mm | skill | success | steps | final position (mm) | "  # noqa: T201
          "final rotation (deg) | jaw closing starts at (mm) |\n|---|---|---|---|---|---|---|---|")
    for scale, jaw in cfg.settings:
        for skill in SKILL_NAMES:
            runs = [demo_ending(skill, scale, jaw, seed) for seed in range(cfg.episodes)]
            mean = {k: float(np.nanmean([r[k] for r in runs])) if any(np.isfinite(r[k]) for r in runs)
                    else float("nan") for k in runs[0]}
            rows.append({"demo_threshold_scale": scale, "expert_jaw_close_mm": jaw, "skill": skill, **mean})
            close = "-" if np.isnan(mean["jaw_close_at_mm"]) else f"{mean['jaw_close_at_mm']:.2f}"
            print(f"| {scale} | {jaw} | {skill} | {mean['success']:.2f} | {mean['steps']:.1f} | "  # noqa: T201
                  f"{mean['position_mm']:.2f} | {mean['rotation_deg']:.2f} | {close} |")
    print(json.dumps(rows))  # noqa: T201


if __name__ == "__main__":
    run_cli(PROG, main)  # usage errors: one line
