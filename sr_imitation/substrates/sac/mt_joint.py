"""The MT-joint oracle of the paper's MT5 table (appendix B.1): one SAC agent trained on all skills at once.

    python -m sr_imitation.substrates.sac.mt_joint --config_path=configs/sac_mt5_cpu.json --seed=0 \\
        --output_dir=outputs/mt_joint

Every episode draws one skill uniformly (its own seeded generator) and one of that skill's 50 configurations; one
replay buffer, the same SAC, plain actor (no excitability: it is Sleeping Robots' mechanism) and update-to-data
ratio as the stream, for ``episodes`` episodes (paper: 13,000, times ``wake.budget_scale`` like every wake budget;
no early stopping). Then every skill is evaluated exactly as in the stream (the same fixed configurations per
skill). Reported apart: there is no sequence, so the results file's success matrix repeats the final evaluation in
every row and the after-wake row (AFSR and PRS are the final ones; BWT = 0 by definition; SPI is undefined, null).

Phases (``progress.json``; a run killed inside a phase redoes it with the same numbers): ``train`` (checkpoint
``agent.safetensors``; a training killed inside continues from ``train_snapshot.safetensors``, written every few
minutes, :mod:`sr_imitation.substrates.sac.wake_snapshot`), ``eval``. Settings are fingerprinted and checked before
anything is written, as for a stream.
"""

from __future__ import annotations

import dataclasses
import logging
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sr_imitation.envs.metaworld.tasks import SkillEnv, StepResult, canonical_skill
from sr_imitation.infra.fingerprint import SettingsFingerprint, settings_fingerprint
from sr_imitation.infra.folder_lock import hold_folder
from sr_imitation.infra.provenance import log_code_version
from sr_imitation.infra.threads import set_torch_threads
from sr_imitation.io import load_checked_safetensors, save_checked_safetensors
from sr_imitation.reporting.results import build_results, write_results
from sr_imitation.stream.rundir import RUN_CONFIG_FILE, RunDirectory
from sr_imitation.stream.substrate import seed_sequence
from sr_imitation.substrates.sac.config import RESUME_ALLOW_LIST, RLTrainConfig, SkillBudget
from sr_imitation.substrates.sac.evaluate import evaluate_policy, evaluation_configurations
from sr_imitation.substrates.sac.results import prs_pairs
from sr_imitation.substrates.sac.sac import SACAgent
from sr_imitation.substrates.sac.wake import train_skill

logger = logging.getLogger(__name__)

JOINT = "mt-joint"
PAPER_EPISODES = 13_000
"""Episodes of the paper's MT-joint oracle (appendix B.1), before ``wake.budget_scale``."""


class MultiSkillEnv:
    """All skills behind one environment interface: each :meth:`reset` draws a skill uniformly (seeded)."""

    def __init__(self, skills: list[str], seed: int, max_episode_steps: int) -> None:
        self.skill = JOINT
        self.envs = [SkillEnv(s, seed=seed % (2**31) + i, max_episode_steps=max_episode_steps)
                     for i, s in enumerate(skills)]
        self.seed(seed)
        self.current = self.envs[0]

    def seed(self, seed: int) -> None:
        self._rng = np.random.default_rng([seed % (2**63), 99])
        for i, env in enumerate(self.envs):
            env.seed(seed % (2**31) + i)

    def rng_state(self) -> dict[str, Any]:
        """The skill choice's generator and every skill environment's (:meth:`SkillEnv.rng_state`)."""
        return {"choice": self._rng.bit_generator.state, "envs": [env.rng_state() for env in self.envs]}

    def set_rng_state(self, state: dict[str, Any]) -> None:
        self._rng.bit_generator.state = state["choice"]
        for env, own in zip(self.envs, state["envs"], strict=True):
            env.set_rng_state(own)

    def reset(self) -> np.ndarray:
        self.current = self.envs[int(self._rng.integers(len(self.envs)))]
        return self.current.reset()

    def step(self, action: np.ndarray) -> StepResult:
        return self.current.step(action)

    def close(self) -> None:
        for env in self.envs:
            env.close()

    def __enter__(self) -> MultiSkillEnv:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def joint_config(cfg: RLTrainConfig, episodes: int) -> RLTrainConfig:
    """The stream config as the oracle uses it: plain actor, a fixed budget of ``episodes`` (scaled), no early
    stopping."""
    wake = dataclasses.replace(cfg.wake, early_stopping=False,
                               budgets={**cfg.wake.budgets, JOINT: SkillBudget(episodes, episodes, episodes)})
    return dataclasses.replace(cfg, wake=wake, excitability=dataclasses.replace(cfg.excitability, enabled=False))


def joint_fingerprint(cfg: RLTrainConfig, episodes: int = PAPER_EPISODES) -> SettingsFingerprint:
    """The settings the oracle run of the stream config ``cfg`` is fingerprinted with (as :func:`run_mt_joint`)."""
    return settings_fingerprint(_stored_config(joint_config(cfg, episodes), episodes), RESUME_ALLOW_LIST)


