"""``sr-sleep``: consolidate an already deployed ACT-SR policy offline from saved skill memories.

    sr-sleep --policy.path=outputs/place/checkpoints/last/pretrained_model \\
        --memories=[outputs/approach/memory.safetensors,outputs/place/memory.safetensors] --output_dir=outputs/slept

One sleep phase of Algorithm 1 (lines 7-15; :func:`~sr_imitation.core.sleep.sleep_consolidate`: Nash-bargained
per-memory gradients, Eq. 1, with the gated proximal anchor of Eq. 2) with the ``--sleep.*`` settings of
``sr-train`` (defaults: the paper's SurgicAI table), on the deployed policy's parameters only and with each memory
evaluating the deployed action chunk, exactly as the stream's sleep does (both use
:func:`~sr_imitation.substrates.act.substrate.act_sleep_problem`).

What the stream knows from its run directory is taken here from the inputs:

- **memories** M_1..M_k: ACT actor memories (:class:`~lerobot_policy_act_sr.actor_memory.ActorMemory`) in skill
  order, the newest skill last: the ``memory.safetensors`` that stock ``lerobot-train --policy.type=act_sr
  --policy.sleep=true`` writes beside each checkpoint, or an ``sr-train`` run's ``memories/skill_k_*.safetensors``.
- **anchor** theta_{k-1}^sleep of Eq. 2: ``--anchor.path``, the previous consolidated policy; by default the
  deployed policy itself (our choice: a deployed policy has no recorded predecessor, and anchored at itself the
  proximal term keeps the consolidated policy near what is deployed). With ``--anchor.path`` set to stage k-1's
  final checkpoint, sleeping an ``sr-train`` run's stage-k wake checkpoint with its memories 1..k,
  ``--sleep.seed`` = that stage's sleep seed (:func:`~sr_imitation.stream.substrate.phase_seed`:
  1000 x run seed + 10 k + 3) and ``--final_skill`` as in the run gives the run's own sleep, bit for bit.
- **gate snapshots** theta_i^wake, i < k, of Eq. 2: the checkpoint each of the first k-1 memories names as its
  snapshot (``config["snapshot"]``: an ``sr-train`` memory names its stage checkpoint relative to the run
  directory, the parent of ``memories/``; a memory written beside a checkpoint names that directory, ``.``).
  Needed only when the gate decides (``sleep.anchor_strength`` > 0 and ``sleep.anchor_tau`` set); a missing one is
  a one-line error.
- **targets in one action space**: a memory's targets are its snapshot's action chunks in the snapshot's normalized
  action space. Where the snapshot checkpoint (found as above) normalizes actions with other statistics than the
  deployed policy (two skills trained by stock ``lerobot-train`` on their own datasets), the targets are mapped
  through the snapshot's unnormalizer and the deployed policy's normalizer (our choice: the objective then compares
  the raw-space behaviours in the deployed policy's normalized action space, as the stream's fixed statistics do).
  Where the snapshot is not found, the targets are used as stored (reported as ``unchecked``).
- **no standard deviation of ~0**: where the deployed policy's statistics have a standard deviation below
  ``--min_std`` (a dimension constant in its dataset, e.g. the needle's jaw while placing), that dimension is
  normalized with the statistics of the policy's and its memories' snapshots together and the policy re-expressed
  with the same actions (:func:`settle_statistics`), so no memory is mapped through a division by ~1e-8.

A sleep that cannot consolidate, or did not, is an error naming the memory, with nothing written: a memory loss that
is non-finite or absurd (:data:`ABSURD_LOSS`) before or after the sleep, or no memory's loss moved.

Every input is checked before the first gradient (one-line errors naming the file): the policy directory loads as
an ACT-SR policy with its processors, every memory loads and matches the policy's observation features and action
chunk, the anchor and the gate snapshots hold the policy's deployed parameters. Outputs, built in a staging
directory and renamed into ``output_dir`` only when complete:

- ``pretrained_model/``: the consolidated policy with its pre/post-processors (LeRobot layout: stock
  ``lerobot-eval --policy.path=...`` loads it), sealed by ``checksums.json``;
- ``sleep.json`` (checked JSON) and ``sleep.md``: memory losses on each memory's whole buffer before and after the
  sleep, success before and after on ``--eval.skills`` (in ``--eval.env``, as sr-train's; off by default), the sleep's
  summary; ``sleep_diagnostics.json``: every iteration's losses, weights and gradient norms (as the stream's);
  ``videos/`` when evaluating.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import re
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import torch
from lerobot.configs.policies import PreTrainedConfig
from lerobot.policies.factory import make_pre_post_processors
from lerobot.processor.normalize_processor import NormalizerProcessorStep, UnnormalizerProcessorStep
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE
from safetensors.torch import load_file

from lerobot_policy_act_sr import ACTSRConfig, ACTSRPolicy
from lerobot_policy_act_sr.actor_memory import ActorMemory
from sr_imitation.core.memory import load_memory, memory_contents
from sr_imitation.core.sleep import SleepConfig, SleepResult, anchor_gate_decides
from sr_imitation.envs.needle.skills import SKILL_NAMES as NEEDLE_SKILLS
from sr_imitation.infra.fingerprint import FINGERPRINT_FILE, to_jsonable
from sr_imitation.io import (
    MANIFEST,
    CorruptFileError,
    WriteError,
    atomic_write_bytes,
    atomic_write_json,
    staged_directory,
    verify_checkpoint,
    write_checked_json,
)
from sr_imitation.lerobot_compat import is_torch_device_available
from sr_imitation.progress import format_duration
from sr_imitation.stream.rundir import RUN_CONFIG_FILE, OverwriteRefusedError, check_run_config, few_names
from sr_imitation.substrates.act.config import SurgicAISleepConfig
from sr_imitation.substrates.act.evaluate import (
    EnvFactory,
    EvalConfig,
    evaluate_skills,
    make_env_factory,
    resolve_eval_env,
)
from sr_imitation.substrates.act.normalization import (
    MIN_STD,
    Stats,
    map_actions,
    pooled,
    reexpress_policy,
    same_stats,
)
from sr_imitation.substrates.act.substrate import (
    act_sleep_problem,
    deployed_parameters,
    normalize_raw_observations,
    save_pretrained_model,
    seed_everything,
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
    deployed policy may have no environment here; the memory losses are reported either way)."""
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
@dataclass
class LoadedPolicy:
    """The deployed policy with its processors, as ``lerobot-eval`` builds them."""

    path: Path
    config: ACTSRConfig
    policy: ACTSRPolicy
    preprocessor: Any
    postprocessor: Any
    stats: Stats = field(default_factory=dict)
    """The statistics its processors normalize with (inputs: the normalizer's; the action: the unnormalizer's)."""
    deployed_stats: Stats = field(default_factory=dict)
    """Those of the checkpoint as deployed (``stats`` differ once :func:`settle_statistics` re-expressed it)."""


