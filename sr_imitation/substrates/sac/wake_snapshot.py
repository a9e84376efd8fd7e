"""Mid-wake snapshots: a SAC wake killed at any point resumes from its last snapshot with identical results.

A wake is one phase of the stream engine, and a phase killed inside used to be redone from its start (same numbers,
all its time again): at the gate preset's budgets (``configs/sac_mt5_gate.json``) one wake, or the MT-Joint oracle's
one training phase, is up to two hours on one core. So :func:`~sr_imitation.substrates.sac.wake.train_skill` writes, at
an episode boundary every ``--wake.snapshot_every_s`` seconds of wall time (default 300, our choice; a snapshot of a
full 160k-transition replay is about 55 MB, written in well under a second), everything the rest of the wake
depends on to one checked safetensors file, and a wake that finds that file continues from it:

- the agent's whole state (actor with its excitability, twin critic and its target, alpha, the observation
  normalizer) and its three Adam states;
- the replay buffer and the critic's held-out transitions (the rows filled so far, and the running count);
- the wake's own generator, the process's global generators (torch's, CUDA's, NumPy's, Python's), and the
  environment's generators (per-episode configuration choice and the simulator's own);
- the loop's record: episode rewards, successes and start positions, counters, the carried update credit and the
  last update's numbers.

When and whether a snapshot is written depends on wall time only; writing one reads the state and draws nothing, so
the numbers of a run never depend on it (``tests/substrates/sac/test_wake_snapshot.py`` kills a wake between episodes
and checks the resumed one bit for bit against one that was never stopped). The file is removed when the wake ends.
A continual method's wake hooks travel with the snapshot: their generator and counters and the method's own wake state
(``ContinualMethod.wake_state``: A-GEM's reference gradient, PCGrad's projection-order generator, Nash-MTL's warm
start); a wake shaped by hooks that do not declare their state (``resumable_wake_hooks`` False, a new method's
default) is not snapshotted: killed, it starts again.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch

from sr_imitation.infra.snapshot import (
    load_weights,
    optimizer_tensors,
    prefixed,
    read_snapshot,
    restore_optimizer,
    write_snapshot,
)
from sr_imitation.substrates.sac.sac import ReplayBuffer, SACAgent, UpdateInfo

logger = logging.getLogger(__name__)

FORMAT = "sr_imitation.rl.wake_snapshot"
"""The format name written in the file (the module's name before the substrates/ move: files keep their format)."""
VERSION = 2
_BUFFER_FIELDS = ("obs", "next_obs", "actions", "rewards", "terminated")
_OPTIMIZERS = ("actor_optimizer", "critic_optimizer", "alpha_optimizer")


class SeededEnv(Protocol):
    """What a snapshot needs of an environment: its generators' state, as plain data."""

    def rng_state(self) -> dict[str, Any]: ...

    def set_rng_state(self, state: dict[str, Any]) -> None: ...


@dataclasses.dataclass
class WakeLoop:
    """The wake loop's own record (what :class:`~sr_imitation.substrates.sac.wake.WakeResult` accumulates, and the
    loop's carried variables)."""

    episode_rewards: list[float]
    episode_successes: list[bool]
    episode_starts: list[int]
    env_steps: int
    updates: int
    update_credit: float
    info: UpdateInfo | None
    seconds: float
    """Wall time of the wake so far (reported only; never part of a result's numbers)."""

    @property
    def episodes(self) -> int:
        return len(self.episode_rewards)


def save(path: Path, identity: dict[str, Any], loop: WakeLoop, agent: SACAgent, env: SeededEnv,
         replay: ReplayBuffer, holdout: ReplayBuffer, rng: np.random.Generator, hooks: Any = None) -> None:
    """Write the snapshot of a wake between two episodes (atomically; checked on load); ``hooks``: the method's
    resumable wake hooks, if any."""
    tensors = {f"agent.{n}": t for n, t in agent.state_dict().items()}
    for name in _OPTIMIZERS:  # 0-d tensors (alpha, Adam's steps) keep their shape: checked files store them as is
        tensors.update(optimizer_tensors(name, getattr(agent, name)))
    for prefix, buffer in (("replay", replay), ("holdout", holdout)):
        for field in _BUFFER_FIELDS:  # the filled rows: a view, written as it is
            tensors[f"{prefix}.{field}"] = torch.from_numpy(getattr(buffer, field)[: len(buffer)])
    tensors["loop.episode_rewards"] = torch.tensor(loop.episode_rewards, dtype=torch.float64)
    tensors["loop.episode_successes"] = torch.tensor(loop.episode_successes, dtype=torch.bool)
    tensors["loop.episode_starts"] = torch.tensor(loop.episode_starts, dtype=torch.int64)
    header = {
        "replay_total": replay.total, "holdout_total": holdout.total,
        "rng": rng.bit_generator.state, "env_rng": env.rng_state(),
        "env_steps": loop.env_steps, "updates": loop.updates, "update_credit": loop.update_credit,
        "info": None if loop.info is None else dataclasses.asdict(loop.info), "seconds": loop.seconds,
    }
    write_snapshot(path, {"format": FORMAT, "version": VERSION, **identity}, tensors, header, hooks)


def load(path: Path, identity: dict[str, Any], agent: SACAgent, env: SeededEnv, replay: ReplayBuffer,
         holdout: ReplayBuffer, rng: np.random.Generator, hooks: Any = None) -> WakeLoop:
    """Restore a wake from its snapshot into freshly built ``agent``, ``env``, buffers and ``rng``; returns the
    loop's record. A snapshot of another wake, format or agent is a :class:`CorruptFileError` naming the file."""
    tensors, header = read_snapshot(path, {"format": FORMAT, "version": VERSION, **identity}, hooks)
    load_weights(path, agent, prefixed(tensors, "agent."), "agent")
    agent.normalizer.refresh_seen()
    for name in _OPTIMIZERS:
        restore_optimizer(name, getattr(agent, name), tensors)
    for prefix, buffer in (("replay", replay), ("holdout", holdout)):
        for field in _BUFFER_FIELDS:
            rows = tensors[f"{prefix}.{field}"].numpy()
            getattr(buffer, field)[: len(rows)] = rows
        buffer.total = int(header[f"{prefix}_total"])
    rng.bit_generator.state = header["rng"]
    env.set_rng_state(header["env_rng"])
    info = header["info"]
    return WakeLoop(
        episode_rewards=tensors["loop.episode_rewards"].tolist(),
        episode_successes=tensors["loop.episode_successes"].tolist(),
        episode_starts=tensors["loop.episode_starts"].tolist(),
        env_steps=int(header["env_steps"]), updates=int(header["updates"]),
        update_credit=float(header["update_credit"]), info=None if info is None else UpdateInfo(**info),
        seconds=float(header["seconds"]))
