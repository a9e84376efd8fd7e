"""The ACT substrate's measurements for the shared results (:mod:`sr_imitation.reporting.results`): success matrices
and SPI curves per evaluation seed (the evaluation unit), from the files the stream wrote.

Everything is rebuilt from the files the stream wrote (``eval.json`` and ``trajectories.npz`` per phase), so a
resumed run reports exactly what an uninterrupted one does.

BWT has two references (``sr_imitation.core.metrics``): ``bwt`` the success on skill i after stage i (after its
sleep when there is one), ``bwt_wake`` the success on skill i right after its own wake (the ``wake.eval`` of stage
i). Both are computed per evaluation seed: the seed's episodes reset identically in every phase, so the
differences are paired. SPI uses only the tool's own state (``substrates.act.evaluate.SPI_FEATURES``), sliced here.

Files (written by :func:`sr_imitation.reporting.results.write_results`): ``results.json``, ``results.md``,
``metrics.png``, ``success_matrix.png``.

Without an evaluation environment (``--eval.env=none``) there is no success: the results say ``evaluation: none``,
AFSR, PRS, BWT and SPI are null, and ``losses`` holds what the stream measured instead (:func:`loss_matrices`): each
stored memory's loss and each skill's validation l1 under the policy after every stage and right after every wake.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sr_imitation.core.memory import Memory
from sr_imitation.core.metrics import all_pairs, policy_motion, spi_at_stage
from sr_imitation.envs.metaworld.tasks import MT5_PAIRS, canonical_skill
from sr_imitation.envs.needle.skills import PRS_PAIRS as SURGICAI_PAIRS
from sr_imitation.io import load_checked_safetensors, read_checked_json
from sr_imitation.reporting.results import (
    build_results,
    memory_budget,
    metric_curves,
    summarize_curve,
    unit_mean,
    write_results,
)
from sr_imitation.stream.substrate import PHASES
from sr_imitation.substrates.act.evaluate import spi_features

PAIR_LISTS = ("surgicai", "mt5", "all", "adjacent")
"""The names ``--stream.pairs`` takes (:func:`pair_list`)."""


def pair_list(name: str, skills: Sequence[str]) -> list[tuple[str, str]]:
    """``surgicai`` (the paper's 7 pairs), ``mt5`` (the paper's 6 MT5 pairs, matched by Meta-World skill identity:
    ``reach-v3`` is ``reach``), each restricted to the skills in the stream, ``all`` or ``adjacent``."""
    if name == "mt5":
        by_identity = {canonical_skill(s): s for s in skills}
        return [(by_identity[a], by_identity[b]) for a, b in MT5_PAIRS if a in by_identity and b in by_identity]
    if name == "surgicai":
        present = set(skills)
        return [p for p in SURGICAI_PAIRS if p[0] in present and p[1] in present]
    if name == "all":
        return list(all_pairs(list(skills)))
    if name == "adjacent":
        return list(zip(skills[:-1], skills[1:], strict=True))
    raise ValueError(f"unknown pair list {name!r}; choose one of {PAIR_LISTS}")


def no_pairs_warning(name: str, skills: Sequence[str]) -> str | None:
    """Why PRS will be n/a on this stream, when the pair list ``name`` holds no pair of its ``skills`` (e.g. the
    default ``surgicai`` on Meta-World skills); ``None`` when it holds one, or the stream has one skill."""
    if len(skills) < 2 or pair_list(name, skills):
        return None
    return (f"--stream.pairs={name} names no pair of the skills {list(skills)}: PRS (Eq. 5) will be n/a; "
            "--stream.pairs=mt5 (Meta-World's MT5 skills), all or adjacent give it pairs")


def _load_eval(phase_dir: Path) -> dict[str, Any]:
    return read_checked_json(phase_dir / "eval.json")


TRAJECTORIES_FILE = "trajectories.safetensors"
"""An evaluation's SPI trajectories (checked safetensors, one tensor ``<skill>__<episode>`` each); runs written
before they were sealed have ``trajectories.npz`` with the same names (still read)."""


def _load_trajectories(phase_dir: Path) -> dict[str, list[np.ndarray]]:
    out: dict[str, list[np.ndarray]] = {}
    if (phase_dir / TRAJECTORIES_FILE).is_file():
        tensors, _ = load_checked_safetensors(phase_dir / TRAJECTORIES_FILE)
        arrays = {key: t.numpy() for key, t in tensors.items()}
    else:
        with np.load(phase_dir / "trajectories.npz") as data:
            arrays = {key: data[key] for key in data.files}
    for key in sorted(arrays, key=lambda k: (k.split("__")[0], int(k.split("__")[1]))):
        out.setdefault(key.split("__")[0], []).append(arrays[key])
    return out


def _matrices(phase_dirs: Sequence[Path], skills: Sequence[str], n_seeds: int) -> np.ndarray:
    """S[seed, k, i] from the evaluation after each stage (NaN above the diagonal)."""
    k_total = len(skills)
    s = np.full((n_seeds, k_total, k_total), np.nan)
    for k, phase_dir in enumerate(phase_dirs):
        record = _load_eval(phase_dir)
        for i in range(k + 1):
            s[:, k, i] = record[skills[i]]["success_per_seed"]
    return s


def _spi_curves(
    phase_dirs: Sequence[Path], skills: Sequence[str], n_seeds: int
) -> tuple[np.ndarray, tuple[int, ...]]:
    """SPI_k per evaluation seed, and the agent_pos entries used. Reference = skill i's trajectories right after
    stage i; each episode enters as the motion of its ``spi_features`` (``SPI_FEATURES`` for the needle env;
    ``policy_motion``), the only place the stored agent_pos is sliced."""
    trajs = [_load_trajectories(d) for d in phase_dirs]
    features = spi_features(int(trajs[0][skills[0]][0].shape[1]))
    curves = np.full((n_seeds, len(skills)), np.nan)
    for seed in range(n_seeds):
        def stacked(stage: int, skill: str, seed: int = seed) -> np.ndarray:
            episodes = trajs[stage][skill]
            per_seed = len(episodes) // n_seeds
            return policy_motion(episodes[seed * per_seed : (seed + 1) * per_seed], features)

        for k in range(1, len(skills)):
            earlier = list(skills[:k])
            reference = {s: stacked(i, s) for i, s in enumerate(earlier)}
            current = {s: stacked(k, s) for s in earlier}
            curves[seed, k] = spi_at_stage(reference, current, earlier)
    return curves, features


LOSS_KEYS = ("memory_loss", "validation_l1")
"""What an evaluation without an environment measures per skill (``eval.json``; ``substrates.act.substrate``)."""


def loss_matrices(final_dirs: Sequence[Path], wake_dirs: Sequence[Path], skills: Sequence[str],
                  stages: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """``results.json``'s ``losses`` of a run without evaluation environment: for each of :data:`LOSS_KEYS` the K x K
    matrix after every stage (row k: the policy after stage k, its sleep when it slept; column i: skill i) and the one
    right after every wake (null above the diagonal; ``memory_loss`` null where the method stores no actor memory),
    and ``wake_best_val_l1``: each wake's best validation l1 (the l1 its early stopping saw)."""
    n = len(skills)
    out: dict[str, Any] = {}
    for name, dirs in (("", final_dirs), ("_after_wake", wake_dirs)):
        matrices = {key: np.full((n, n), np.nan) for key in LOSS_KEYS}
        for k, phase_dir in enumerate(dirs):
            record = _load_eval(phase_dir)
            for i in range(k + 1):
                for key in LOSS_KEYS:
                    value = record[skills[i]][key]
                    matrices[key][k, i] = np.nan if value is None else value
        out.update({f"{key}{name}": matrices[key].tolist() for key in LOSS_KEYS})
    out["wake_best_val_l1"] = [stage.get("wake", {}).get("best_val_l1") for stage in stages]
    return out