@dataclass
class LoadedMemory:
    """One memory file, checked against the policy."""

    path: Path
    memory: ActorMemory
    snapshot: Path | None
    """The snapshot's pretrained_model directory, when found."""
    targets: str
    """``as stored`` (the snapshot normalizes actions as the policy does), ``re-expressed`` (mapped into the
    policy's action space) or ``unchecked`` (snapshot not found)."""


def _check_pretrained_dir(path: Path, what: str) -> None:
    if not path.is_dir():
        raise FileNotFoundError(f"{path}: {what}: no such directory (a LeRobot pretrained_model directory)")
    missing = [name for name in PRETRAINED_FILES if not (path / name).is_file()]
    if missing:
        raise FileNotFoundError(f"{path}: {what} is not a LeRobot pretrained_model directory with processors "
                                f"(no {', '.join(missing)})")
    verify_checkpoint(path, what)  # an sr-train stage or sr-sleep checkpoint is sealed; else one warning line


def _load_state(path: Path) -> dict[str, torch.Tensor]:
    file = path / "model.safetensors"
    try:
        return load_file(str(file))
    except Exception as exc:  # safetensors raises its own error types without the file name
        raise CorruptFileError(file, f"unreadable weights ({exc})") from exc


def load_policy(path: Path, device: str | None) -> LoadedPolicy:
    """The deployed ACT-SR policy of a pretrained_model directory and its processors, checked (strict weights)."""
    path = Path(path)
    _check_pretrained_dir(path, "policy.path")
    try:
        config = PreTrainedConfig.from_pretrained(path)
    except Exception as exc:  # draccus' decoding errors name neither the file nor, often, the key
        raise CorruptFileError(path / "config.json", f"not a readable policy config ({exc})") from exc
    if not isinstance(config, ACTSRConfig):
        raise ValueError(f"{path}: a {config.type!r} policy; sr-sleep consolidates ACT-SR policies (act_sr)")
    if device is not None:
        if not is_torch_device_available(device):
            raise ValueError(f"policy.device: {device!r} is not available here")
        config.device = device
    state = _load_state(path)
    policy = ACTSRPolicy(config)
    missing, unexpected = policy.load_state_dict(state, strict=False)
    if missing or unexpected:
        raise CorruptFileError(path / "model.safetensors", f"weights do not match its config.json (missing "
                                                           f"{missing[:3]}, unexpected {unexpected[:3]})")
    policy.to(config.device).eval()
    try:
        pre, post = make_pre_post_processors(config, pretrained_path=str(path),
                                             preprocessor_overrides={"device_processor": {"device": config.device}})
    except Exception as exc:  # LeRobot's pipeline loader names neither the file nor the step
        raise CorruptFileError(path, f"unreadable policy processors ({exc})") from exc
    policy.set_observation_normalizer(partial(normalize_raw_observations, pre))
    stats = processor_stats(pre, post)
    return LoadedPolicy(path, config, policy, pre, post, stats, stats)


