"""sr-sleep's inputs, loaded and checked before the first gradient: the policy and its memories in one action
space."""

from __future__ import annotations

import logging
import re
from collections.abc import Sequence
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
from sr_imitation.envs.needle.skills import SKILL_NAMES as NEEDLE_SKILLS
from sr_imitation.infra.fingerprint import FINGERPRINT_FILE
from sr_imitation.io import (
    MANIFEST,
    CorruptFileError,
    verify_checkpoint,
)
from sr_imitation.lerobot_compat import is_torch_device_available
from sr_imitation.stream.rundir import RUN_CONFIG_FILE, OverwriteRefusedError, check_run_config, few_names
from sr_imitation.stream.substrate_base import load_weights
from sr_imitation.substrates.act.evaluate import resolve_eval_env
from sr_imitation.substrates.act.normalization import (
    Stats,
    map_actions,
    pooled,
    reexpress_policy,
    same_stats,
)
from sr_imitation.substrates.act.offline_sleep.config import (
    DIAGNOSTICS_FILE,
    PRETRAINED_FILES,
    REPORT_FILE,
    RESULTS_FILE,
    OfflineSleepConfig,
    SleepEvalConfig,
)
from sr_imitation.substrates.act.substrate import (
    deployed_parameters,
    normalize_raw_observations,
)

logger = logging.getLogger(__name__)

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
    load_weights(policy, state, path / "model.safetensors")
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
