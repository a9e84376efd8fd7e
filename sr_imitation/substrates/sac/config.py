"""Hyperparameters of the SAC substrate, all in one place (Appendix A.1, Tables "SAC hyperparameters",
"Wake-phase budgets", "Homeostatic excitability", "Sleep-consolidation hyperparameters").

Defaults are the paper preset. The CPU preset (``configs/sac_mt5_cpu.json``) changes only what the CPU cannot
afford (episode budgets through ``wake.budget_scale``, episode length, update-to-data ratio, batch size, warm-up
and evaluation episodes) and keeps every architectural and optimizer setting.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sr_imitation.core.excitability import ExcitabilityConfig
from sr_imitation.envs.metaworld.tasks import STREAMS
from sr_imitation.envs.metaworld.video import DEFAULT_CAMERA, VideoSpec, check_video_settings
from sr_imitation.infra.fingerprint import (
    RUN_DIRECTORY,
    SettingsFingerprint,
    check_finite,
    settings_fingerprint,
    to_jsonable,
)
from sr_imitation.infra.snapshot import EVERY_S
from sr_imitation.stream.config import RunConfig, StreamSettings, StreamSleepConfig, check_shared_settings


@dataclass
class SACConfig:
    """Table "SAC hyperparameters for Meta-World MT5 wake training" and the architecture paragraph."""

    hidden_dim: int = 256
    """Actor and each critic: two hidden layers of 256 units."""
    actor_log_std_bias_init: float = -1.0
    """Initial bias of the Gaussian head's log-std output."""
    log_std_min: float = -5.0
    """Clamp of the actor's log-std (CleanRL default; the paper gives none)."""
    log_std_max: float = 2.0
    """Upper clamp of the actor's log-std."""
    critic_layer_norm: bool = True
    """Twin Q-networks with LayerNorm."""
    actor_lr: float = 3e-4
    """Adam learning rate of the actor (paper 3e-4)."""
    critic_lr: float = 3e-4
    """Adam learning rate of the twin critics (paper 3e-4)."""
    alpha_lr: float = 3e-4
    """Entropy optimizer: Adam 3e-4, alpha automatically tuned."""
    target_entropy: float = -2.0
    """Entropy target of the automatic temperature tuning (paper -2)."""
    log_alpha_min: float = -10.0
    """Lower clamp of log alpha."""
    log_alpha_max: float = 4.0
    """log alpha clamp [-10, 4]."""
    initial_log_alpha: float = 0.0
    """log alpha at the start of every skill (0 - alpha 1)."""
    reward_scale: float = 1.0
    """Factor on the environment reward in the critic targets."""
    buffer_size: int = 1_000_000
    """Replay buffer capacity in transitions (paper 1e6)."""
    utd_ratio: float = 5.0
    """Update-to-data ratio: gradient updates per environment step (fractions: one update every 1/utd steps)."""
    batch_size: int = 256
    """SAC minibatch size (paper 256)."""
    gamma: float = 0.99
    """Discount factor (paper 0.99)."""
    tau: float = 0.005
    """Target-network Polyak rate."""
    warmup_steps: int = 5000
    """Uniform random actions at the start of every skill."""
    normalize_observations: bool = True
    """Running mean/std observation normalizer (the paper's normalizer nu; snapshot stored with each memory)."""

    def __post_init__(self) -> None:
        checks = {  # rule text, holds
            "hidden_dim": (">= 1", self.hidden_dim >= 1),
            "actor_lr": ("> 0", self.actor_lr > 0),
            "critic_lr": ("> 0", self.critic_lr > 0),
            "alpha_lr": ("> 0", self.alpha_lr > 0),
            "log_alpha_min": ("< log_alpha_max", self.log_alpha_min < self.log_alpha_max),
            "log_std_min": ("< log_std_max", self.log_std_min < self.log_std_max),
            "buffer_size": (">= batch_size >= 1", self.buffer_size >= self.batch_size >= 1),
            "utd_ratio": ("> 0", self.utd_ratio > 0),
            "gamma": ("in [0, 1)", 0 <= self.gamma < 1),
            "tau": ("in (0, 1]", 0 < self.tau <= 1),
            "warmup_steps": (">= 0", self.warmup_steps >= 0),
            "reward_scale": ("> 0", self.reward_scale > 0),
        }
        # the key as the command line names it (--sac.<key>)
        bad = [f"sac.{k} must be {rule}, got {getattr(self, k)!r}" for k, (rule, ok) in checks.items() if not ok]
        if bad:
            raise ValueError("; ".join(bad))


