"""One offline sleep of a deployed ACT-SR policy (Algorithm 1, lines 7-15), with its loss checks."""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch

from lerobot_policy_act_sr.actor_memory import ActorMemory
from sr_imitation.core.sleep import SleepConfig
from sr_imitation.io import (
    WriteError,
    atomic_write_bytes,
    atomic_write_json,
    staged_directory,
    write_checked_json,
)
from sr_imitation.progress import format_duration
from sr_imitation.substrates.act.evaluate import (
    EnvFactory,
    episode_positions,
    evaluate_skills,
    make_env_factory,
)
from sr_imitation.substrates.act.offline_sleep.config import (
    DIAGNOSTICS_FILE,
    LOSS_BATCH,
    REPORT_FILE,
    RESULTS_FILE,
    OfflineSleepConfig,
)
from sr_imitation.substrates.act.offline_sleep.inputs import (
    LoadedMemory,
    LoadedPolicy,
    check_inputs,
)
from sr_imitation.substrates.act.offline_sleep.report import _record, report_markdown
from sr_imitation.substrates.act.substrate import (
    act_sleep_problem,
    save_pretrained_model,
    seed_everything,
)

logger = logging.getLogger(__name__)

def memory_loss(memory: ActorMemory, policy_fn: Callable[[Mapping[str, torch.Tensor]], torch.Tensor]) -> float:
    """L_i(theta) on the memory's whole buffer (the objective's expectation over B_i, not a sampled batch)."""
    total = 0.0
    with torch.no_grad():
        for start in range(0, memory.size, LOSS_BATCH):
            batch = {k: memory.tensors[k][start : start + LOSS_BATCH] for k in memory.buffer_keys}
            total += float(memory.loss(policy_fn, batch)) * len(batch["target"])
    return total / memory.size


def _evaluate(cfg: OfflineSleepConfig, loaded: LoadedPolicy, make_env: EnvFactory | None, video_dir: Path,
              stream: Sequence[str]) -> dict[str, Any]:
    """Success on ``--eval.skills``, each skill's episodes those of its position in ``stream`` (the memories' skills,
    in skill order): the run's own episodes."""
    skills, protocol = list(cfg.eval.skills), cfg.eval.protocol()
    indices = episode_positions(skills, stream)
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
            stream = [m.memory.skill for m in memories]  # the skill order (checked by check_inputs)
            success_before = (_evaluate(cfg, loaded, make_env, tmp / "videos" / "before", stream)
                              if cfg.eval.skills else None)
            seed_everything(cfg.sleep.seed)
            t0 = time.perf_counter()
            result = problem.consolidate([m.memory for m in memories], inputs.anchor, inputs.wake_snapshots,
                                         is_final_skill=cfg.final_skill, progress=cfg.progress,
                                         on_iteration=_progress_logger(cfg.sleep))
            seconds = time.perf_counter() - t0
            after = [memory_loss(m.memory, problem.policy) for m in memories]
            check_losses(memories, after, "after the sleep")
            check_moved(memories, before, after, result.stop_iteration)
            success_after = (_evaluate(cfg, loaded, make_env, tmp / "videos" / "after", stream)
                             if cfg.eval.skills else None)
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
