"""Chained mode: the expert performs all five skills in one episode (a full suture), e.g. for a video.

Like SurgicAI's chained env (spec §3.6) each skill starts from where the previous one ended; the only scripted
switch is PSM2 opening its jaw when PULLOUT begins (hand-over). Run::

    python -m sr_imitation.envs.needle.chained --output=outputs/needle_suture.mp4 --seed=0
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sr_imitation.envs.needle.env import NeedleEnv
from sr_imitation.envs.needle.expert import NeedleExpert
from sr_imitation.envs.needle.skills import SKILL_NAMES, Skill
from sr_imitation.infra.cli_errors import run_cli, setup_logging
from sr_imitation.infra.cli_parsing import parse_command
from sr_imitation.offscreen import setup_offscreen_rendering

logger = logging.getLogger(__name__)
PROG = "python -m sr_imitation.envs.needle.chained"
"""The command as a user types it (usage errors and ``--help`` name it)."""


@dataclass
class ChainedRunResult:
    """Per-skill outcome of a chained episode."""

    steps: dict[str, int] = field(default_factory=dict)
    success: dict[str, bool] = field(default_factory=dict)

    @property
    def all_success(self) -> bool:
        return len(self.success) == len(SKILL_NAMES) and all(self.success.values())


def _compose(scene: np.ndarray, wrist: np.ndarray) -> np.ndarray:
    """Scene frame with the wrist view inset in the top-left corner (2 px white border)."""
    out = scene.copy()
    h, w = wrist.shape[:2]
    out[: h + 4, : w + 4] = 255
    out[2 : h + 2, 2 : w + 2] = wrist
    return out


def run_chained_episode(
    seed: int,
    thresholds: str = "learnable",
    render: bool = False,
    height: int = 240,
    width: int = 320,
    wrist_size: int = 80,
) -> tuple[ChainedRunResult, list[np.ndarray]]:
    """Run approach -> place -> insert -> regrasp -> pullout with the expert; frames only if ``render``."""
    env = NeedleEnv(
        skill=Skill.APPROACH.value,
        thresholds=thresholds,
        obs_type="agent_pos",
        render_mode="rgb_array" if render else None,
        render_height=height,
        render_width=width,
    )
    result, frames = ChainedRunResult(), []

    def snapshot() -> None:
        if render:
            frames.append(_compose(env.render(), env.render_camera("wrist", wrist_size, wrist_size)))

    try:
        env.reset(seed=seed)
        snapshot()
        for k, skill in enumerate(SKILL_NAMES):
            if k > 0:
                env.continue_with(skill)
            expert = NeedleExpert(env, seed=seed * 10 + k)
            expert.reset()
            steps, info = 0, {"is_success": False}
            while True:
                _, _, terminated, truncated, info = env.step(expert.act())
                steps += 1
                snapshot()
                if terminated or truncated:
                    break
            result.steps[skill] = steps
            result.success[skill] = bool(info["is_success"])
            if not info["is_success"]:
                logger.warning("chained episode (seed %d) failed at %s", seed, skill)
                break
    finally:
        env.close()
    return result, frames


@dataclass
class ChainedVideoConfig:
    """Options of the full-suture video CLI.

    Args:
        output: mp4 path.
        seed: episode seed.
        thresholds: success preset.
        height, width: scene-camera frame size (even numbers).
        fps: video frame rate.
    """

    output: Path = Path("outputs/needle_suture.mp4")
    seed: int = 0
    thresholds: str = "learnable"
    height: int = 480
    width: int = 640
    fps: int = 30

    def __post_init__(self) -> None:
        if self.height % 2 or self.width % 2 or min(self.height, self.width) < 64:
            raise ValueError(f"height and width must be even and >= 64, got {self.height}x{self.width}")
        if self.fps < 1:
            raise ValueError(f"fps must be >= 1, got {self.fps}")


def main(args: list[str] | None = None) -> None:
    setup_offscreen_rendering()
    from sr_imitation.video import write_mp4

    cfg = parse_command(ChainedVideoConfig, args, prog=PROG)
    setup_logging()
    result, frames = run_chained_episode(
        cfg.seed, cfg.thresholds, render=True, height=cfg.height, width=cfg.width, wrist_size=cfg.height // 4
    )
    path = write_mp4(cfg.output, frames, fps=cfg.fps)
    print(f"steps per skill {result.steps}, success {result.success}")  # noqa: T201
    print(f"wrote {path.resolve()}")  # noqa: T201


if __name__ == "__main__":
    run_cli(PROG, main)  # usage errors: one line