@dataclass
class SkillBudget:
    """One row of Table "Wake-phase budgets and early-stopping configuration for MT5" (episodes)."""

    max_episodes: int
    """Episode budget of the skill's wake."""
    min_episodes: int
    """Episodes before early stopping may trigger."""
    patience: int
    """Episodes over which the rolling mean reward must improve by more than wake.improvement."""


PAPER_BUDGETS: dict[str, SkillBudget] = {
    "reach": SkillBudget(1500, 500, 500),
    "door-open": SkillBudget(4000, 1000, 1000),
    "drawer-open": SkillBudget(3000, 1000, 1000),
    "window-close": SkillBudget(2000, 500, 500),
    "button-press-topdown": SkillBudget(2500, 800, 800),
}
"""Paper Table "Wake-phase budgets"; MT8's extra skills have no published budget (see ``default_budget``)."""


@dataclass
class WakeConfig:
    """Wake budgets and early stopping (Appendix A.1, "Wake budgets and early stopping").

    Training on a skill stops at ``max_episodes`` or, after ``min_episodes``, when the ``rolling_window``-episode
    rolling mean reward has not improved by more than ``improvement`` (2%) over the last ``patience`` episodes.
    ``budget_scale`` multiplies every episode count (max, min, patience, rolling window and the excitability
    novelty period) so the CPU preset keeps the paper's proportions.
    """

    budget_scale: float = 1.0
    """Factor on every episode count (max, min, patience, rolling window, excitability novelty period); the CPU
    preset's budget cut."""
    rolling_window: int = 100
    """Episodes in the rolling mean reward of the early-stopping rule (paper 100)."""
    improvement: float = 0.02
    """Relative improvement of the rolling mean reward that counts as progress (paper 2 percent)."""
    early_stopping: bool = True
    """Stop a wake early by the rule above; false - every skill runs its max_episodes."""
    budgets: dict[str, SkillBudget] = field(default_factory=lambda: dict(PAPER_BUDGETS))
    """Per-skill budgets {skill - {max_episodes, min_episodes, patience}} (default - the paper's table)."""
    default_budget: SkillBudget = field(default_factory=lambda: SkillBudget(2500, 800, 800))
    """Budget for skills without a table row (the MT8 extension; our choice: the table's median row)."""
    snapshot_every_s: float = EVERY_S
    """Seconds of wall time between two mid-wake snapshots (:mod:`sr_imitation.substrates.sac.wake_snapshot`, written
    between episodes: a wake killed inside continues from the last one); 0 - after every episode; negative - never. Does
    not change results (a resume may change it)."""

    def __post_init__(self) -> None:
        if self.budget_scale <= 0:
            raise ValueError(f"wake.budget_scale must be > 0, got {self.budget_scale}")
        if math.isnan(self.snapshot_every_s):
            raise ValueError("wake.snapshot_every_s must be a number of seconds (negative: no snapshots), got nan")
        if self.rolling_window < 1 or self.improvement < 0:
            raise ValueError("wake.rolling_window must be >= 1 and wake.improvement >= 0")
        for name, b in {**self.budgets, "default": self.default_budget}.items():
            if isinstance(b, dict):  # draccus/JSON may hand us plain dicts
                b = SkillBudget(**b)
                if name == "default":
                    self.default_budget = b
                else:
                    self.budgets[name] = b
            if not 1 <= b.min_episodes <= b.max_episodes or b.patience < 1:
                raise ValueError(f"wake budget for {name!r} needs 1 <= min <= max and patience >= 1, got {b}")

    def scaled(self, count: int) -> int:
        return max(1, int(math.ceil(count * self.budget_scale)))

    def budget_for(self, skill: str) -> SkillBudget:
        """The scaled budget of ``skill`` (Meta-World id or bare name)."""
        name = skill.removesuffix("-v3")
        b = self.budgets.get(name, self.default_budget)
        return SkillBudget(self.scaled(b.max_episodes), self.scaled(b.min_episodes), self.scaled(b.patience))

    @property
    def scaled_window(self) -> int:
        return self.scaled(self.rolling_window)


