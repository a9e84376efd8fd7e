"""The SAC substrate of the stream engine (:class:`~sr_imitation.stream.substrate.Substrate`) on Meta-World.

Per stage k, under ``stages/<k+1:02d>_<skill>/`` (every file written atomically; checkpoints checksummed):

- ``wake``: SAC on skill k (:func:`~sr_imitation.substrates.sac.wake.train_skill`, excitability at the wake rate), which
  also freezes the critic memory M_k from its replay buffer (``memory.safetensors``, written with the wake); while it
  runs, ``wake_snapshot.safetensors`` every few minutes (:mod:`sr_imitation.substrates.sac.wake_snapshot`: a wake killed
  inside resumes from it with identical results);
  checkpoint ``wake/agent.safetensors`` (the whole agent: theta_k^wake, the gate snapshot of later sleeps);
- ``wake.eval``: before a sleep, skill k alone (``eval.after_wake``; the reference of BWT_wake); without a sleep,
  every learned skill (the stage's evaluation, reused as the after-wake one: same policy, same configurations);
- ``sleep``: Nash-bargained sleep with the actor's sleep-rate excitability after every update (Eq. 3); checkpoint
  ``sleep/agent.safetensors`` and ``sleep/sleep_diagnostics.json``;
- stage evaluations write ``trajectories.safetensors`` (SPI inputs) and videos under ``videos/stage_<k>_<skill>/``.

Evaluation is paired (common random numbers): skill i is evaluated on the same Meta-World configurations after its
wake and after every stage (:func:`~sr_imitation.substrates.sac.evaluate.evaluation_configurations`). Seeds: the network
from ``seed_sequence(seed, K, 1)``, stage k's wake from ``seed_sequence(seed, k)``, its sleep from salts 2 (sleep
sampling) and 3 (excitability batches), every other phase from salt ``10 + phase id``.
"""

from __future__ import annotations

import dataclasses
import logging
import shutil
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch

from sr_imitation.core.excitability import activity_recording_off, update_excitability
from sr_imitation.core.memory import Memory
from sr_imitation.core.metrics import policy_motion
from sr_imitation.envs.metaworld.tasks import STREAMS, SkillEnv, canonical_skill
from sr_imitation.envs.metaworld.video import rendering_unavailable
from sr_imitation.infra.threads import set_torch_threads
from sr_imitation.io import load_checked_safetensors, save_checked_safetensors
from sr_imitation.stream.substrate import MethodSettings, SleepProblem, seed_sequence
from sr_imitation.stream.substrate_base import SubstrateBase
from sr_imitation.substrates.sac.config import RLTrainConfig
from sr_imitation.substrates.sac.critic_memory import CriticMemory
from sr_imitation.substrates.sac.evaluate import SPI_FEATURES, evaluate_policy, evaluation_configurations
from sr_imitation.substrates.sac.results import SUBSTRATE, write_results
from sr_imitation.substrates.sac.sac import SACAgent, TwinQ
from sr_imitation.substrates.sac.wake import train_skill

logger = logging.getLogger(__name__)

WAKE_SNAPSHOT = "wake_snapshot.safetensors"
"""A wake's snapshot in its stage folder, while the wake runs (:mod:`sr_imitation.substrates.sac.wake_snapshot`)."""
CHECKPOINT_FORMAT = "sr_imitation.rl.stage"
"""The format name of every file this substrate writes is ``sr_imitation.rl.<what>`` (the package's
name before the substrates/ move: files keep their format)."""
CHECKPOINT_VERSION = 3
"""3: one checkpoint per policy-changing phase (``wake/``, ``sleep/``) of the stream engine (2: one per stage with
the wake snapshot inside; 1: per-stage evaluation draws)."""