def checkpoint_parameters(policy: ACTSRPolicy, path: Path, what: str) -> list[torch.Tensor]:
    """The deployed parameters saved in the pretrained_model directory ``path`` (checked against ``policy``)."""
    path = Path(path)
    if not path.is_dir():
        raise FileNotFoundError(f"{path}: {what}: no such directory (a LeRobot pretrained_model directory)")
    if not (path / "model.safetensors").is_file():
        raise FileNotFoundError(f"{path}: {what}: no model.safetensors (not a LeRobot pretrained_model directory)")
    verify_checkpoint(path, what)
    state = _load_state(path)
    own = dict(policy.deployed_named_parameters())
    missing = [n for n in own if n not in state]
    shapes = [n for n in own if n in state and tuple(state[n].shape) != tuple(own[n].shape)]
    if missing or shapes:
        raise ValueError(f"{path / 'model.safetensors'}: {what} is not a policy of the deployed policy's "
                         f"architecture (missing {missing[:3]}, other shapes {shapes[:3]})")
    return deployed_parameters(policy, state)


def snapshot_directory(path: Path, memory: ActorMemory) -> Path | None:
    """The pretrained_model directory of the memory's snapshot theta^wake, when it is where the memory says
    (see the module docstring), else ``None``."""
    ref = str(memory.config.get("snapshot", ""))
    if not ref:
        return None
    path = Path(path)
    for base in (path.parent, path.parent.parent):  # beside the memory ("."), or the run holding memories/
        for candidate in (base / ref, base / ref / "pretrained_model"):
            if (candidate / "model.safetensors").is_file():
                return candidate
    return None


STAGE_REFERENCE = re.compile(r"(?:^|/)skill_(\d+)_")
"""An ``sr-train`` memory's snapshot reference, ``skill_<k>_<skill>/wake``: the stage k it was written at."""
RUN_SEARCH_DEPTH = 4
"""Folders above ``--policy.path`` searched for the ``sr-train`` run holding it (``<run>/skill_k_<skill>/<phase>/
pretrained_model``)."""


def policy_run_skills(policy_path: Path) -> tuple[Path, list[str]] | None:
    """The ``sr-train`` run holding the policy (a folder above it with the run's settings fingerprint and
    ``train_config.json``, checked as a resume checks it) and its skill order, or ``None``."""
    for folder in list(Path(policy_path).resolve().parents)[:RUN_SEARCH_DEPTH]:
        if (folder / FINGERPRINT_FILE).is_file() and (folder / RUN_CONFIG_FILE).is_file():
            config = check_run_config(folder) or {}
            skills = (config.get("stream") or {}).get("skills")
            return (folder, [str(x) for x in skills]) if isinstance(skills, list) else None
    return None


def check_memory_order(paths: Sequence[Path], memories: Sequence[ActorMemory], policy_path: Path) -> None:
    """The memories are in skill order, the newest last, as far as the memories or the policy's run record it: the
    stage each memory's snapshot names (``skill_<k>_...``), else the run's ``stream.skills`` for the memories' skills.
    A sleep weighs and gates memories by their position (M_k is the newest skill; the gate of Eq. 2 uses the wake
    snapshots of M_1..M_{k-1}), so another order is refused in one line naming the expected order."""
    stages = [STAGE_REFERENCE.search(str(m.config.get("snapshot", ""))) for m in memories]
    if all(stages):
        keys, source = [int(match.group(1)) for match in stages], "their snapshots' stages"
    else:
        found = policy_run_skills(policy_path)
        if found is None or not all(m.skill in found[1] for m in memories):
            return  # nothing records an order (stock memories beside a deployed checkpoint)
        keys, source = [found[1].index(m.skill) for m in memories], f"the skill order of {found[0] / RUN_CONFIG_FILE}"
    if keys != sorted(keys):
        expected = [str(path) for _, path in sorted(zip(keys, paths, strict=True), key=lambda pair: pair[0])]
        raise ValueError(f"memories: given as skills {[m.skill for m in memories]}, not in skill order by {source}; "
                         f"give them oldest first: --memories=[{','.join(expected)}]")


def expected_observations(config: ACTSRConfig, stored: Sequence[str]) -> dict[str, tuple[int, ...]]:
    """The raw observations (key -> shape per sample) a memory must hold for the policy: its input features, less
    the environment state that state-only ACT-SR feeds from the robot state when it is not stored."""
    out = {k: tuple(f.shape) for k, f in config.input_features.items()}
    if OBS_ENV_STATE in out and OBS_STATE in out and OBS_ENV_STATE not in stored:
        del out[OBS_ENV_STATE]
    return out


def _steps(post: Any, pre: Any) -> tuple[UnnormalizerProcessorStep | None, NormalizerProcessorStep | None]:
    unnorm = next((s for s in post.steps if isinstance(s, UnnormalizerProcessorStep)), None)
    norm = next((s for s in pre.steps if isinstance(s, NormalizerProcessorStep)), None)
    return unnorm, norm


