"""Needle environment speed: env steps/s without rendering, wrist-camera fps, demo-recording wall time.

    python -m sr_imitation.benchmarks.needle_env                       # steps/s and fps
    python -m sr_imitation.benchmarks.needle_env --record_episodes=20  # + timed sr-record, all five skills

Targets: >= 20,000 steps/s on one core, >= 1,000 wrist fps at 96x96 and >= 100 at 640x480,
<= 10 minutes to record 100 demos x 5 skills at 96x96 on 2 cores.
"""

from __future__ import annotations

import os

from sr_imitation.offscreen import setup_offscreen_rendering

setup_offscreen_rendering()

import json  # noqa: E402
import platform  # noqa: E402
import shutil  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402

from sr_imitation.envs.needle import SKILL_NAMES, NeedleEnv, gym_id  # noqa: E402
from sr_imitation.infra.cli_errors import run_cli  # noqa: E402
from sr_imitation.infra.cli_parsing import parse_command  # noqa: E402

PROG = "python -m sr_imitation.benchmarks.needle_env"
"""The command as a user types it (usage errors and ``--help`` name it)."""


@dataclass
class NeedleBenchConfig:
    """Options.

    Args:
        steps: env steps per skill for the steps/s measurement.
        frames: rendered frames per resolution.
        record_episodes: if > 0, time ``sr-record`` with this many demos per skill (96x96); the result is
            also extrapolated linearly to 100 demos per skill.
        seed: seed for actions and resets.
        output: optional JSON file for the numbers.
    """

    steps: int = 20_000
    frames: int = 500
    record_episodes: int = 0
    seed: int = 0
    output: Path | None = None

    def __post_init__(self) -> None:
        if self.steps < 1 or self.frames < 1 or self.record_episodes < 0:
            raise ValueError("steps and frames must be >= 1 and record_episodes >= 0")


def _steps_per_second(env, steps: int, seed: int) -> float:
    actions = np.random.default_rng(seed).uniform(-1, 1, size=(steps, 7)).astype(np.float32)
    env.reset(seed=seed)
    t0 = time.perf_counter()
    for a in actions:
        _, _, terminated, truncated, _ = env.step(a)
        if terminated or truncated:
            env.reset()
    return steps / (time.perf_counter() - t0)


def bench_steps(cfg: NeedleBenchConfig) -> dict:
    raw, wrapped = {}, {}
    for skill in SKILL_NAMES:
        env = NeedleEnv(skill=skill, obs_type="agent_pos")
        raw[skill] = _steps_per_second(env, cfg.steps, cfg.seed)
        env = gym.make(gym_id(skill), obs_type="agent_pos")
        wrapped[skill] = _steps_per_second(env, cfg.steps, cfg.seed)
        env.close()
    return {"steps_per_s_raw": raw, "steps_per_s_gym_make": wrapped}


def bench_render(cfg: NeedleBenchConfig) -> dict:
    out = {}
    for h, w in ((96, 96), (480, 640)):
        env = NeedleEnv(skill="approach", obs_type="agent_pos")
        try:
            env.reset(seed=cfg.seed)
            env.render_camera("wrist", h, w)  # create the context outside the timing
            rng = np.random.default_rng(cfg.seed)
            t0 = time.perf_counter()
            for _ in range(cfg.frames):
                _, _, terminated, truncated, _ = env.step(rng.uniform(-0.3, 0.3, size=7))
                if terminated or truncated:
                    env.reset()
                env.render_camera("wrist", h, w)
            out[f"wrist_fps_{w}x{h}"] = cfg.frames / (time.perf_counter() - t0)
        finally:
            env.close()
    return out


def bench_record(cfg: NeedleBenchConfig) -> dict:
    from sr_imitation.recorders.needle import RecordConfig, record

    tmp = Path(tempfile.mkdtemp(prefix="sr_needle_bench_"))
    try:
        t0 = time.perf_counter()
        record(RecordConfig(num_episodes=cfg.record_episodes, root=tmp, image_size=96, seed=cfg.seed))
        wall = time.perf_counter() - t0
        frames = sum(int(json.loads((tmp / s / "meta" / "info.json").read_text())["total_frames"])
                     for s in SKILL_NAMES)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return {
        "record_episodes_per_skill": cfg.record_episodes,
        "record_wall_s": wall,
        "record_frames": frames,
        "record_wall_s_extrapolated_to_100": wall * 100.0 / cfg.record_episodes,
    }


def main(args: list[str] | None = None) -> dict:
    cfg = parse_command(NeedleBenchConfig, args, prog=PROG)
    results = {"machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs",
               "mujoco_gl": os.environ.get("MUJOCO_GL")}
    results.update(bench_steps(cfg))
    results.update(bench_render(cfg))
    if cfg.record_episodes:
        results.update(bench_record(cfg))
    print(json.dumps(results, indent=2))
    if cfg.output is not None:
        from sr_imitation.io import atomic_write_json

        atomic_write_json(cfg.output, results)
    return results


if __name__ == "__main__":
    run_cli(PROG, main)  # usage errors: one line
