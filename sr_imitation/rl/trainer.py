"""The MT5 stream trainer (Algorithm 1 with the SAC substrate).

For each skill k of the stream: wake (SAC, :func:`~sr_imitation.rl.wake.train_skill`) -> frozen critic memory
M_k -> evaluation of skill k right after its wake (``eval.after_wake``, on by default) -> sleep over M_1..M_k when
k >= 2 (:func:`~sr_imitation.core.sleep.sleep_consolidate`: Nash bargaining, anchor gate of Eq. 2, sleep-rate
excitability) -> evaluation of the shared actor on every learned skill -> one checkpoint directory per stage. After
the stream: success matrix, AFSR/PRS/BWT (after-stage and after-own-wake references)/SPI, ``results.json``, plots
and a short ``report.md``.

Evaluation is paired (common random numbers): skill i is evaluated on the same Meta-World configurations after
its wake and after every stage (:func:`~sr_imitation.rl.evaluate.evaluation_configurations`). Without a sleep
(k = 1, wake-only) the after-wake policy is the stage policy, so the stage evaluation of skill k is reused as its
after-wake evaluation (same configurations, same deterministic policy: the same numbers) instead of running twice.

Output layout (every file written atomically; ``stage.json`` is written last and marks a completed stage)::

    <output_dir>/settings_fingerprint.json, config.json   (written once at the start, never on resume)
    <output_dir>/stages/01_reach/{agent.safetensors, memory.safetensors, trajectories.safetensors, stage.json}
    <output_dir>/videos/stage_01_reach/reach_episode0_success.mp4   (eval.videos_per_skill per learned skill)
    <output_dir>/videos/stage_02_door-open/{reach,door-open}_episode0_<success|failure>.mp4
    ...
    <output_dir>/results.json, report.md, plots/*.png

Every stage reseeds torch and numpy from (seed, stage) and resets optimizers and replay, so ``--resume`` after a
kill continues from the last completed stage and, on CPU, reproduces the uninterrupted run exactly.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sr_imitation.core.excitability import update_excitability
from sr_imitation.core.fingerprint import (
    FINGERPRINT_FILE,
    SettingsFingerprint,
    check_settings,
    read_fingerprint,
    settings_from_config,
    write_fingerprint,
)
from sr_imitation.core.io import (
    CorruptFileError,
    atomic_write_bytes,
    atomic_write_json,
    load_checked_safetensors,
    read_json,
    save_checked_safetensors,
)
from sr_imitation.core.metrics import (
    MT5_PAIRS,
    all_pairs,
    canonical_skill,
    policy_motion,
    spi_at_stage,
    stream_metrics,
)
from sr_imitation.core.sleep import sleep_consolidate
from sr_imitation.rl.config import RLTrainConfig
from sr_imitation.rl.critic_memory import CriticMemory
from sr_imitation.rl.envs import SkillEnv
from sr_imitation.rl.evaluate import SPI_FEATURES, evaluate_policy, evaluation_configurations
from sr_imitation.rl.sac import SACAgent
from sr_imitation.rl.video import rendering_unavailable
from sr_imitation.rl.wake import train_skill

logger = logging.getLogger(__name__)

CHECKPOINT_FORMAT = "sr_imitation.rl.stage"
CHECKPOINT_VERSION = 2
"""2: paired evaluation configurations and SPI trajectories of SPI_FEATURES motions (1: per-stage draws, 39-d)."""
RESULTS_VERSION = 2
"""results.json schema: 2 adds ``success_after_own_wake``, ``metrics.bwt_wake``, ``spi_features``."""
WAKE_PREFIX = "wake_snapshot."


def stage_seed(seed: int, stage: int, salt: int = 0) -> int:
    """Deterministic per-stage seed (independent of whether earlier stages ran in this process)."""
    return int(np.random.SeedSequence([seed, stage, salt]).generate_state(1)[0])


def prs_pairs(skills: list[str]) -> tuple[tuple[str, str], ...]:
    """MT5 (either order): the paper's six pairs; MT8: all 28 pairs; other lists: MT5 pairs present, else all."""
    names = [canonical_skill(s) for s in skills]
    if len(names) == 8:
        return all_pairs(names)
    present = tuple(p for p in MT5_PAIRS if p[0] in names and p[1] in names)
    return present or all_pairs(names)