def processor_stats(pre: Any, post: Any) -> Stats:
    """The statistics a policy's processors hold: its inputs' (the normalizer's) and its action's (the
    unnormalizer's, which turns the policy's outputs into actions)."""
    stats: Stats = {}
    unnorm, norm = _steps(post, pre)
    for step in (norm, unnorm):  # the unnormalizer's action statistics last: they are what the policy outputs in
        for name, tensor in ({} if step is None else step.state_dict()).items():
            key, stat = name.rsplit(".", 1)
            stats.setdefault(key, {})[stat] = tensor.detach().float().cpu()
    return stats


@dataclass
class MemoryFile:
    """One memory file read and checked against the policy, its targets as stored."""

    path: Path
    memory: ActorMemory
    snapshot: Path | None
    snapshot_stats: Stats | None
    """The statistics of the snapshot's processors (the action space its targets are in), when found."""


def read_actor_memory(path: Path, loaded: LoadedPolicy) -> MemoryFile:
    """Load one memory file and check it against the policy: an ACT actor memory whose observations are the
    policy's inputs and whose targets are (size, chunk_size, action_dim) chunks; with its snapshot's statistics."""
    path = Path(path)
    memory = load_memory(path)  # a missing or damaged file: one line naming it
    if not isinstance(memory, ActorMemory):
        raise ValueError(f"{path}: a {memory.kind!r} memory ({memory_contents(memory.kind)}); sr-sleep consolidates "
                         f"ACT actor memories ({ActorMemory.kind!r}, e.g. lerobot-train --policy.sleep=true's "
                         "memory.safetensors)")
    config = loaded.config
    observations = memory.observations()
    expected = expected_observations(config, list(observations))
    if set(observations) != set(expected):
        raise ValueError(f"{path}: memory observations {sorted(observations)} are not the policy's inputs "
                         f"{sorted(expected)} ({loaded.path})")
    for key, shape in expected.items():
        if tuple(observations[key].shape[1:]) != shape:
            raise ValueError(f"{path}: memory observation {key!r} has shape {tuple(observations[key].shape[1:])}, "
                             f"the policy takes {shape} ({loaded.path})")
    chunk = (config.chunk_size, int(config.output_features[ACTION].shape[0]))
    target = memory.tensors["target"]
    if tuple(target.shape[1:]) != chunk:
        raise ValueError(f"{path}: memory action chunks are {tuple(target.shape[1:])} (chunk x action), the policy's "
                         f"are {chunk} ({loaded.path})")
    snapshot = snapshot_directory(path, memory)
    if snapshot is None or not (snapshot / "policy_postprocessor.json").is_file():
        logger.warning("%s: its snapshot checkpoint (%r) is not beside it; its targets are taken to be in the "
                       "policy's normalized action space", path, memory.config.get("snapshot", ""))
        return MemoryFile(path, memory, snapshot, None)
    try:
        snapshot_pre, snapshot_post = make_pre_post_processors(config, pretrained_path=str(snapshot))
    except Exception as exc:  # LeRobot's pipeline loader names neither the file nor the step
        raise CorruptFileError(snapshot, f"unreadable processors of the snapshot of {path} ({exc})") from exc
    return MemoryFile(path, memory, snapshot, processor_stats(snapshot_pre, snapshot_post))


def settle_statistics(loaded: LoadedPolicy, snapshot_stats: Sequence[Stats | None], min_std: float) -> str | None:
    """Where the deployed policy's statistics have a standard deviation below ``min_std`` (a dimension constant in
    its dataset: LeRobot divides by std + 1e-8 there, and another skill's memory would sit ~1e8 standard deviations
    away), that dimension's statistics become those of the deployed policy's and its memories' snapshots' together
    (:func:`~sr_imitation.substrates.act.normalization.pooled`, floored); the policy's layers are re-expressed so its
    actions are unchanged (:func:`~sr_imitation.substrates.act.normalization.reexpress_policy`) and its processors are
    rebuilt with the new statistics (what the consolidated checkpoint is saved with). Our choice. Returns a
    description of what changed, ``None`` when nothing did (every standard deviation at least ``min_std``: an
    sr-train run's checkpoints, whose statistics are floored, are slept exactly as the run sleeps them)."""
    own, config = loaded.stats, loaded.config
    others = [s for s in snapshot_stats if s is not None]
    new: Stats = {key: dict(entry) for key, entry in own.items()}
    thin_dims: list[str] = []
    for key in dict.fromkeys([*config.input_features, ACTION]):  # the policy's own inputs and output, in order
        entry = own.get(key, {})
        if key in config.image_features or "std" not in entry or "mean" not in entry:
            continue
        thin = entry["std"] < min_std
        if not bool(thin.any()):
            continue
        together = pooled([{key: entry}] + [{key: s[key]} for s in others if key in s], min_std)[key]
        new[key] = {**entry, "mean": torch.where(thin, together["mean"], entry["mean"]),
                    "std": torch.where(thin, together["std"], entry["std"])}
        thin_dims.append(f"{key}{thin.nonzero().flatten().tolist()}")
    if not thin_dims:
        return None
    reexpress_policy(loaded.policy, own, new, min_std)
    features = {**config.input_features, **config.output_features}
    try:
        pre, post = make_pre_post_processors(
            config, pretrained_path=str(loaded.path),
            preprocessor_overrides={"device_processor": {"device": config.device},
                                    "normalizer_processor": {"stats": new, "features": features,
                                                             "norm_map": config.normalization_mapping}},
            postprocessor_overrides={"unnormalizer_processor": {"stats": new, "features": config.output_features,
                                                                "norm_map": config.normalization_mapping}})
    except Exception as exc:  # LeRobot's pipeline loader names neither the file nor the step
        raise CorruptFileError(loaded.path, f"unreadable policy processors ({exc})") from exc
    loaded.preprocessor, loaded.postprocessor, loaded.stats = pre, post, processor_stats(pre, post)
    loaded.policy.set_observation_normalizer(partial(normalize_raw_observations, pre))
    what = (f"standard deviation below {min_std:g} in {', '.join(thin_dims)} (constant in the deployed policy's "
            "dataset): those dimensions normalized with the statistics of the policy's and its memories' snapshots "
            "together, the policy re-expressed with the same actions")
    logger.warning("%s: %s", loaded.path, what)
    return what


