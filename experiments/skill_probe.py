"""Probe of the base learner: one skill's wake from scratch, evaluated right after it (what the stream's
after-own-wake row measures, without the stream around it), under chosen normalization statistics.

    python -m experiments.skill_probe --preset=configs/needle_cpu.json \\
        --skills=[place,insert,regrasp] --stats=[own,first,union] --seeds=[0] --output_root=outputs/skill_probe \\
        --extra=[--wake.max_epochs=20,--wake.min_epochs=20]

``stats``: ``own`` (the probed skill's dataset), ``first`` (the preset stream's first skill's: what
``--stream.stats=first`` gives every later skill), ``union`` (all the preset stream's datasets). The wake is the
substrate's own (the preset's policy, wake budget and seeds; ``--extra`` adds ``sr-train`` flags) and the evaluation
uses the skill's position in the preset's stream, so its episodes are those of the stream's evaluations. Each probe
goes to ``<output_root>/<skill>_<stats>_seed<seed>/`` (checkpoint, ``eval.json``, trajectories, rollout video,
``probe.json``); finished probes are skipped. ``probe.md`` / ``probe.json`` in ``output_root`` list the success,
per evaluation seed, and the failed episodes' final state: position and rotation error (the geodesic angle between
the tool's and the goal's orientation) and the jaw, which is how the failure modes in docs/RESULTS.md were found;
and the RMS of each input modality's features after the wake (the state tokens' projections, each camera's
backbone feature map, the encoder output) on :data:`FEATURE_FRAMES` demonstration frames, which is how the vision
backbone's unnormalized features were found (``--extra=[--policy.backbone_norm=frozen_batch]`` shows them).
"""

from __future__ import annotations

import copy
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sr_imitation.envs.needle import geometry as G
from sr_imitation.infra.cli_errors import run_cli, setup_logging
from sr_imitation.infra.cli_parsing import parse_command
from sr_imitation.io import atomic_write_bytes, read_checked_json, write_checked_json
from sr_imitation.main_job import preset_with_datasets
from sr_imitation.offscreen import setup_offscreen_rendering
from sr_imitation.stream.config import check_choices
from sr_imitation.substrates.act.data import load_metadata
from sr_imitation.substrates.act.evaluate import evaluate_skills
from sr_imitation.substrates.act.substrate import ACTSubstrate
from sr_imitation.substrates.act.trainer import TrainStreamConfig

logger = logging.getLogger(__name__)
PROG = "python -m experiments.skill_probe"
"""The command as a user types it (usage errors and ``--help`` name it)."""

STATS = ("own", "first", "union")
FEATURE_FRAMES = 64
"""Demonstration frames the feature RMS is measured on."""


@dataclass
class ProbeConfig:
    preset: Path = Path("configs/needle_cpu.json")
    """The sr-main preset: its policy, wake budget, evaluation and recorded datasets."""
    skills: list[str] = field(default_factory=lambda: ["place", "insert", "regrasp"])
    """Skills to probe (each must be in the preset's stream)."""
    stats: list[str] = field(default_factory=lambda: ["own", "first"])
    """Normalization statistics to probe under (own, first, union)."""
    seeds: list[int] = field(default_factory=lambda: [0])
    """Training seeds."""
    output_root: Path = Path("outputs/skill_probe")
    """Where the probes and the tables go."""
    extra: list[str] = field(default_factory=list)
    """sr-train flags added to every probe (e.g. --wake.max_epochs=20)."""

    def __post_init__(self) -> None:
        check_choices("stats", self.stats, STATS)


class ProbeSubstrate(ACTSubstrate):
    """The ACT substrate on a one-skill stream, normalized with the statistics of ``stats_from`` datasets."""

    def __init__(self, cfg: TrainStreamConfig, stats_from: list[tuple[Path, str]], make_env: Any = None) -> None:
        super().__init__(cfg, make_env)
        self.stats_from = stats_from

    def stats_metas(self, first_meta: Any) -> list[Any]:
        return [load_metadata(path, repo_id) for path, repo_id in self.stats_from]


def final_errors(state: np.ndarray) -> dict[str, float]:
    """Position error (mm), geodesic rotation error (deg) and jaw of a needle ``agent_pos`` (cur, goal, ...);
    nothing for a state of another layout."""
    if state.shape[0] < 14:
        return {}
    cur, goal = state[0:7], state[7:14]
    rotation = G.rotation_angle(G.rpy_to_matrix(*cur[3:6]), G.rpy_to_matrix(*goal[3:6]))
    return {"position_mm": float(10.0 * np.linalg.norm(goal[:3] - cur[:3])),
            "rotation_deg": float(math.degrees(rotation)), "jaw": float(cur[6])}