class StreamTrainer:
    """Runs (or resumes) one seed of the stream described by ``cfg``.

    ``after_stage`` (tests) is called with the stage index after each completed stage; raising there simulates
    a killed run.
    """

    def __init__(self, cfg: RLTrainConfig, after_stage: Callable[[int], None] | None = None) -> None:
        self.cfg = cfg
        self.skills = cfg.stream_skills
        self.out = Path(cfg.output_dir)
        self.after_stage = after_stage
        self._eval_envs: dict[str, SkillEnv] = {}
        self._videos = cfg.eval.videos_per_skill > 0

    # -- output directory ----------------------------------------------------------------------------------
    def _prepare_output_dir(self) -> int:
        """Create/validate the output dir; returns the number of completed stages to skip.

        Fresh run: the settings fingerprint and ``config.json`` are written once. Resume: the requested settings are
        checked against the stored fingerprint before anything is written, and nothing stored is rewritten."""
        fingerprint = self.cfg.resume_fingerprint()
        exists = self.out.exists() and any(self.out.iterdir())
        if exists and not (self.cfg.resume or self.cfg.overwrite):
            raise FileExistsError(f"{self.out} already exists and is not empty; pass --resume=true to continue it "
                                  "or --overwrite=true to replace it")
        if exists and self.cfg.overwrite:
            shutil.rmtree(self.out)
            exists = False
        if exists:
            if self._check_resume_settings(fingerprint):  # a run from before fingerprints: store them once
                write_fingerprint(self.out / FINGERPRINT_FILE, fingerprint)
            return self._completed_stages()
        self.out.mkdir(parents=True, exist_ok=True)
        write_fingerprint(self.out / FINGERPRINT_FILE, fingerprint)
        atomic_write_json(self.out / "config.json", self.cfg.stored_config())
        return 0

    def _check_resume_settings(self, fingerprint: SettingsFingerprint) -> bool:
        """Compare with the stored fingerprint (runs from before fingerprints: the ``fingerprint`` in their
        ``config.json``); :class:`SettingsMismatchError` naming every differing key. Returns whether the run had
        no fingerprint file."""
        path = self.out / FINGERPRINT_FILE
        if path.is_file():
            check_settings(path, read_fingerprint(path), fingerprint)
            return False
        path = self.out / "config.json"
        if not path.is_file():
            raise CorruptFileError(path, f"cannot resume: neither {FINGERPRINT_FILE} nor config.json is there")
        saved = read_json(path)
        if not isinstance(saved, dict) or not isinstance(saved.get("fingerprint"), dict):
            raise CorruptFileError(path, f"cannot resume: no {FINGERPRINT_FILE} and no fingerprint in config.json")
        check_settings(path, settings_from_config(saved["fingerprint"]), fingerprint)
        return True

    def stage_dir(self, k: int) -> Path:
        return self.out / "stages" / f"{k + 1:02d}_{canonical_skill(self.skills[k])}"

    def _completed_stages(self) -> int:
        done = 0
        for k in range(len(self.skills)):
            if (self.stage_dir(k) / "stage.json").is_file():
                done = k + 1
            else:
                break
        return done

    # -- checkpoints -----------------------------------------------------------------------------------------
    def _save_stage(self, k: int, agent: SACAgent, memory: CriticMemory, wake_snapshot: list[torch.Tensor],
                    trajectories: dict[str, np.ndarray], record: dict[str, Any]) -> None:
        d = self.stage_dir(k)
        d.mkdir(parents=True, exist_ok=True)
        # 0-d tensors (log alpha, normalizer count) are stored as shape (1,): the core digest needs >= 1 dim
        tensors = {f"agent.{n}": t.reshape(-1) if t.ndim == 0 else t for n, t in agent.state_dict().items()}
        tensors.update({f"{WAKE_PREFIX}{i}": t for i, t in enumerate(wake_snapshot)})
        header = {"format": CHECKPOINT_FORMAT, "format_version": CHECKPOINT_VERSION, "stage": k,
                  "skill": self.skills[k], "seed": self.cfg.seed}
        save_checked_safetensors(d / "agent.safetensors", tensors, header)
        memory.save(d / "memory.safetensors")
        traj = {f"traj.{canonical_skill(s)}": torch.as_tensor(x) for s, x in trajectories.items()}
        save_checked_safetensors(d / "trajectories.safetensors", traj,
                                 {**header, "format": "sr_imitation.rl.traj", "spi_features": list(SPI_FEATURES)})
        atomic_write_json(d / "stage.json", record)

    def _load_stage(self, k: int, agent: SACAgent) -> tuple[CriticMemory, list[torch.Tensor], dict[str, Any]]:
        d = self.stage_dir(k)
        path = d / "agent.safetensors"
        tensors, header = load_checked_safetensors(path)
        want = {"format": CHECKPOINT_FORMAT, "format_version": CHECKPOINT_VERSION, "stage": k,
                "skill": self.skills[k], "seed": self.cfg.seed}
        got = {key: header.get(key) for key in want}
        if got != want:
            raise CorruptFileError(path, f"checkpoint header {got} does not match the expected {want}")
        shapes = {n: t.shape for n, t in agent.state_dict().items()}
        state = {n.removeprefix("agent."): t for n, t in tensors.items() if n.startswith("agent.")}
        state = {n: t.reshape(shapes[n]) if n in shapes and t.numel() == shapes[n].numel() else t
                 for n, t in state.items()}
        try:
            agent.load_state_dict(state, strict=True)
        except RuntimeError as exc:
            raise CorruptFileError(path, f"agent weights do not fit this configuration: {exc}") from exc
        snapshot = [tensors[f"{WAKE_PREFIX}{i}"] for i in range(sum(n.startswith(WAKE_PREFIX) for n in tensors))]
        memory = CriticMemory.load(d / "memory.safetensors", skill=canonical_skill(self.skills[k]))
        record = json.loads((d / "stage.json").read_text())
        return memory, snapshot, record

    def video_dir(self, k: int) -> Path:
        """Videos of the evaluation after stage ``k`` (every learned skill), named like the stage directory."""
        return self.out / "videos" / f"stage_{k + 1:02d}_{canonical_skill(self.skills[k])}"

    def _load_trajectories(self, k: int) -> dict[str, np.ndarray]:
        tensors, _ = load_checked_safetensors(self.stage_dir(k) / "trajectories.safetensors")
        return {n.removeprefix("traj."): t.numpy() for n, t in tensors.items()}

    # -- phases -----------------------------------------------------------------------------------------------
    def _sleep(self, k: int, agent: SACAgent, memories: list[CriticMemory], anchor: list[torch.Tensor],
               wake_snapshots: list[list[torch.Tensor]]) -> dict[str, Any]:
        cfg = self.cfg
        sleep_cfg = dataclasses.replace(cfg.sleep, seed=stage_seed(cfg.seed, k, 2) % (2**31))
        rate = cfg.excitability.rate("sleep")
        gen = torch.Generator().manual_seed(stage_seed(cfg.seed, k, 3) % (2**31))

        def excitability_step(_iteration: int) -> None:
            # Eq. 3 at the sleep rate, from the actor's activity on a batch of every memory's states
            if rate <= 0.0:
                return
            states = torch.cat([m.sample(sleep_cfg.batch_size, gen)["state"] for m in memories])
            with torch.no_grad():
                agent.policy_fn(states)
            update_excitability(agent.actor, rate)

        before = [m.value(agent.policy_fn) for m in memories]
        result = sleep_consolidate(
            agent.actor_parameters(), agent.policy_fn, memories, sleep_cfg, anchor_params=anchor,
            wake_snapshots=wake_snapshots[:-1], is_final_skill=(k == len(self.skills) - 1),
            step_callback=excitability_step, progress=cfg.progress,
        )
        after = [m.value(agent.policy_fn) for m in memories]
        return {
            **result.summary(),
            "frozen_critic_value_before": before,
            "frozen_critic_value_after": after,
            "frozen_critic_value_change": [a - b for a, b in zip(after, before, strict=True)],
            "anchor_distances": result.anchor_distances,
            "sleep_objective_first_last": [result.sleep_objective[0], result.sleep_objective[-1]]
            if result.sleep_objective else None,
        }

    def _evaluate(self, k: int, agent: SACAgent, only_current: bool = False, videos: bool = False
                  ) -> tuple[list[dict[str, Any]], dict[str, np.ndarray]]:
        """Evaluate every skill learned so far (only skill k with ``only_current``), each on its paired
        configurations (:func:`evaluation_configurations`: the same at every stage); each row lists them, and
        with ``videos`` its mp4 files (relative to the output directory). Returns the rows and, per skill, the
        SPI input (:func:`policy_motion` of ``SPI_FEATURES``) of its episodes."""
        cfg = self.cfg
        rows, trajectories = [], {}
        spec = cfg.eval.video_spec(self.video_dir(k)) if videos and self._videos else None
        if spec is not None:
            shutil.rmtree(spec.directory, ignore_errors=True)  # leftovers of a killed attempt at this stage
        for i, skill in enumerate(self.skills[: k + 1]):
            if only_current and i < k:
                continue
            env = self._eval_envs.get(skill)
            if env is None:
                env = self._eval_envs[skill] = SkillEnv(skill, seed=0, max_episode_steps=cfg.max_episode_steps)
            configurations = evaluation_configurations(cfg.seed, skill, cfg.eval.episodes)
            res = evaluate_policy(
                lambda obs: agent.act(obs, deterministic=cfg.eval.deterministic), env, cfg.eval.episodes,
                seed=cfg.seed, success_mode=cfg.eval.success_mode, stop_on_success=cfg.eval.stop_on_success,
                record_trajectories=True, configurations=configurations, video=spec,
            )
            rows.append({**res.summary(), "configurations": configurations})
            if spec is not None:
                rows[-1]["videos"] = [p.relative_to(self.out).as_posix() for p in res.videos]
            trajectories[skill] = policy_motion(res.trajectories, SPI_FEATURES)
        return rows, trajectories

    # -- main loop -------------------------------------------------------------------------------------------
    def run(self) -> dict[str, Any]:
        cfg = self.cfg
        torch.set_num_threads(cfg.torch_threads)
        start_stage = self._prepare_output_dir()
        torch.manual_seed(stage_seed(cfg.seed, len(self.skills), 1))  # network initialization
        agent = SACAgent(cfg.sac, cfg.excitability, device=cfg.device)
        memories: list[CriticMemory] = []
        wake_snapshots: list[list[torch.Tensor]] = []
        records: list[dict[str, Any]] = []
        for k in range(start_stage):
            memory, snapshot, record = self._load_stage(k, agent)
            memories.append(memory)
            wake_snapshots.append(snapshot)
            records.append(record)
        if start_stage:
            logger.info("resuming %s after %d completed stage(s)", self.out, start_stage)
        if self._videos and start_stage < len(self.skills) and (reason := rendering_unavailable()) is not None:
            logger.warning("no evaluation videos: offscreen rendering is unavailable (%s); set MUJOCO_GL=egl "
                           "or eval.videos_per_skill=0", reason)
            self._videos = False

        for k in range(start_stage, len(self.skills)):
            skill = self.skills[k]
            t0 = time.perf_counter()
            seed = stage_seed(cfg.seed, k)
            torch.manual_seed(seed % (2**63))
            np.random.seed(seed % (2**32))
            anchor = [p.detach().clone() for p in agent.actor_parameters()]  # theta_{k-1}^sleep
            with SkillEnv(skill, seed=seed % (2**31), max_episode_steps=cfg.max_episode_steps) as env:
                wake, memory = train_skill(agent, env, k, cfg.sac, cfg.wake, cfg.excitability, cfg.memory,
                                           seed=seed, progress=cfg.progress)
            memories.append(memory)
            wake_snapshots.append([p.detach().clone() for p in agent.actor_parameters()])  # theta_k^wake
            record: dict[str, Any] = {"stage": k, "skill": skill, "wake": wake.summary(),
                                      "memory": {"states": memory.size, "nbytes": memory.nbytes()}}
            sleeps = k >= 1 and cfg.sleep_enabled
            if cfg.eval.after_wake and sleeps:
                record["eval_after_wake"] = {**self._evaluate(k, agent, only_current=True)[0][-1],
                                             "reused_stage_evaluation": False}
            if sleeps:
                record["sleep"] = self._sleep(k, agent, memories, anchor, wake_snapshots)
            record["eval"], trajectories = self._evaluate(k, agent, videos=True)
            if not sleeps:  # no sleep: the after-wake policy is the stage policy (free, so even with after_wake off)
                row = {key: value for key, value in record["eval"][-1].items() if key != "videos"}
                record["eval_after_wake"] = {**row, "reused_stage_evaluation": True}
            record["seconds"] = time.perf_counter() - t0
            self._save_stage(k, agent, memory, wake_snapshots[-1], trajectories, record)
            records.append(record)
            logger.info("stage %d (%s) done in %.1fs: success %s", k + 1, skill, record["seconds"],
                        [round(r["success_rate"], 3) for r in record["eval"]])
            if self.after_stage is not None:
                self.after_stage(k)
        for env in self._eval_envs.values():
            env.close()
        results = self._results(records, memories)
        atomic_write_json(self.out / "results.json", results)
        atomic_write_bytes(self.out / "report.md", render_report(results).encode())
        if cfg.plots:
            write_plots(results, self.out / "plots")
        return results

    def _results(self, records: list[dict[str, Any]], memories: list[CriticMemory]) -> dict[str, Any]:
        n = len(self.skills)
        matrix = np.full((n, n), np.nan)
        for k, rec in enumerate(records):
            for i, row in enumerate(rec["eval"]):
                matrix[k, i] = row["success_rate"]
        trajectories = [self._load_trajectories(k) for k in range(n)]
        names = [canonical_skill(s) for s in self.skills]
        reference = {names[i]: trajectories[i][names[i]] for i in range(n)}
        spi = [spi_at_stage(reference, trajectories[k], names[:k]) for k in range(n)]
        pairs = prs_pairs(self.skills)
        after_wake = [rec["eval_after_wake"]["success_rate"] if "eval_after_wake" in rec else None
                      for rec in records]
        complete = all(x is not None for x in after_wake[:-1])
        metrics = stream_metrics(matrix, names, pairs, spi=spi,
                                 wake_diagonal=[np.nan if x is None else x for x in after_wake] if complete else None)
        if not complete:  # eval.after_wake was off: the after-own-wake reference was not measured
            metrics["bwt_wake"], metrics["bwt_wake_curve"] = float("nan"), [float("nan")] * n
        return {
            "results_version": RESULTS_VERSION,
            "seed": self.cfg.seed,
            "skills": names,
            "method": "sleeping_robots" if self.cfg.sleep_enabled else "wake_only",
            "pairs": [list(p) for p in pairs],
            "success_matrix": [[None if np.isnan(x) else float(x) for x in row] for row in matrix],
            "success_after_own_wake": after_wake,
            "metrics": _nan_to_none(metrics),
            "spi_features": list(SPI_FEATURES),
            "memory_nbytes_total": int(sum(m.nbytes() for m in memories)),
            "stages": records,
            "config": self.cfg.stored_config(),
        }