def express_targets(read: MemoryFile, loaded: LoadedPolicy) -> LoadedMemory:
    """The memory with its targets in the policy's normalized action space: mapped from its snapshot's action
    statistics (from the deployed checkpoint's when the snapshot is not found) where they differ."""
    memory, target = read.memory, read.memory.tensors["target"]
    source = loaded.deployed_stats if read.snapshot_stats is None else read.snapshot_stats
    label = "unchecked" if read.snapshot_stats is None else "as stored"
    if same_stats(source, loaded.stats, [ACTION]):
        return LoadedMemory(read.path, memory, read.snapshot, label)
    if ACTION not in source or ACTION not in loaded.stats:
        raise ValueError(f"{read.path}: its snapshot {read.snapshot} and the policy {loaded.path} normalize actions "
                         "differently and one has no action (un)normalizer to map the targets with")
    with torch.no_grad():
        mapped = map_actions(target, source[ACTION], loaded.stats[ACTION])
    logger.info("%s: targets re-expressed from %s's action statistics into the policy's", read.path,
                read.snapshot or loaded.path)
    memory = ActorMemory(memory.skill, {**memory.tensors, "target": mapped}, dict(memory.config))
    return LoadedMemory(read.path, memory, read.snapshot, "re-expressed" if read.snapshot_stats is not None
                        else label)


def load_actor_memory(path: Path, loaded: LoadedPolicy) -> LoadedMemory:
    """:func:`read_actor_memory` and :func:`express_targets`: the memory checked against the policy, its targets in
    the policy's normalized action space (module docstring)."""
    return express_targets(read_actor_memory(path, loaded), loaded)


@dataclass
class SleepInputs:
    """Everything the sleep needs, loaded and checked (nothing is written before this exists)."""

    loaded: LoadedPolicy
    memories: list[LoadedMemory]
    anchor: list[torch.Tensor] | None
    wake_snapshots: list[list[torch.Tensor]]
    statistics: str | None = None
    """What :func:`settle_statistics` changed (``None``: the policy's statistics as deployed)."""


def _inside(path: Path, directory: Path) -> bool:
    path, directory = path.resolve(), directory.resolve()
    return path == directory or directory in path.parents


SLEEP_OUTPUT_ENTRIES = ("pretrained_model", RESULTS_FILE, REPORT_FILE, DIAGNOSTICS_FILE, "videos", MANIFEST)
"""What an ``sr-sleep`` output directory holds (module docstring): ``--overwrite=true`` replaces only such a
directory."""


def sleep_output_problem(out: Path) -> str | None:
    """Why the occupied ``out`` is not an earlier ``sr-sleep`` output that ``--overwrite=true`` may replace (None if
    it is): it is not a directory, holds no ``sleep.json``, or holds an entry sr-sleep never writes (a user's folder
    given as output_dir by mistake is never removed)."""
    if not out.is_dir() or out.is_symlink():
        return "not a directory"
    names = sorted(p.name for p in out.iterdir())
    if RESULTS_FILE not in names:
        return f"it holds no {RESULTS_FILE}, so it is not an sr-sleep output"
    foreign = [n for n in names if n not in SLEEP_OUTPUT_ENTRIES]
    if foreign:
        return f"it holds {few_names(foreign)}, which sr-sleep does not write"
    return None