@dataclass
class CriticMemoryConfig:
    """Frozen critic memories (Appendix A.1, "Sleep consolidation", "Frozen critic validation", "Memory cost")."""

    buffer_size: int = 1000
    """States per memory, sampled uniformly from the final ``late_fraction`` of wake episodes."""
    late_fraction: float = 0.2
    """Final share of the wake's episodes the memory's states are sampled from (paper 0.2)."""
    holdout_fraction: float = 0.05
    """Share of wake transitions never trained on, used to validate the critic (our choice; unspecified)."""
    holdout_batch: int = 1024
    """Held-out transitions kept per skill, and checked, for the critic's validation."""
    validation_threshold: float = 0.5
    """Max normalized Bellman residual RMSE(TD) / std(target) before freezing (our choice; unspecified)."""
    validation_chunk: int = 500
    """Extra critic-only updates per failed validation."""
    validation_max_rounds: int = 4
    """Rounds of extra critic updates at most; a critic still above the threshold is frozen with a warning."""

    def __post_init__(self) -> None:
        if self.buffer_size < 1 or not 0 < self.late_fraction <= 1 or not 0 <= self.holdout_fraction < 1:
            raise ValueError("memory.buffer_size >= 1, 0 < late_fraction <= 1, 0 <= holdout_fraction < 1")
        if self.validation_threshold <= 0 or self.validation_chunk < 0 or self.validation_max_rounds < 0:
            raise ValueError("memory validation settings must be positive")


@dataclass
class EvalConfig:
    """Evaluation protocol (Appendix A.1: N = 100 episodes per learned skill after each stage). Each skill is
    evaluated on the same configurations at every stage (``substrates.sac.evaluate.evaluation_configurations``)."""

    episodes: int = 100
    """Evaluation episodes per learned skill after every stage (paper 100)."""
    success_mode: str = "any_step"
    """An episode succeeds if any step succeeds (any_step) or its last step does (final_step)."""
    stop_on_success: bool = True
    """End an any_step episode at its first success (same success rate, faster)."""
    deterministic: bool = True
    """Evaluate the Gaussian mean (tanh) action."""
    after_wake: bool = True
    """Evaluate each new skill right after its wake, on the same configurations as its stage evaluations: the
    reference of ``bwt_wake``. Costs one extra evaluation of one skill per sleep stage; stages without sleep reuse
    their stage evaluation (also when this is off). Off: sleep stages have no after-wake success and a sleeping
    run's ``bwt_wake`` is null."""
    videos_per_skill: int = 1
    """After every stage, record the first N evaluation episodes of each learned skill as mp4 (0: no videos)."""
    video_height: int = 240
    """Video frame height in pixels (a multiple of 16)."""
    video_width: int = 320
    """Video frame width in pixels (a multiple of 16)."""
    video_camera: str = DEFAULT_CAMERA
    """Meta-World camera of the videos."""

    def __post_init__(self) -> None:
        if self.episodes < 1:
            raise ValueError(f"eval.episodes must be >= 1, got {self.episodes}")
        if self.success_mode not in ("any_step", "final_step"):
            raise ValueError(f"eval.success_mode must be any_step or final_step, got {self.success_mode!r}")
        try:
            check_video_settings(self.videos_per_skill, self.video_height, self.video_width, self.video_camera)
        except ValueError as exc:
            raise ValueError(f"eval.{exc}") from None

    def video_spec(self, directory: Path) -> VideoSpec | None:
        """The evaluation videos to record into ``directory`` (``None`` when ``videos_per_skill`` is 0)."""
        if not self.videos_per_skill:
            return None
        return VideoSpec(directory, self.videos_per_skill, self.video_height, self.video_width, self.video_camera)