def write_report(
    out: Path,
    skills: Sequence[str],
    pairs_name: str,
    progress: dict[str, Any],
    config: dict[str, Any],
    final_dirs: Sequence[Path],
    wake_dirs: Sequence[Path],
    memories: Sequence[Memory],
    evaluation: str = "needle",
) -> dict[str, Any]:
    """Build results.json, results.md, metrics.png and success_matrix.png in ``out`` (the shared schema of
    :mod:`sr_imitation.reporting.results`; evaluation units are the evaluation seeds). ``evaluation``: the run's
    ``--eval.env`` (``none``: no success, :func:`loss_matrices` instead, no plots)."""
    pairs = pair_list(pairs_name, skills)
    done = progress["completed"]
    stages = [{"stage": k, "skill": skill, **{phase: done[f"{k + 1}.{phase}"] for phase in PHASES
                                               if f"{k + 1}.{phase}" in done}}
              for k, skill in enumerate(skills)]
    per_skill, per_kind = memory_budget(memories)
    if evaluation == "none":
        results = build_results(
            substrate="act", method=config["method"], sleep_enabled=config["sleep"]["enabled"], seed=config["seed"],
            skills=skills, pairs=pairs, success=None, after_wake=None, spi=None, spi_features=[],
            memory_bytes=per_skill, memory_kinds=per_kind, stages=stages, config=config, evaluation=evaluation,
            losses=loss_matrices(final_dirs, wake_dirs, skills, stages))
        write_results(out, results, plots=False)
        return results
    n_seeds = len(config["eval"]["seeds"])
    s_final = _matrices(final_dirs, skills, n_seeds)
    s_wake = _matrices(wake_dirs, skills, n_seeds)
    spi, features = _spi_curves(final_dirs, skills, n_seeds)
    wake_curves = metric_curves(s_wake, skills, pairs, None)
    extra = {  # the whole matrix right after each wake, and its metrics (the same run before each sleep)
        "success_matrix_after_wake": unit_mean(s_wake).tolist(),
        "metrics_after_wake": {name: summarize_curve(c) for name, c in wake_curves.items()},
        "episodes_per_skill_per_unit": config["eval"]["episodes"],
    }
    results = build_results(
        substrate="act", method=config["method"], sleep_enabled=config["sleep"]["enabled"], seed=config["seed"],
        skills=skills, pairs=pairs, success=s_final, after_wake=np.stack([np.diag(m) for m in s_wake]), spi=spi,
        spi_features=features, memory_bytes=per_skill,
        memory_kinds=per_kind, stages=stages, config=config,
        extra=extra, evaluation=None if evaluation == "needle" else evaluation)
    write_results(out, results)
    return results