class SACSubstrate(SubstrateBase):
    """SAC with an excitability-gated actor on a Meta-World stream (checkpoints and files: :class:`SubstrateBase`)."""

    name: ClassVar[str] = SUBSTRATE
    seed_scheme: ClassVar[str] = "seed_sequence"
    wake_hooks: ClassVar[frozenset[str]] = frozenset({"wake_batch", "wake_loss", "adjust_gradients"})
    extension_keys: ClassVar[tuple[str, ...]] = ("stream.name", "stream.skills", "stream.extend_from")
    stage_folder: ClassVar[str] = "stages/{n:02d}_{skill}"
    checkpoint_file: ClassVar[str] = "agent.safetensors"
    memory_files: ClassVar[str] = "stages/{n:02d}_{skill}/{name}.safetensors"

    def __init__(self, cfg: RLTrainConfig) -> None:
        self.cfg = cfg
        self.skills = cfg.stream_skills
        self.out = Path(cfg.output_dir)
        self._eval_envs: dict[str, SkillEnv] = {}
        self._videos = cfg.eval.videos_per_skill > 0
        self._memories: dict[int, CriticMemory] = {}

    def method_settings(self) -> MethodSettings:
        return MethodSettings(sleep=self.cfg.sleep.enabled, distill_weight=None,
                              extra={"aggregator": self.cfg.sleep.aggregator})

    # -- set-up and seeding ---------------------------------------------------------------------------------
    def setup(self) -> None:
        set_torch_threads(self.cfg.torch_threads, logger)
        torch.manual_seed(seed_sequence(self.cfg.seed, len(self.skills), 1))  # network initialization
        self.agent = SACAgent(self.cfg.sac, self.cfg.excitability, device=self.cfg.device)
        if self._videos and (reason := rendering_unavailable()) is not None:
            logger.warning("no evaluation videos: offscreen rendering is unavailable (%s); set MUJOCO_GL=egl "
                           "or eval.videos_per_skill=0", reason)
            self._videos = False

    @property
    def run_seed(self) -> int:
        return self.cfg.seed

    def begin_phase(self, k: int, phase: str, seed: int) -> None:
        torch.manual_seed(seed % (2**63))
        np.random.seed(seed % (2**32))

    # -- files (SubstrateBase writes and reads them) -------------------------------------------------------------
    def video_dir(self, k: int) -> Path:
        """Videos of the evaluation after stage ``k`` (every learned skill), named like the stage directory."""
        return self.out / "videos" / f"stage_{k + 1:02d}_{canonical_skill(self.skills[k])}"

    def checkpoint_header(self, k: int, phase: str) -> dict[str, Any]:
        return {"format": CHECKPOINT_FORMAT, "format_version": CHECKPOINT_VERSION, "stage": k, "phase": phase,
                "skill": self.skills[k], "seed": self.cfg.seed}

    def checkpoint_module(self) -> torch.nn.Module:
        """The whole agent: actor, critics, temperature, normalizer (a checkpoint resumes SAC, not only the actor)."""
        return self.agent

    # -- phases -----------------------------------------------------------------------------------------------
    def wake(self, k: int, memories: Sequence[Memory], distill_weight: float, method: Any = None
             ) -> tuple[dict[str, Any], dict[str, Any]]:
        if memories:
            raise ValueError("the SAC wake has no distillation term (the paper's wake is plain SAC); methods shape "
                             "it through their wake hooks")
        cfg = self.cfg
        t0 = time.perf_counter()
        seed = seed_sequence(cfg.seed, k)
        with SkillEnv(self.skills[k], seed=seed % (2**31), max_episode_steps=cfg.max_episode_steps) as env:
            self.stage_dir(k).mkdir(parents=True, exist_ok=True)
            wake, memory = train_skill(self.agent, env, k, cfg.sac, cfg.wake, cfg.excitability, cfg.memory,
                                       seed=seed, progress=cfg.progress, method=method,
                                       snapshot=self.stage_dir(k) / WAKE_SNAPSHOT)
        snapshot = getattr(self.agent.actor, "snapshot_normalizer", None)  # per-skill modules (CompoNet)
        if snapshot is not None:
            snapshot(k, self.agent.normalizer)  # before the wake checkpoint, which keeps it
        # what the memory phase may need once the replay buffer is gone (kept for a resume; not a memory itself)
        memory.save(self.memory_path(k))  # SR's M_k comes from the wake's replay buffer
        if wake.state_sample is not None:
            save_checked_safetensors(self.stage_dir(k) / "state_sample.safetensors",
                                     {"state": wake.state_sample},
                                     {**self.checkpoint_header(k, "wake"), "format": "sr_imitation.rl.state_sample"})
        if wake.transition_sample is not None:
            save_checked_safetensors(self.stage_dir(k) / "transition_sample.safetensors",
                                     wake.transition_sample,
                                     {**self.checkpoint_header(k, "wake"),
                                      "format": "sr_imitation.rl.transition_sample"})
        self._memories[k] = memory
        # the phase's whole time: a wake resumed from its snapshot adds the time it had run before (our choice, as
        # the ACT wake does; runs written before 2026-11-28 count from the resume: reporting.summary.phase_seconds)
        return {"wake": wake.summary(), "seconds": time.perf_counter() - t0 + wake.seconds_before_resume}, {}

    def make_memory(self, k: int) -> Memory:
        memory = self._memories.pop(k, None)
        return memory if memory is not None else self.load_memory(k)

    # -- what continual methods ask of the policy ---------------------------------------------------------------
    def memory_states(self, k: int) -> torch.Tensor:
        """The raw late-wake states of SR's memory M_k (``memory.buffer_size`` of them; DER stores these too)."""
        memory = self._memories.get(k)
        if memory is None:
            memory = CriticMemory.load(self.memory_path(k), skill=self.memory_skill(k))
        return memory.tensors["state"]

    def state_sample(self, k: int, n: int | None = None) -> torch.Tensor:
        """Raw states drawn uniformly from wake k's replay (``method.wake_state_sample`` of them, drawn during the
        wake; ``n`` is not used: the replay is gone by now)."""
        tensors, _ = load_checked_safetensors(self.stage_dir(k) / "state_sample.safetensors")
        return tensors["state"]

    def reset_networks(self, k: int) -> None:
        """Freshly initialized actor, critic, target critic and temperature (Reset & Distill's network for skill k),
        seeded from (run seed, k); the observation normalizer is kept. The global random state is left as it was."""
        saved = torch.random.get_rng_state()
        torch.manual_seed(seed_sequence(self.cfg.seed, k, 20) % (2**63))
        fresh = SACAgent(self.cfg.sac, self.cfg.excitability, device=self.cfg.device)
        torch.random.set_rng_state(saved)
        fresh.normalizer.load_state_dict(self.agent.normalizer.state_dict())
        self.agent.load_state_dict(fresh.state_dict())
        self.agent.reset_optimizers(reset_alpha=True)

    def replace_actor(self, build: Callable[..., torch.nn.Module]) -> None:
        """Put ``build(sac_config, n_skills)`` in place of the actor (seeded from the run seed; fresh optimizers):
        a method's architecture (CompoNet). Called before any checkpoint is loaded."""
        saved = torch.random.get_rng_state()
        torch.manual_seed(seed_sequence(self.cfg.seed, len(self.skills), 21) % (2**63))
        self.agent.actor = build(self.cfg.sac, len(self.skills)).to(self.agent.device)
        torch.random.set_rng_state(saved)
        self.agent.reset_optimizers()

    def current_actor(self) -> torch.nn.Module:
        """The actor trained now (CompoNet's composed actor once it replaced the plain one)."""
        return self.agent.actor

    def reset_critic(self, k: int) -> None:
        """A freshly initialized twin critic and target for skill k (CompoNet's critic per skill), seeded from
        (run seed, k); actor, normalizer and temperature are kept. The global random state is left alone."""
        saved = torch.random.get_rng_state()
        torch.manual_seed(seed_sequence(self.cfg.seed, k, 22) % (2**63))
        fresh = TwinQ(self.cfg.sac).to(self.agent.device)
        torch.random.set_rng_state(saved)
        self.agent.critic.load_state_dict(fresh.state_dict())
        self.agent.critic_target.load_state_dict(fresh.state_dict())
        self.agent.reset_optimizers(reset_alpha=True)

    def load_actor(self, k: int, phase: str) -> None:
        """Only the actor of the checkpoint after ``phase`` of stage k (Reset & Distill's shared actor)."""
        state = self.checkpoint_state(k, phase)
        self.agent.actor.load_state_dict({n.removeprefix("actor."): t for n, t in state.items()
                                          if n.startswith("actor.")})

    def memory_skill(self, k: int) -> str:
        """The skill name memories of stage k carry (without the Meta-World version)."""
        return canonical_skill(self.skills[k])

    def transition_sample(self, k: int) -> dict[str, torch.Tensor]:
        """Transitions (obs, actions, rewards, next_obs, terminated) drawn uniformly from wake k's replay
        (``method.wake_transition_sample`` of them)."""
        tensors, _ = load_checked_safetensors(self.stage_dir(k) / "transition_sample.safetensors")
        return tensors

    def gaussian_policy(self, states: torch.Tensor) -> torch.Tensor:
        """The actor's pre-tanh Gaussian on raw states as one tensor [mean, log std] (B x 8; DER's target). Its
        forward passes are not the actor's recorded activity (Eq. 3 follows the SAC updates only)."""
        with activity_recording_off(self.agent.actor):
            x = self.agent.normalizer(states.to(self.agent.device, torch.float32)).float()
            mean, log_std = self.agent.actor(x)
        return torch.cat([mean, log_std], dim=-1)

    def policy_parameters(self) -> list[torch.Tensor]:
        """theta: the actor's trainable parameters (what the sleep and the methods' penalties act on; what
        ``parameters_at`` reads from a checkpoint)."""
        return list(self.agent.actor_parameters())

    def log_likelihood(self, states: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """log pi_theta(u | s) of one pre-tanh action u ~ pi_theta(.|s) drawn per state (B,), differentiable in
        theta: its squared gradient, averaged over states, is the policy's Fisher information (EWC)."""
        gaussian = self.gaussian_policy(states)
        mean, log_std = gaussian.chunk(2, dim=-1)
        with torch.no_grad():
            u = mean + log_std.exp() * torch.randn(mean.shape, generator=generator)
        return torch.distributions.Normal(mean, log_std.exp()).log_prob(u).sum(-1)

    def wake_eval_skills(self, k: int, sleeps: bool) -> list[int]:
        if not sleeps:
            return list(range(k + 1))  # the stage's evaluation, also the after-wake one
        return [k] if self.cfg.eval.after_wake else []

    def evaluate(self, k: int, phase: str, skills: Sequence[int]) -> dict[str, Any]:
        stage_eval = list(skills) == list(range(k + 1))  # every learned skill: the stage's evaluation
        rows, trajectories = self.evaluate_rows(k, skills, videos=stage_eval, trajectories=stage_eval)
        if stage_eval:
            traj = {f"traj.{canonical_skill(s)}": torch.as_tensor(x) for s, x in trajectories.items()}
            save_checked_safetensors(self.stage_dir(k) / "trajectories.safetensors", traj,
                                     {**self.checkpoint_header(k, phase), "format": "sr_imitation.rl.traj",
                                      "spi_features": list(SPI_FEATURES)})
        logger.info("stage %d %s: success %s", k + 1, phase, [round(r["success_rate"], 3) for r in rows])
        return {"rows": rows, "stage_evaluation": stage_eval}

    def evaluate_rows(self, k: int, skills: Sequence[int], videos: bool = False, trajectories: bool = True
                      ) -> tuple[list[dict[str, Any]], dict[str, np.ndarray]]:
        """Evaluate ``skills`` (indices), each on its paired configurations (the same at every stage); each row
        lists them, and with ``videos`` its mp4 files (relative to the output directory). Returns the rows and, with
        ``trajectories`` (only stage evaluations keep them), per skill the SPI input (:func:`policy_motion` of
        ``SPI_FEATURES``) of its episodes."""
        cfg, agent = self.cfg, self.agent
        rows, motions = [], {}
        spec = cfg.eval.video_spec(self.video_dir(k)) if videos and self._videos else None
        if spec is not None:
            shutil.rmtree(spec.directory, ignore_errors=True)  # leftovers of a killed attempt at this stage
        select = getattr(agent.actor, "select_skill", None)  # an architecture with per-skill modules (CompoNet)
        live = agent.normalizer
        try:
            for i in skills:
                skill = self.skills[i]
                if select is not None:
                    select(i)
                    agent.normalizer = agent.actor.module_normalizer(i, live)  # its own end-of-wake statistics
                env = self._eval_envs.get(skill)
                if env is None:
                    env = self._eval_envs[skill] = SkillEnv(skill, seed=0, max_episode_steps=cfg.max_episode_steps)
                configurations = evaluation_configurations(cfg.seed, skill, cfg.eval.episodes)
                res = evaluate_policy(
                    lambda obs: agent.act(obs, deterministic=cfg.eval.deterministic), env, cfg.eval.episodes,
                    seed=cfg.seed, success_mode=cfg.eval.success_mode, stop_on_success=cfg.eval.stop_on_success,
                    record_trajectories=trajectories, configurations=configurations, video=spec,
                )
                rows.append({**res.summary(), "configurations": configurations})
                if spec is not None:
                    rows[-1]["videos"] = [p.relative_to(self.out).as_posix() for p in res.videos]
                if trajectories:
                    motions[skill] = policy_motion(res.trajectories, SPI_FEATURES)
        finally:
            agent.normalizer = live
        return rows, motions

    def sleep_problem(self, k: int, memories: Sequence[Memory]) -> SleepProblem:
        cfg, agent = self.cfg, self.agent
        sleep_cfg = dataclasses.replace(cfg.sleep, seed=seed_sequence(cfg.seed, k, 2) % (2**31))
        rate = cfg.excitability.rate("sleep")
        gen = torch.Generator().manual_seed(seed_sequence(cfg.seed, k, 3) % (2**31))

        def excitability_step(_iteration: int) -> None:
            # Eq. 3 at the sleep rate, from the actor's activity on a batch of every memory's states
            if rate <= 0.0:
                return
            batches = [m.sample(sleep_cfg.batch_size, gen) for m in memories]  # expert memories: "input.state"
            states = torch.cat([b["state"] if "state" in b else b["input.state"] for b in batches])
            with torch.no_grad():
                agent.policy_fn(states)
            update_excitability(agent.actor, rate)

        def critic_values() -> dict[str, Any]:
            # the frozen critics' values (SR's expert memories, --method_options={expert_memory: ...}, have none)
            return {"frozen_critic_value": [m.value(agent.policy_fn) for m in memories if isinstance(m, CriticMemory)]}

        return SleepProblem(agent.actor_parameters(), agent.policy_fn, sleep_cfg, excitability_step, critic_values)

    def source_skills(self, settings: dict[str, Any]) -> list[str]:
        skills = settings.get("stream.skills")
        return list(skills) if skills not in (None, {}) else list(STREAMS[settings["stream.name"]])

    def report(self, progress: dict[str, Any], memories: Sequence[Memory], final_phases: Sequence[str]
               ) -> dict[str, Any]:
        for env in self._eval_envs.values():
            env.close()
        self._eval_envs.clear()
        return write_results(self, progress, list(memories))