def _nan_to_none(obj: Any) -> Any:
    """Strict JSON: NaN (undefined metric, e.g. PRS at k = 1) becomes null."""
    if isinstance(obj, dict):
        return {k: _nan_to_none(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_nan_to_none(v) for v in obj]
    if isinstance(obj, float) and np.isnan(obj):
        return None
    return obj


REPORT_METRICS = ("afsr", "prs", "bwt", "bwt_wake", "spi")
METRIC_LABELS = {"afsr": "AFSR", "prs": "PRS", "bwt": "BWT (ref. after stage i)",
                 "bwt_wake": "BWT_wake (ref. after own wake)", "spi": "SPI"}


def render_report(results: dict[str, Any]) -> str:
    """A short markdown report: success matrix, success right after each skill's own wake, final metrics."""
    names = results["skills"]
    lines = [f"# SAC stream report ({results['method']}, seed {results['seed']})", "",
             "Success S[k, i] after stage k (rows) on skill i (columns):", "",
             "| after \\ skill | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
    for k, row in enumerate(results["success_matrix"]):
        cells = ["" if x is None else f"{x:.2f}" for x in row]
        lines.append(f"| {k + 1}. {names[k]} | " + " | ".join(cells) + " |")
    wake = results.get("success_after_own_wake")
    if wake is not None:
        lines.append("| right after own wake | " + " | ".join("-" if x is None else f"{x:.2f}" for x in wake) + " |")
    m = results["metrics"]
    lines += ["", "| metric | final | per stage |", "|---|---|---|"]
    for key in REPORT_METRICS:
        if key in m:
            curve = ", ".join("-" if x is None else f"{x:.3f}" for x in m[f"{key}_curve"])
            final = "-" if m[key] is None else f"{m[key]:.3f}"
            lines.append(f"| {METRIC_LABELS[key]} | {final} | {curve} |")
    lines += ["", f"Memory stored: {results['memory_nbytes_total'] / 1e6:.2f} MB", ""]
    return "\n".join(lines)


def write_plots(results: dict[str, Any], plot_dir: Path) -> None:
    """Success-matrix heatmap and metric curves (PNG, written atomically)."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = results["skills"]
    matrix = np.array([[np.nan if x is None else x for x in row] for row in results["success_matrix"]])
    fig, ax = plt.subplots(figsize=(1.2 * len(names) + 2, 1.0 * len(names) + 1.5))
    im = ax.imshow(matrix, vmin=0, vmax=1, cmap="viridis")
    ax.set_xticks(range(len(names)), names, rotation=45, ha="right")
    ax.set_yticks(range(len(names)), [f"after {n}" for n in names])
    for (k, i), v in np.ndenumerate(matrix):
        if not np.isnan(v):
            ax.text(i, k, f"{v:.2f}", ha="center", va="center", color="w" if v < 0.5 else "k", fontsize=8)
    fig.colorbar(im, ax=ax, label="success")
    ax.set_title(f"{results['method']} seed {results['seed']}")
    _save_fig(fig, plot_dir / "success_matrix.png", io, plt)

    m = results["metrics"]
    fig, axes = plt.subplots(1, 4, figsize=(14, 3))
    for ax, keys in zip(axes, (("afsr",), ("prs",), ("bwt", "bwt_wake"), ("spi",)), strict=True):
        for key in keys:
            curve = [np.nan if x is None else x for x in m.get(f"{key}_curve", [])]
            ax.plot(range(1, len(curve) + 1), curve, marker="o", label=METRIC_LABELS[key])
        ax.set_title(" / ".join(key.upper() for key in keys))
        if len(keys) > 1:
            ax.legend(fontsize=7)
        ax.set_xlabel("stage k")
        ax.grid(alpha=0.3)
    _save_fig(fig, plot_dir / "metrics.png", io, plt)


def _save_fig(fig, path: Path, io, plt) -> None:
    buf = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())