def run_probe(base: TrainStreamConfig, skill: str, stats: str, seed: int, out: Path, make_env: Any = None
              ) -> dict[str, Any]:
    """One probe in ``out`` (skipped when its ``probe.json`` exists); returns its record."""
    if (out / "probe.json").is_file():
        return read_checked_json(out / "probe.json")
    stream = base.stream
    position = stream.skills.index(skill)
    sources = {"own": [position], "first": [0], "union": list(range(len(stream.skills)))}[stats]
    cfg = copy.deepcopy(base)
    cfg.stream.skills, cfg.stream.dataset_paths = [skill], [stream.dataset_path(position)]
    cfg.seed, cfg.output_dir, cfg.method = seed, out, "sequential_bc"
    substrate = ProbeSubstrate(cfg, [(stream.dataset_path(i), stream.repo_id(i)) for i in sources], make_env)
    out.mkdir(parents=True, exist_ok=True)
    substrate.setup()
    substrate.begin_phase(0, "wake", substrate.phase_seed(0, "wake"))
    wake, files = substrate.wake(0, [], 0.0)
    substrate.save_policy(0, "wake", files)
    substrate.begin_phase(0, "wake.eval", substrate.phase_seed(0, "wake.eval"))
    evaluation = evaluate_skills(substrate.policy, substrate.preprocessor, substrate.postprocessor, [skill],
                                 [position], substrate.make_env, cfg.eval, out / "videos", cfg.progress)[skill]
    failures = [final_errors(t[-1]) for t, n in zip(evaluation.trajectories, evaluation.episode_lengths, strict=True)
                if n >= cfg.eval.max_steps]
    result = {"skill": skill, "stats": stats, "seed": seed, "success": evaluation.success,
              "success_per_seed": evaluation.success_per_seed, "wake_steps": wake["steps"],
              "wake_seconds": wake["seconds"], "failures": failures, "feature_rms": feature_rms(substrate)}
    write_checked_json(out / "probe.json", result)
    return result


def feature_rms(substrate: ACTSubstrate) -> dict[str, float]:
    """RMS of each modality's features of the current policy (see :meth:`ACTSRPolicy.action_chunk_and_features`) on
    :data:`FEATURE_FRAMES` of the skill's demonstration frames (after the evaluation: it draws nothing the probe
    uses)."""
    frames = substrate.state_sample(0, FEATURE_FRAMES)
    batch = {key: torch.cat([f[key] for f in frames]) for key in frames[0] if isinstance(frames[0][key], torch.Tensor)}
    with torch.no_grad():
        _, features = substrate.chunk_and_features(batch)
    return {name: float(f.float().pow(2).mean().sqrt()) for name, f in sorted(features.items())}


def _mean(rows: list[dict[str, float]], key: str) -> str:
    values = [r[key] for r in rows if key in r]
    return "-" if not values else f"{np.mean(values):.2f}"


def render(results: list[dict[str, Any]]) -> str:
    lines = ["Success right after the skill's own wake (mean over evaluation seeds) and the failed episodes' final "
             "state (means).", "",
             "| skill | stats | seed | success | per evaluation seed | failed | position (mm) | rotation (deg) | jaw |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        f = r["failures"]
        lines.append(f"| {r['skill']} | {r['stats']} | {r['seed']} | {r['success']:.3f} | "
                     f"{', '.join(f'{x:.2f}' for x in r['success_per_seed'])} | {len(f)} | {_mean(f, 'position_mm')} "
                     f"| {_mean(f, 'rotation_deg')} | {_mean(f, 'jaw')} |")
    scales = [r for r in results if r.get("feature_rms")]
    if scales:
        names = sorted({n for r in scales for n in r["feature_rms"]})
        lines += ["", f"Feature RMS after the wake ({FEATURE_FRAMES} demonstration frames):", "",
                  "| skill | stats | seed | " + " | ".join(names) + " |", "|---|---|---|" + "---|" * len(names)]
        lines += [f"| {r['skill']} | {r['stats']} | {r['seed']} | "
                  + " | ".join(f"{r['feature_rms'][n]:.3g}" if n in r["feature_rms"] else "-" for n in names) + " |"
                  for r in scales]
    return "\n".join(lines) + "\n"


def run(cfg: ProbeConfig, make_env: Any = None) -> list[dict[str, Any]]:
    main = preset_with_datasets(cfg.preset, cfg.extra)
    unknown = [s for s in cfg.skills if s not in main.train.stream.skills]
    if unknown:
        raise ValueError(f"skills: {unknown} are not in the preset's stream {main.train.stream.skills}")
    results = []
    for skill in cfg.skills:
        for stats in cfg.stats:
            for seed in cfg.seeds:
                out = cfg.output_root / f"{skill}_{stats}_seed{seed}"
                logger.info("=== probe %s, %s statistics, seed %d -> %s", skill, stats, seed, out)
                results.append(run_probe(main.train, skill, stats, seed, out, make_env))
    write_checked_json(cfg.output_root / "probe.json", {"probes": results})
    atomic_write_bytes(cfg.output_root / "probe.md", render(results).encode())
    return results


def main(args: list[str] | None = None) -> None:
    setup_offscreen_rendering()
    setup_logging()
    cfg = parse_command(ProbeConfig, args, prog=PROG)
    print(render(run(cfg)))  # noqa: T201  (command output)


if __name__ == "__main__":
    run_cli(PROG, main)