@dataclass
class StreamConfig(StreamSettings):
    """The Meta-World skill stream (paper Appendix A.1: MT5, its reverse, and MT8 continuing MT5)."""

    name: str = "mt5"
    """A named stream - mt5, mt5-reverse or mt8 (``sr_imitation.envs.metaworld.tasks.STREAMS``)."""
    skills: list[str] | None = None
    """Explicit skill list (Meta-World v3 ids); overrides ``name``."""

    def __post_init__(self) -> None:
        if self.skills is None and self.name not in STREAMS:
            raise ValueError(f"stream.name: unknown stream {self.name!r}; choose from {sorted(STREAMS)}")
        if self.skills is not None and len(self.skills) == 0:
            raise ValueError("stream.skills must not be empty")

    @property
    def skill_list(self) -> list[str]:
        return list(self.skills) if self.skills is not None else list(STREAMS[self.name])


@dataclass
class RLTrainConfig(RunConfig):
    """``sr-train --substrate=sac``: SAC wake, frozen critic memories and Nash sleep on Meta-World (e.g.
    ``--config_path=configs/sac_mt5_cpu.json``). The flags shared with the imitation substrate have the same names
    (``--method``, ``--stream.*``, ``--sleep.*``, ``--memory.*``, ``--eval.*``, ``--seed``, ``--output_dir``)."""

    substrate: str = "sac"
    """The substrate sr-train runs - sac (this one) or act (ACT-SR on the needle stream)."""
    output_dir: Path = Path("outputs/sac_mt5")
    """Run directory (refused if it exists, unless --resume or --overwrite)."""
    seed: int = 0
    """Training seed - every phase seeds its generators from it."""
    stream: StreamConfig = field(default_factory=StreamConfig)
    """The skills (--stream.name=mt5|mt5-reverse|mt8 or --stream.skills=[...]) and --stream.extend_from."""
    max_episode_steps: int = 500
    """Meta-World's time limit (max_path_length)."""
    sac: SACConfig = field(default_factory=SACConfig)
    """SAC (Table "SAC hyperparameters")."""
    wake: WakeConfig = field(default_factory=WakeConfig)
    """Wake budgets and early stopping (Table "Wake-phase budgets")."""
    excitability: ExcitabilityConfig = field(default_factory=ExcitabilityConfig)
    """Homeostatic excitability of the actor (Eq. 3)."""
    sleep: StreamSleepConfig = field(default_factory=StreamSleepConfig)
    """Sleep consolidation (defaults - the paper's MT5 table; --sleep.enabled=false is SR wake-only)."""
    memory: CriticMemoryConfig = field(default_factory=CriticMemoryConfig)
    """The frozen critic memories."""
    eval: EvalConfig = field(default_factory=EvalConfig)
    """Evaluation after every stage (and right after each wake)."""
    device: str = "cpu"
    """Torch device (cpu or cuda)."""
    torch_threads: int = 1
    """Torch intra-op threads (results are reproducible at a fixed count)."""
    plots: bool = True
    """Draw PNG plots from results.json at the end."""

    def __post_init__(self) -> None:
        self.output_dir = Path(self.output_dir)
        if self.max_episode_steps < 1:
            raise ValueError(f"max_episode_steps must be >= 1, got {self.max_episode_steps}")
        check_shared_settings(self, "sac")
        if self.torch_threads < 1:
            raise ValueError(f"torch_threads must be >= 1, got {self.torch_threads}")
        check_finite(self)  # every numeric setting, before anything is written
        from sr_imitation.stream import method_class

        method_class(self.method, "sac")  # what the method asks of the substrate: checked when the run is built
        if self.sleep.early_stop_scale == "memory_scale" and self.method_options.get("expert_memory") == "instead":
            raise ValueError("sleep.early_stop_scale=memory_scale measures the plateau rule on the frozen critics' "
                             "scale; method_options expert_memory=instead keeps none (use early_stop_scale=window)")

    @property
    def stream_skills(self) -> list[str]:
        return self.stream.skill_list

    def stored_config(self) -> dict[str, Any]:
        """``train_config.json`` of a run: the whole config (draccus reads it back with ``--config_path``) without the
        per-invocation flags and with ``output_dir`` "." (the directory holding the file: the run never names its
        absolute location, so a copied run resumes where it is)."""
        out = {k: v for k, v in to_jsonable(self).items() if k not in ("resume", "overwrite")}
        out["output_dir"] = RUN_DIRECTORY
        return out

    def resume_fingerprint(self) -> SettingsFingerprint:
        """The settings a resume must keep: the whole config minus :data:`RESUME_ALLOW_LIST`, plus the method's
        own settings with their defaults (``method_config``, :func:`~sr_imitation.stream.methods.method_config`)."""
        from sr_imitation.stream import method_config

        return settings_fingerprint(self, RESUME_ALLOW_LIST,
                                    {"method_config": method_config(self.method, self.method_options)},
                                    added=SETTINGS_ADDED)


