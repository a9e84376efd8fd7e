"""sr-sleep's command line: the policy, the memories, the anchor, the sleep and evaluation settings."""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sr_imitation.core.sleep import anchor_gate_decides
from sr_imitation.substrates.act.config import SurgicAISleepConfig
from sr_imitation.substrates.act.evaluate import (
    EvalConfig,
)
from sr_imitation.substrates.act.normalization import (
    MIN_STD,
)

logger = logging.getLogger(__name__)

PRETRAINED_FILES = ("config.json", "model.safetensors", "policy_preprocessor.json", "policy_postprocessor.json")
"""What a LeRobot ``pretrained_model/`` directory of a policy with processors holds (and ``lerobot-eval`` reads)."""

RESULTS_FILE = "sleep.json"
REPORT_FILE = "sleep.md"
DIAGNOSTICS_FILE = "sleep_diagnostics.json"
RESULTS_FORMAT = "sr_imitation.offline_sleep"
RESULTS_VERSION = 1

LOSS_BATCH = 64
"""Observations per forward pass when a memory loss is computed on the whole buffer (memory only, not values)."""


@dataclass
class PolicyPathConfig:
    """The deployed policy (``--policy.path``, as ``lerobot-eval`` names it)."""

    path: Path | None = None
    """A LeRobot pretrained_model directory of an ACT-SR policy (config.json, model.safetensors and its processors),
    e.g. a lerobot-train checkpoint or an sr-train stage checkpoint."""
    device: str | None = None
    """Device to sleep on (null - the checkpoint's device, or the one LeRobot picks when that is unavailable)."""


@dataclass
class AnchorConfig:
    """theta_{k-1}^sleep, the proximal anchor of Eq. 2."""

    path: Path | None = None
    """The previous consolidated policy (a pretrained_model directory of the same architecture); null - the deployed
    policy itself (our choice). An sr-train run's stage k-1 final checkpoint repeats that run's sleep of stage k."""


@dataclass
class SleepEvalConfig:
    """Success before and after the sleep: the stream's evaluation protocol (:class:`~sr_imitation.substrates.act.
    evaluate.EvalConfig`'s settings of the same names), in any environment sr-train evaluates in."""

    skills: list[str] = field(default_factory=list)
    """Skills to evaluate before and after the sleep, in stream order; empty - no evaluation (the default: a
    deployed policy may have no environment here; the memory losses are reported either way). Each skill's episodes
    are those of its position in the memories' skill order: an sr-train run's own episodes, in any stream order."""
    env: str = "needle"
    """Where each skill is evaluated, as sr-train's --eval.env - needle (the needle skills), metaworld (a Meta-World
    v3 task per skill), gym (--eval.gym_ids) or lerobot (--eval.env_type, --eval.env_tasks)."""
    gym_ids: list[str] | None = None
    """--eval.env=gym: one gymnasium id per skill, in the order of eval.skills."""
    env_type: str | None = None
    """--eval.env=lerobot: the LeRobot env type (lerobot-eval's --env.type)."""
    env_tasks: list[str] | None = None
    """--eval.env=lerobot or metaworld: one task per skill; null - each skill's name is its task."""
    env_options: dict[str, Any] = field(default_factory=dict)
    """Keyword arguments of the environment (as sr-train's --eval.env_options)."""
    episodes: int = 20
    """Episodes per skill per evaluation seed (paper 20)."""
    seeds: list[int] = field(default_factory=lambda: [0, 1, 2])
    """Evaluation seeds (paper three); the same episodes before and after the sleep."""
    max_steps: int = 300
    """Episode step limit (SurgicAI 300)."""
    videos_per_skill: int = 1
    """Episodes per skill (first seed) also saved as mp4 (videos/before, videos/after); 0 disables videos."""
    video_height: int = 240
    """Video frame height."""
    video_width: int = 320
    """Video frame width."""
    thresholds: str = "learnable"
    """Success-threshold preset of the needle environment - learnable or surgicai."""

    def protocol(self) -> EvalConfig:
        """The stream's evaluation settings (checked by :class:`EvalConfig`, the per-skill lists against
        ``skills``)."""
        if self.env == "none":
            raise ValueError("eval.env=none evaluates nothing; leave eval.skills empty instead")
        protocol = EvalConfig(env=self.env, gym_ids=self.gym_ids, env_type=self.env_type, env_tasks=self.env_tasks,
                              env_options=dict(self.env_options), episodes=self.episodes, seeds=list(self.seeds),
                              max_steps=self.max_steps, videos_per_skill=self.videos_per_skill,
                              video_height=self.video_height, video_width=self.video_width,
                              thresholds=self.thresholds)
        protocol.check_skills(self.skills)
        return protocol