def check_inputs(cfg: OfflineSleepConfig, custom_env: bool = False) -> SleepInputs:
    """Load and check every input of the sleep (see the module docstring); raises one-line errors naming the file."""
    out = cfg.output_dir
    inputs = [cfg.policy.path, *cfg.memories] + ([cfg.anchor.path] if cfg.anchor.path is not None else [])
    for path in inputs:
        if _inside(Path(path), out):
            raise ValueError(f"output_dir {out} holds the input {path}; choose another output_dir")
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        if not cfg.overwrite:
            raise FileExistsError(f"{out} already exists; pass --overwrite=true to replace it")
        problem = sleep_output_problem(out)
        if problem is not None:
            raise OverwriteRefusedError(f"{out}: --overwrite=true refused: {problem}; remove or move it yourself, or "
                                        "choose another output_dir (nothing was removed)")
    if cfg.eval.skills and not custom_env:
        check_eval_envs(cfg.eval)
    loaded = load_policy(Path(cfg.policy.path), cfg.policy.device)
    read = [read_actor_memory(path, loaded) for path in cfg.memories]
    check_memory_order(cfg.memories, [r.memory for r in read], Path(cfg.policy.path))
    statistics = settle_statistics(loaded, [r.snapshot_stats for r in read], cfg.min_std)
    memories = [express_targets(r, loaded) for r in read]
    anchor = None
    if cfg.sleep.anchor_strength > 0:
        if cfg.anchor.path is None:
            anchor = [p.detach().clone() for _, p in loaded.policy.deployed_named_parameters()]
        else:
            anchor = checkpoint_parameters(loaded.policy, Path(cfg.anchor.path), "anchor.path")
    wake_snapshots: list[list[torch.Tensor]] = []
    for m in memories[:-1]:  # theta_i^wake for i < k
        if m.snapshot is None:
            if cfg.gate_decides():
                raise ValueError(
                    f"{m.path}: the gate of Eq. 2 (sleep.anchor_tau={cfg.sleep.anchor_tau}) needs this memory's wake "
                    f"snapshot, but its checkpoint {m.memory.config.get('snapshot', '')!r} is not beside it; give "
                    "--sleep.anchor_tau=null (anchor always on) or --sleep.anchor_strength=0 (no anchor)")
            wake_snapshots = []  # the distances are diagnostics only then: all or none
            break
        wake_snapshots.append(checkpoint_parameters(loaded.policy, m.snapshot, f"the wake snapshot of {m.path}"))
    return SleepInputs(loaded, memories, anchor, wake_snapshots, statistics)


# -- the sleep ---------------------------------------------------------------------------------------------------
def memory_loss(memory: ActorMemory, policy_fn: Callable[[Mapping[str, torch.Tensor]], torch.Tensor]) -> float:
    """L_i(theta) on the memory's whole buffer (the objective's expectation over B_i, not a sampled batch)."""
    total = 0.0
    with torch.no_grad():
        for start in range(0, memory.size, LOSS_BATCH):
            batch = {k: memory.tensors[k][start : start + LOSS_BATCH] for k in memory.buffer_keys}
            total += float(memory.loss(policy_fn, batch)) * len(batch["target"])
    return total / memory.size


def check_eval_envs(eval_cfg: SleepEvalConfig) -> None:
    """Every skill of ``--eval.skills`` has its environment (``--eval.env``, as sr-train checks it): a needle skill
    name, a Meta-World task, a registered gym id or a LeRobot env config; ``ValueError`` naming the key."""
    protocol, skills = eval_cfg.protocol(), list(eval_cfg.skills)
    if protocol.env == "needle":
        unknown = [s for s in skills if s not in NEEDLE_SKILLS]
        if unknown:
            raise ValueError(f"eval.skills: {unknown} have no evaluation environment (the needle environment has "
                             f"{list(NEEDLE_SKILLS)}); other environments: --eval.env=metaworld|gym|lerobot")
        return
    for index in range(len(skills)):
        resolve_eval_env(protocol, skills, index)


def _evaluate(cfg: OfflineSleepConfig, loaded: LoadedPolicy, make_env: EnvFactory | None, video_dir: Path
              ) -> dict[str, Any]:
    skills, protocol = list(cfg.eval.skills), cfg.eval.protocol()
    indices = [NEEDLE_SKILLS.index(s) if s in NEEDLE_SKILLS else i for i, s in enumerate(skills)]
    if make_env is None:
        images = list(loaded.config.image_features)
        size = None if not images else tuple(int(x) for x in loaded.config.image_features[images[0]].shape[1:])
        make_env = make_env_factory(protocol, skills, size)
    results = evaluate_skills(loaded.policy, loaded.preprocessor, loaded.postprocessor, skills, indices, make_env,
                              protocol, video_dir if cfg.eval.videos_per_skill else None, cfg.progress)
    return {s: {"success": r.success, "success_per_seed": r.success_per_seed,
                "videos": [Path(v).relative_to(video_dir.parent.parent).as_posix() for v in r.videos]}
            for s, r in results.items()}