def _stored_config(joint: RLTrainConfig, episodes: int) -> dict[str, Any]:
    return {**joint.stored_config(), "mt_joint_episodes": episodes}


def run_mt_joint(cfg: RLTrainConfig, episodes: int = PAPER_EPISODES) -> dict[str, Any]:
    """Train (or resume) the multi-task oracle in ``cfg.output_dir``, as its only writer (its lock held throughout);
    returns the results dictionary."""
    with hold_folder(cfg.output_dir):
        return _run_mt_joint(joint_config(cfg, episodes), episodes)


def _run_mt_joint(cfg: RLTrainConfig, episodes: int) -> dict[str, Any]:
    """:func:`run_mt_joint` of the joint config ``cfg`` once its output_dir's lock is held."""
    out = Path(cfg.output_dir)
    stored = _stored_config(cfg, episodes)
    run = RunDirectory(out, settings_fingerprint(stored, RESUME_ALLOW_LIST), RUN_CONFIG_FILE, stored, cfg.resume,
                       cfg.overwrite)
    run.prepare()
    with run.undo_on_error():  # a run --overwrite replaced comes back if the start fails
        log_code_version(logger)
        set_torch_threads(cfg.torch_threads, logger)
        torch.manual_seed(seed_sequence(cfg.seed, len(cfg.stream_skills), 1))
        agent = SACAgent(cfg.sac, cfg.excitability, device=cfg.device)
        skills = cfg.stream_skills
        checkpoint = out / "agent.safetensors"
        header = {"format": "sr_imitation.rl.mt_joint", "seed": cfg.seed, "skills": list(skills)}
        if not run.done(0, "train"):
            seed = seed_sequence(cfg.seed, 0)
            torch.manual_seed(seed % (2**63))
            np.random.seed(seed % (2**32))
            t0 = time.perf_counter()
            with MultiSkillEnv(skills, seed, cfg.max_episode_steps) as env:
                wake, _ = train_skill(agent, env, 0, cfg.sac, cfg.wake, cfg.excitability, cfg.memory, seed=seed,
                                      progress=cfg.progress, snapshot=out / "train_snapshot.safetensors")
            tensors = {n: t.reshape(-1) if t.ndim == 0 else t for n, t in agent.state_dict().items()}
            save_checked_safetensors(checkpoint, tensors, header)
            run.mark(0, "train", {"wake": wake.summary(),
                                  "seconds": time.perf_counter() - t0 + wake.seconds_before_resume})
        else:
            tensors, _ = load_checked_safetensors(checkpoint)
            shapes = {n: t.shape for n, t in agent.state_dict().items()}
            agent.load_state_dict({n: t.reshape(shapes[n]) for n, t in tensors.items()})
    if not run.done(0, "eval"):
        rows = []
        for skill in skills:
            with SkillEnv(skill, seed=0, max_episode_steps=cfg.max_episode_steps) as env:
                configurations = evaluation_configurations(cfg.seed, skill, cfg.eval.episodes)
                res = evaluate_policy(lambda obs: agent.act(obs, deterministic=cfg.eval.deterministic), env,
                                      cfg.eval.episodes, seed=cfg.seed, success_mode=cfg.eval.success_mode,
                                      stop_on_success=cfg.eval.stop_on_success, record_trajectories=False,
                                      configurations=configurations)
            rows.append({**res.summary(), "configurations": configurations})
        run.mark(0, "eval", {"rows": rows})
    rows = run.record(0, "eval")["rows"]
    final = np.array([row["success_rate"] for row in rows])
    n = len(skills)
    matrix = np.tile(final, (n, 1))
    matrix[np.triu_indices(n, 1)] = np.nan
    names = [canonical_skill(s) for s in skills]
    results = build_results(substrate="sac", method="mt_joint", sleep_enabled=False, seed=cfg.seed, skills=names,
                            pairs=prs_pairs(skills), success=matrix[None], after_wake=final[None],
                            spi=np.full((1, n), np.nan), spi_features=[], memory_bytes={},
                            stages=[run.record(0, "train")], config=stored,
                            extra={"oracle": "all skills trained jointly; rows repeat the final evaluation"})
    write_results(out, results, plots=cfg.plots)
    return results


def main(args: list[str] | None = None) -> None:
    from sr_imitation.infra.cli_errors import run_cli, setup_logging
    from sr_imitation.substrates.sac.cli import parse

    def _main(argv: list[str]) -> None:
        setup_logging()
        episodes = PAPER_EPISODES
        rest = []
        for a in argv:
            if a.startswith("--episodes="):
                episodes = int(a.split("=", 1)[1])
            else:
                rest.append(a)
        results = run_mt_joint(parse(rest), episodes)
        logger.info("MT-joint: final success %s, AFSR %.3f", results["success_matrix"][-1],
                    results["metrics"]["afsr"]["final"])

    run_cli("mt-joint", _main, list(sys.argv[1:] if args is None else args))


if __name__ == "__main__":
    main()
