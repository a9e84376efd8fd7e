"""Results of a stream run: success matrices, AFSR/PRS/BWT/BWT_wake/SPI per evaluation seed with mean +- SE, plots.

Everything is rebuilt from the files the stream wrote (``eval.json`` and ``trajectories.npz`` per phase), so a
resumed run reports exactly what an uninterrupted one does.

BWT has two references (``sr_imitation.core.metrics``): ``bwt`` the success on skill i after stage i (after its
sleep when there is one), ``bwt_wake`` the success on skill i right after its own wake (the ``wake.eval`` of stage
i). Both are computed per evaluation seed: the seed's episodes reset identically in every phase, so the
differences are paired. SPI uses only the tool's own state (``imitation.evaluate.SPI_FEATURES``), sliced here.

Files: ``results.json``, ``results.md`` (tables), ``metrics.png`` (AFSR, PRS, BWT and BWT_wake, SPI against k,
like the paper's Figure 2, shaded +- SE over evaluation seeds), ``success_matrix.png`` (heatmap of S[k][i]).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sr_imitation.core.io import atomic_write_bytes, atomic_write_json
from sr_imitation.core.memory import Memory
from sr_imitation.core.metrics import (
    SURGICAI_PAIRS,
    afsr_curve,
    all_pairs,
    bwt_curve,
    mean_sem,
    policy_motion,
    prs_curve,
    spi_at_stage,
)
from sr_imitation.imitation.evaluate import spi_features

METRICS = ("afsr", "prs", "bwt", "bwt_wake", "spi")
LABELS = {"afsr": "AFSR", "prs": "PRS", "bwt": "BWT (ref. after stage i)",
          "bwt_wake": "BWT_wake (ref. after own wake)", "spi": "SPI"}
RESULTS_VERSION = 2
"""results.json schema: 2 adds ``metrics.bwt_wake``, ``success_after_own_wake(_per_seed)``, ``spi_features``;
SPI is computed on ``spi_features`` motions (1: no version field, SPI on the full 35-d ``agent_pos``)."""


def pair_list(name: str, skills: Sequence[str]) -> list[tuple[str, str]]:
    """``surgicai`` (the paper's 7 pairs, restricted to skills in the stream), ``all`` or ``adjacent``."""
    if name == "surgicai":
        present = set(skills)
        return [p for p in SURGICAI_PAIRS if p[0] in present and p[1] in present]
    if name == "all":
        return list(all_pairs(list(skills)))
    if name == "adjacent":
        return list(zip(skills[:-1], skills[1:], strict=True))
    raise ValueError(f"unknown pair list {name!r}; choose surgicai, all or adjacent")


def _seed_mean(s: np.ndarray) -> np.ndarray:
    """Mean over evaluation seeds, NaN above the diagonal (no warning for the all-NaN cells)."""
    with np.errstate(invalid="ignore"):
        counts = np.sum(~np.isnan(s), axis=0)
        total = np.nansum(s, axis=0)
        return np.where(counts > 0, total / np.maximum(counts, 1), np.nan)


def _load_eval(phase_dir: Path) -> dict[str, Any]:
    return json.loads((phase_dir / "eval.json").read_text())


def _load_trajectories(phase_dir: Path) -> dict[str, list[np.ndarray]]:
    out: dict[str, list[np.ndarray]] = {}
    with np.load(phase_dir / "trajectories.npz") as data:
        for key in sorted(data.files, key=lambda k: (k.split("__")[0], int(k.split("__")[1]))):
            out.setdefault(key.split("__")[0], []).append(data[key])
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


def _curves(s: np.ndarray, skills: Sequence[str], pairs: Sequence[tuple[str, str]],
            s_wake: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Curves per evaluation seed; with the after-wake matrices ``s_wake`` also ``bwt_wake`` (reference: the
    seed's success on skill i right after its own wake, diag of s_wake)."""
    curves = {
        "afsr": np.stack([afsr_curve(m) for m in s]),
        "prs": np.stack([prs_curve(m, skills, pairs) if pairs else np.full(len(skills), np.nan) for m in s]),
        "bwt": np.stack([bwt_curve(m) for m in s]),
    }
    if s_wake is not None:
        curves["bwt_wake"] = np.stack([bwt_curve(m, np.diag(w)) for m, w in zip(s, s_wake, strict=True)])
    return curves


def _summary(curves: np.ndarray) -> dict[str, Any]:
    """Per-stage mean and SE across seeds, and the final value."""
    stats = [mean_sem([float(x) for x in curves[:, k]]) for k in range(curves.shape[1])]
    return {"mean_curve": [m for m, _ in stats], "sem_curve": [e for _, e in stats],
            "final_mean": stats[-1][0], "final_sem": stats[-1][1], "final_per_seed": curves[:, -1].tolist()}


def _fmt(mean: float, sem: float) -> str:
    if math.isnan(mean):
        return "n/a"
    return f"{mean:.3f}" if math.isnan(sem) else f"{mean:.3f} +- {sem:.3f}"


def _plots(out: Path, skills: Sequence[str], summaries: dict[str, dict[str, Any]], s_mean: np.ndarray) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import io

    import matplotlib.pyplot as plt

    ks = np.arange(1, len(skills) + 1)
    fig, axes = plt.subplots(1, 4, figsize=(14, 3.2))
    for ax, names in zip(axes, (("afsr",), ("prs",), ("bwt", "bwt_wake"), ("spi",)), strict=True):
        for name in names:
            mean = np.array(summaries[name]["mean_curve"], dtype=float)
            sem = np.nan_to_num(np.array(summaries[name]["sem_curve"], dtype=float))
            ax.plot(ks, mean, marker="o", label=LABELS[name])
            ax.fill_between(ks, mean - sem, mean + sem, alpha=0.25)
        ax.set_title(" / ".join(name.upper() for name in names))
        if len(names) > 1:
            ax.legend(fontsize=7)
        ax.set_ylim(*((-1.05, 1.05) if names[0] == "bwt" else (-0.02, 1.05)))
        ax.set_xlabel("skills learned k")
        ax.set_xticks(ks)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    atomic_write_bytes(out / "metrics.png", buf.getvalue())

    fig, ax = plt.subplots(figsize=(1.2 * len(skills) + 2, 1.0 * len(skills) + 1.5))
    im = ax.imshow(np.ma.masked_invalid(s_mean), vmin=0, vmax=1, cmap="viridis")
    for k in range(len(skills)):
        for i in range(k + 1):
            ax.text(i, k, f"{s_mean[k, i]:.2f}", ha="center", va="center", color="w" if s_mean[k, i] < 0.6 else "k")
    ax.set_xticks(range(len(skills)), skills, rotation=30)
    ax.set_yticks(range(len(skills)), [f"after {s}" for s in skills])
    ax.set_xlabel("evaluated skill i")
    ax.set_title("success S[k][i]")
    fig.colorbar(im, ax=ax, fraction=0.046)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    atomic_write_bytes(out / "success_matrix.png", buf.getvalue())


def write_report(
    out: Path,
    skills: Sequence[str],
    pairs_name: str,
    progress: dict[str, Any],
    config: dict[str, Any],
    final_dirs: Sequence[Path],
    wake_dirs: Sequence[Path],
    memories: Sequence[Memory],
) -> dict[str, Any]:
    """Build results.json, results.md, metrics.png and success_matrix.png in ``out``."""
    n_seeds = len(config["eval"]["seeds"])
    pairs = pair_list(pairs_name, skills)
    s_final = _matrices(final_dirs, skills, n_seeds)
    s_wake = _matrices(wake_dirs, skills, n_seeds)
    curves = _curves(s_final, skills, pairs, s_wake)
    curves["spi"], features = _spi_curves(final_dirs, skills, n_seeds)
    summaries = {name: _summary(c) for name, c in curves.items()}
    wake_curves = _curves(s_wake, skills, pairs)
    sleep_records = {key: value for key, value in progress["completed"].items() if key.endswith(".sleep")}
    results = {
        "results_version": RESULTS_VERSION,
        "skills": list(skills),
        "pairs": [list(p) for p in pairs],
        "method": config["method"],
        "policy_sleep": config["policy"].get("sleep"),
        "seed": config["seed"],
        "eval_seeds": config["eval"]["seeds"],
        "episodes_per_skill_per_seed": config["eval"]["n_episodes"],
        "success_matrix": _seed_mean(s_final).tolist(),
        "success_matrix_per_seed": s_final.tolist(),
        "success_matrix_after_wake": _seed_mean(s_wake).tolist(),
        "success_after_own_wake": np.diag(_seed_mean(s_wake)).tolist(),  # the bwt_wake reference, per skill
        "success_after_own_wake_per_seed": [np.diag(m).tolist() for m in s_wake],
        "metrics": summaries,
        "spi_features": list(features),
        "metrics_after_wake": {name: _summary(c) for name, c in wake_curves.items()},  # same run, before each sleep
        "sleep": sleep_records,
        "memory_bytes": {m.skill: m.nbytes() for m in memories},
        "memory_bytes_total": sum(m.nbytes() for m in memories),
        "phases": progress["completed"],
    }
    results = json.loads(json.dumps(results, default=float).replace("NaN", "null"))
    atomic_write_json(out / "results.json", results)

    lines = [f"# Stream results ({config['method']}, sleep={config['policy'].get('sleep')}, seed {config['seed']})",
             "", f"Evaluation: {len(config['eval']['seeds'])} seeds x {config['eval']['n_episodes']} episodes "
             "per skill; mean +- SE over evaluation seeds.", "",
             "| metric | final (k = K) |", "|---|---|"]
    lines += [f"| {LABELS[name]} | {_fmt(summaries[name]['final_mean'], summaries[name]['final_sem'])} |"
              for name in METRICS]
    lines += ["", "Success matrix S[k][i] (rows: after skill k; mean over seeds):", "",
              "| after \\ skill | " + " | ".join(skills) + " |", "|---" * (len(skills) + 1) + "|"]
    s_mean = _seed_mean(s_final)
    for k, skill in enumerate(skills):
        cells = [f"{s_mean[k, i]:.2f}" if i <= k else "" for i in range(len(skills))]
        lines.append(f"| {skill} | " + " | ".join(cells) + " |")
    wake_mean = _seed_mean(s_wake)
    lines.append("| right after own wake | " + " | ".join(f"{wake_mean[i, i]:.2f}" for i in range(len(skills)))
                 + " |")
    atomic_write_bytes(out / "results.md", ("\n".join(lines) + "\n").encode())
    _plots(out, skills, summaries, s_mean)
    return results