def run_offline_sleep(cfg: OfflineSleepConfig, make_env: EnvFactory | None = None) -> dict[str, Any]:
    """Check the inputs, sleep, evaluate (if asked) and write ``cfg.output_dir``; returns ``sleep.json``'s record.
    ``make_env`` replaces the needle environment for ``--eval.skills`` (tests)."""
    if cfg.torch_threads is not None:
        torch.set_num_threads(cfg.torch_threads)
    inputs = check_inputs(cfg, custom_env=make_env is not None)  # before anything is written
    loaded, memories = inputs.loaded, inputs.memories
    policy = loaded.policy
    problem = act_sleep_problem(policy, cfg.sleep)
    logger.info("sr-sleep: %s (%d deployed parameters) over %d memories %s; anchor %s", loaded.path,
                sum(p.numel() for p in problem.parameters), len(memories), [m.memory.skill for m in memories],
                cfg.anchor.path or "the deployed policy")
    out = cfg.output_dir
    try:
        with staged_directory(out) as tmp:
            before = [memory_loss(m.memory, problem.policy) for m in memories]
            check_losses(memories, before, "before the sleep")
            success_before = _evaluate(cfg, loaded, make_env, tmp / "videos" / "before") if cfg.eval.skills else None
            seed_everything(cfg.sleep.seed)
            t0 = time.perf_counter()
            result = problem.consolidate([m.memory for m in memories], inputs.anchor, inputs.wake_snapshots,
                                         is_final_skill=cfg.final_skill, progress=cfg.progress,
                                         on_iteration=_progress_logger(cfg.sleep))
            seconds = time.perf_counter() - t0
            after = [memory_loss(m.memory, problem.policy) for m in memories]
            check_losses(memories, after, "after the sleep")
            check_moved(memories, before, after, result.stop_iteration)
            success_after = _evaluate(cfg, loaded, make_env, tmp / "videos" / "after") if cfg.eval.skills else None
            record = _record(cfg, inputs, result, seconds, before, after, success_before, success_after)
            policy._reservoir = None  # the consolidated policy has no skill memory of its own to write beside it
            save_pretrained_model(tmp / "pretrained_model", policy, loaded.preprocessor, loaded.postprocessor)
            atomic_write_json(tmp / DIAGNOSTICS_FILE, result.to_dict())
            write_checked_json(tmp / RESULTS_FILE, record)
            atomic_write_bytes(tmp / REPORT_FILE, report_markdown(record).encode())
    except WriteError as exc:  # one line, without the stream's advice to resume
        raise WriteError(exc.path, exc, advice=f"nothing was written to {out}; fix the cause and run sr-sleep "
                                               "again") from exc
    logger.info("sr-sleep: summed memory loss %.4g -> %.4g; written %s", sum(before), sum(after), out)
    return record


class SleepFailedError(ValueError):
    """The sleep cannot be, or was not, a consolidation: a memory's loss is non-finite or absurd, or the sleep moved
    no memory's loss. Nothing is written (the input checkpoint is only ever read)."""


ABSURD_LOSS = 1e4
"""A memory loss above this per action-chunk element (a mean squared difference of normalized actions: 100 standard
deviations on average) is absurd (our choice): its targets are not in the policy's action space, e.g. mapped through
statistics with a standard deviation of ~0."""


def _per_element(memory: ActorMemory, loss: float) -> float:
    """The loss per action-chunk element (a ``sum``-reduced memory sums over the chunk's elements)."""
    target = memory.tensors["target"]
    return loss / max(1, target[0].numel()) if memory.config.get("reduction") == "sum" else loss


def check_losses(memories: Sequence[LoadedMemory], losses: Sequence[float], when: str) -> None:
    """:class:`SleepFailedError` naming the first memory whose loss is non-finite or absurd (:data:`ABSURD_LOSS`)."""
    for m, loss in zip(memories, losses, strict=True):
        if not math.isfinite(loss):
            raise SleepFailedError(f"{m.path}: memory loss {loss} {when} (non-finite): the sleep cannot consolidate "
                                   f"it; nothing was written")
        if _per_element(m.memory, loss) > ABSURD_LOSS:
            raise SleepFailedError(
                f"{m.path}: memory loss {loss:.4g} {when} is absurd (targets {m.targets}; a policy near its data has "
                f"losses of order 1): its targets are not in the policy's action space{_stats_hint(m)}; nothing was "
                "written")


def _stats_hint(m: LoadedMemory) -> str:
    if m.targets == "unchecked":
        return " (its snapshot checkpoint is not beside it, so its statistics are unknown)"
    return " (its snapshot's and the policy's action statistics differ by orders of magnitude)"