@dataclass
class OfflineSleepConfig:
    """``sr-sleep``: consolidate a deployed ACT-SR policy from saved memory files, e.g.
    ``sr-sleep --policy.path=<pretrained_model> --memories=[a.safetensors,b.safetensors] --output_dir=out``."""

    policy: PolicyPathConfig = field(default_factory=PolicyPathConfig)
    """The deployed policy - its parameters are what the sleep changes."""
    memories: list[Path] = field(default_factory=list)
    """ACT actor memory files M_1..M_k in skill order, the newest skill last (lerobot-train --policy.sleep=true's
    memory.safetensors beside a checkpoint, or an sr-train run's memories/skill_k_*.safetensors)."""
    anchor: AnchorConfig = field(default_factory=AnchorConfig)
    """The anchor of Eq. 2."""
    sleep: SurgicAISleepConfig = field(default_factory=SurgicAISleepConfig)
    """Sleep consolidation - sr-train's --sleep.* settings (defaults - the paper's SurgicAI table)."""
    final_skill: bool = False
    """This sleep follows the stream's last skill - then the anchor applies only with sleep.anchor_after_final (the
    MT5 table's "not after the final skill"); default false - more skills may follow (our choice)."""
    eval: SleepEvalConfig = field(default_factory=SleepEvalConfig)
    """Evaluation before and after the sleep (off unless eval.skills is given)."""
    output_dir: Path = Path("outputs/sleep")
    """Where the consolidated checkpoint and the tables go (refused if it exists, unless --overwrite=true)."""
    overwrite: bool = False
    """Replace an existing output_dir (only once the new one is complete; only an earlier sr-sleep output)."""
    progress: bool = True
    """Console progress bars."""
    torch_threads: int | None = None
    """torch's intra-op threads (null - this process's default); repeating a run's sleep bit for bit needs the
    run's number."""
    min_std: float = MIN_STD
    """Floor on the policy's normalization standard deviations - a dimension whose std is below it (constant in the
    deployed policy's dataset) is normalized with the statistics of the policy's and its memories' snapshots
    together, the policy re-expressed with the same actions (sr-train's --stream.stats_min_std; default 1e-2)."""

    def __post_init__(self) -> None:
        self.output_dir = Path(self.output_dir)
        if not self.min_std > 0:
            raise ValueError(f"min_std must be > 0, got {self.min_std}")
        self.memories = [Path(p) for p in self.memories]
        if self.policy.path is None:
            raise ValueError("policy.path: give the deployed policy's pretrained_model directory "
                             "(--policy.path=<checkpoint>/pretrained_model)")
        if not self.memories:
            raise ValueError("memories: give at least one memory file (--memories=[a.safetensors,b.safetensors])")
        seen: dict[Path, Path] = {}
        for path in self.memories:
            key = path.resolve()
            if key in seen:
                raise ValueError(f"memories: {path} is given twice (as {seen[key]} too)")
            seen[key] = path
        if not self.sleep.enabled:
            raise ValueError("sleep.enabled=false: sr-sleep always runs one sleep (sleep.enabled switches the stream's "
                             "sleeps in sr-train); leave it out")
        if self.anchor.path is not None and self.sleep.anchor_strength == 0:
            raise ValueError(f"anchor.path={self.anchor.path} has no effect with sleep.anchor_strength=0 (no anchor); "
                             "give one of them")
        if self.torch_threads is not None and self.torch_threads < 1:
            raise ValueError(f"torch_threads must be >= 1, got {self.torch_threads}")
        unused = [f"eval.{f.name}" for f in dataclasses.fields(SleepEvalConfig)
                  if getattr(self.eval, f.name) != getattr(SleepEvalConfig(), f.name)]
        if unused and not self.eval.skills:
            raise ValueError(f"{', '.join(unused)} set but eval.skills is empty, so nothing is evaluated; give "
                             "--eval.skills=[...] or leave them out")
        if self.eval.skills:
            self.eval.protocol()  # the episode settings' own checks, now

    def gate_decides(self) -> bool:
        """Whether Eq. 2's gate decides the anchor (so the gate snapshots theta_i^wake are needed)."""
        return anchor_gate_decides(self.sleep, self.final_skill)


# -- inputs ------------------------------------------------------------------------------------------------------