SETTINGS_ADDED: dict[str, Any] = {
    "sleep.early_stop_scale": "window",  # added 2026-11-29: every earlier run measured against the window
    "sleep.newest_guard": False,  # added 2026-12-07: no earlier run had the newest-skill guard
}
"""Settings added after SAC runs were first fingerprinted, with the value every run that predates them had: such a
run resumes with that value and is refused with another (:attr:`SettingsFingerprint.added`)."""


RESUME_ALLOW_LIST: dict[str, str] = {
    "output_dir": "where the run is, not what it computes: a copied run directory resumes where it is",
    "resume": "the per-invocation flag that asks for this check",
    "overwrite": "per invocation (it excludes --resume, and a fresh run has nothing to compare with)",
    "progress": "console progress bars only",
    "plots": "PNG plots drawn from results.json at the end",
    "wandb": "experiment tracking only (the run log mirrored to Weights & Biases)",
    "eval.videos_per_skill": "which evaluation episodes are also rendered to mp4: rendering only reads the "
                             "simulation state, the outcome is identical (tests/substrates/sac/test_video.py)",
    "eval.video_height": "video frame size only (see eval.videos_per_skill)",
    "eval.video_width": "video frame size only (see eval.videos_per_skill)",
    "eval.video_camera": "video camera only (see eval.videos_per_skill)",
    "wake.snapshot_every_s": "when a wake writes its snapshot: writing one reads the state and draws nothing, and a "
                             "resumed wake continues bit for bit (tests/substrates/sac/test_wake_snapshot.py)",
}
"""Settings of ``sr-rl-train`` that may differ on ``--resume`` (fnmatch patterns, each covering the keys below it),
with the reason each cannot change results. Every other setting of :class:`RLTrainConfig` is fingerprinted at the
run's start (``settings_fingerprint.json``) and must be equal on resume, checked before anything is written. Not
allow-listed on purpose: ``device`` (CPU and CUDA kernels round differently) and ``torch_threads`` (intra-op
parallel reductions may split sums differently, so results are only reproducible at a fixed thread count)."""