def check_moved(memories: Sequence[LoadedMemory], before: Sequence[float], after: Sequence[float],
                iterations: int) -> None:
    """:class:`SleepFailedError` when the sleep changed no memory's loss (its updates never reached the policy)."""
    if any(not math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-12) for a, b in zip(after, before, strict=True)):
        return
    raise SleepFailedError(
        f"{memories[0].path}: memory loss {before[0]:.6g} before and after {iterations} sleep iterations, and no "
        "other memory's moved either: the sleep changed nothing (raise --sleep.lr or --sleep.max_iterations); "
        "nothing was written")


def _progress_logger(config: SleepConfig, clock: Callable[[], float] = time.monotonic
                     ) -> Callable[[int, dict[str, Any]], None]:
    """A log line every tenth of the iteration budget (our choice; the bar shows every iteration), with the time
    spent and the time the rest of the budget takes at this pace (at most: the plateau rule may stop earlier)."""
    every, start = max(1, config.max_iterations // 10), clock()

    def on_iteration(iteration: int, values: dict[str, Any]) -> None:
        done = iteration + 1
        if done % every == 0:
            elapsed = clock() - start
            left = elapsed * (config.max_iterations - done) / done
            logger.info("sleep iteration %d/%d (%.0f%%), %s elapsed, at most ~%s left: objective %.4g, memory "
                        "losses %s", done, config.max_iterations, 100 * done / config.max_iterations,
                        format_duration(elapsed), format_duration(left), values["objective"],
                        [round(x, 5) for x in values["memory_losses"]])

    return on_iteration


def _record(cfg: OfflineSleepConfig, inputs: SleepInputs, result: SleepResult, seconds: float,
            before: list[float], after: list[float], success_before: dict[str, Any] | None,
            success_after: dict[str, Any] | None) -> dict[str, Any]:
    memories = [{"file": str(m.path), "skill": m.memory.skill, "size": m.memory.size,
                 "reduction": m.memory.config.get("reduction"), "snapshot": None if m.snapshot is None
                 else str(m.snapshot), "targets": m.targets, "loss_before": b, "loss_after": a}
                for m, b, a in zip(inputs.memories, before, after, strict=True)]
    success = None
    if success_before is not None and success_after is not None:
        success = {s: {"before": success_before[s]["success"], "after": success_after[s]["success"],
                       "before_per_seed": success_before[s]["success_per_seed"],
                       "after_per_seed": success_after[s]["success_per_seed"],
                       "videos": success_before[s]["videos"] + success_after[s]["videos"]}
                   for s in success_before}
    return {
        "format": RESULTS_FORMAT,
        "version": RESULTS_VERSION,
        "policy": str(cfg.policy.path),
        "anchor": None if cfg.sleep.anchor_strength == 0 else (str(cfg.anchor.path) if cfg.anchor.path else
                                                               "the deployed policy"),
        "final_skill": cfg.final_skill,
        "gate_snapshots": len(inputs.wake_snapshots),
        "statistics": inputs.statistics or "as deployed",
        "sleep_settings": to_jsonable(cfg.sleep),
        "memories": memories,
        "summed_loss": {"before": sum(before), "after": sum(after)},
        "sleep": {"seconds": seconds, **result.summary()},
        "success": success,
        "evaluation": list(cfg.eval.skills) or "off (no --eval.skills)",
        "checkpoint": "pretrained_model",
    }


def report_markdown(record: dict[str, Any]) -> str:
    """``sleep.md``: the before/after tables of a :func:`run_offline_sleep` record."""
    sleep = record["sleep"]
    lines = [
        "# sr-sleep", "",
        f"Policy `{record['policy']}`, anchor: {record['anchor'] or 'none (sleep.anchor_strength=0)'}; "
        f"{sleep['stop_iteration']} iterations ({sleep['stop_reason']}), anchor coefficient "
        f"{sleep['anchor_lambda']:g}, {sleep['seconds']:.1f} s. Consolidated checkpoint: `{record['checkpoint']}/`.",
        "", f"Normalization statistics: {record.get('statistics', 'as deployed')}.",
        "", "Memory losses L_i on each memory's whole buffer (squared action-chunk difference to its frozen snapshot, "
        "in the policy's normalized action space):", "",
        "| # | memory | skill | size | targets | loss before | loss after | change |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for i, m in enumerate(record["memories"], start=1):
        lines.append(f"| {i} | `{Path(m['file']).name}` | {m['skill']} | {m['size']} | {m['targets']} | "
                     f"{m['loss_before']:.4g} | {m['loss_after']:.4g} | {m['loss_after'] - m['loss_before']:+.3g} |")
    total = record["summed_loss"]
    lines.append(f"| | **sum** | | | | {total['before']:.4g} | {total['after']:.4g} | "
                 f"{total['after'] - total['before']:+.3g} |")
    lines.append("")
    if record["success"] is None:
        lines.append("Success: not evaluated (no --eval.skills).")
    else:
        lines += ["| skill | success before | success after |", "| --- | --- | --- |"]
        lines += [f"| {s} | {r['before']:.3f} | {r['after']:.3f} |" for s, r in record["success"].items()]
    return "\n".join(lines) + "\n"
