"""One multi-run summary for both substrates: mean +- SE over training seeds and paired differences.

    python -m sr_imitation.reporting.summary RUN_DIR [NAME=RUN_DIR ...] [--output=DIR] [--baseline=wake_only]

Runs are grouped by variant (``NAME``, else ``results["label"]``: the method, ``wake_only`` for ``sr`` without
sleep) and, within a variant, by training seed. For every variant: the final AFSR, PRS, BWT (reference after
stage i), BWT_wake (reference right after skill i's own wake) and SPI, the final success per skill and the success
right after each skill's own wake, each as mean +- SE over training seeds (each seed's value is its mean over
evaluation units), and every metric's paired difference to the baseline variant over the training seeds both have.
Runs without closed-loop evaluation (``--eval.env=none``) have none of these; for them the final validation l1 and
memory loss (:data:`~sr_imitation.reporting.results.LOSS_METRICS`, lower is better) take their place, paired the same
way. Written as ``summary.json``, ``summary.md`` and ``summary.png`` (bars with the seeds as dots). Used by
``sr_imitation.experiments.needle_compare`` and ``sr_imitation.experiments.mt5_compare``; reads results of every
schema version (:func:`sr_imitation.reporting.results.upgrade_results`).
"""

from __future__ import annotations

import argparse
import io
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sr_imitation.core.metrics import mean_sem
from sr_imitation.io import atomic_write_bytes, write_checked_json
from sr_imitation.reporting.results import (
    LOSS_METRICS,
    METRICS,
    binomial_se_bound,
    episodes_per_cell,
    final_loss,
    load_results,
)
from sr_imitation.stream.rundir import check_run_config, read_progress

SHORT = {"afsr": "AFSR", "prs": "PRS", "bwt": "BWT", "bwt_wake": "BWT_wake", "spi": "SPI"}
DEFAULT_BASELINE = "wake_only"


def mean_sem_dict(values: Sequence[float | None]) -> dict[str, Any]:
    """``{"mean", "sem", "per_seed"}`` over the finite values (NaN when none)."""
    present = [float(x) for x in values if x is not None and math.isfinite(x)]
    mean, sem = mean_sem(present) if present else (float("nan"), float("nan"))
    return {"mean": mean, "sem": sem, "per_seed": list(values)}


def _curve_stats(curves: Sequence[Sequence[float | None] | None]) -> dict[str, list[float]]:
    """Per stage: mean and SE over training seeds of each seed's curve (its mean over evaluation units)."""
    rows = np.array([[np.nan if x is None else x for x in c] for c in curves if c is not None], dtype=float)
    if rows.size == 0:
        return {"mean": [], "sem": []}
    stats = [mean_sem_dict(rows[:, k].tolist()) for k in range(rows.shape[1])]
    return {"mean": [s["mean"] for s in stats], "sem": [s["sem"] for s in stats]}


def group_runs(runs: Sequence[str | Path]) -> dict[str, dict[str, dict[str, Any]]]:
    """``{variant: {seed: results}}`` (seeds as strings). A run is a directory (its variant: ``results["label"]``)
    or ``NAME=DIR`` (variant NAME, e.g. an ablation: ``no_anchor=outputs/run3``); two runs of one variant and seed
    are refused."""
    groups: dict[str, dict[str, dict[str, Any]]] = {}
    for spec in runs:
        name, _, path = str(spec).rpartition("=") if "=" in str(spec) else ("", "", str(spec))
        run = Path(path)
        results = _load_run(run)
        seeds = groups.setdefault(name or results["label"], {})
        seed = str(results["seed"])
        if seed in seeds:
            raise ValueError(f"{run}: a second {results['label']} run with seed {seed} (also {seeds[seed]['run']})")
        seeds[seed] = results
    return groups


def _load_run(run: str | Path) -> dict[str, Any]:
    """A run's results with its directory (``run``) and compute time (``phase_seconds``). Its stored config is
    checked as a resume checks it first (:func:`~sr_imitation.stream.rundir.check_run_config`): a run whose
    ``train_config.json`` was edited is refused, naming the file."""
    check_run_config(Path(run))
    return {**load_results(Path(run)), "run": str(run), "phase_seconds": phase_seconds(run)}


def phase_seconds(run: str | Path) -> float | None:
    """A run's compute time: the sum of its completed phases' ``seconds`` in ``progress.json`` (wake, sleep,
    evaluation, memory; not process start-up or data loading); ``None`` without a progress file. A resumed run
    counts each phase once, as it finally completed. A wake (ACT or SAC, stream or MT-Joint) resumed from its
    snapshot adds the time before the snapshot to its phase's ``seconds`` itself. Runs written before 2026-11-28 did
    not: there a phase's ``seconds`` starts when its process started it, so a SAC wake (or SAC MT-Joint's training)
    counts its own record instead where that is larger (``wake.seconds``, which always carried the time before the
    snapshot), and an ACT wake of such a run counts from the resume."""
    path = Path(run) / "progress.json"
    if not path.is_file():
        return None
    completed = read_progress(path).get("completed") or {}
    return float(sum(_phase_time(rec) for rec in completed.values()
                     if isinstance(rec, Mapping) and isinstance(rec.get("seconds"), (int, float))))


def _phase_time(record: Mapping[str, Any]) -> float:
    wake = record.get("wake")
    own = wake.get("seconds") if isinstance(wake, Mapping) else None
    return max(record["seconds"], own) if isinstance(own, (int, float)) else record["seconds"]


def summarize(groups: Mapping[str, Mapping[str, Mapping[str, Any]]], baseline: str = DEFAULT_BASELINE
              ) -> dict[str, Any]:
    """The summary dictionary of ``{variant: {seed: results}}`` (see the module docstring)."""
    variants: dict[str, Any] = {}
    skills: list[str] = []  # every variant's skills, in order of first appearance (streams may differ: MT8, reverse)
    finals: dict[str, dict[str, dict[str, float | None]]] = {}
    for variant, per_seed in groups.items():
        runs = list(per_seed.values())
        own = runs[0]["skills"]
        if any(r["skills"] != own for r in runs):
            raise ValueError(f"{variant}: runs with different skill lists cannot be summarized together")
        skills += [s for s in own if s not in skills]
        finals[variant] = {m: {seed: r["metrics"][m]["final"] for seed, r in per_seed.items()} for m in METRICS}
        last = np.array([[np.nan if x is None else x for x in r["success_matrix"][-1]] for r in runs], dtype=float)
        wake = np.array([[np.nan if x is None else x for x in r["success_after_own_wake"]] for r in runs], dtype=float)
        variants[variant] = {
            "seeds": list(per_seed),
            "runs": {seed: r.get("run") for seed, r in per_seed.items()},
            "phase_seconds": {seed: r.get("phase_seconds") for seed, r in per_seed.items()},
            "code": {seed: r.get("code") for seed, r in per_seed.items()},
            "unsealed": {seed: bool(r.get("unsealed")) for seed, r in per_seed.items()},
            "substrate": runs[0]["substrate"],
            **{m: mean_sem_dict(list(finals[variant][m].values())) for m in METRICS},
            "skills": list(own),
            "final_success": {s: mean_sem_dict(last[:, i].tolist()) for i, s in enumerate(own)},
            "success_after_own_wake": {s: mean_sem_dict(wake[:, i].tolist()) for i, s in enumerate(own)},
            "memory_bytes_total": mean_sem_dict([r["memory_bytes_total"] for r in runs]),
            "episodes_per_cell": sorted({n for n in map(episodes_per_cell, runs) if n is not None}),
            # None: the run predates per-kind memory accounting (results.json without "memory_kinds")
            "memory_kinds": None if runs[0].get("memory_kinds") is None else dict(runs[0]["memory_kinds"]),
            # what each kind holds, in words (results.json since session 27; older runs: LEGACY_MEMORY_CONTENTS)
            **({"memory_contents": dict(runs[0]["memory_contents"])} if runs[0].get("memory_contents") else {}),
            "oracle": bool((runs[0].get("extra") or {}).get("oracle")),
            "curves": {m: _curve_stats([r["metrics"][m].get("curve") for r in runs]) for m in METRICS},
        }
        offline = {m: {seed: final_loss(r, m) for seed, r in per_seed.items()} for m in LOSS_METRICS}
        if any(v is not None for per in offline.values() for v in per.values()):  # runs without evaluation
            finals[variant].update(offline)
            variants[variant]["offline"] = {m: mean_sem_dict(list(offline[m].values())) for m in LOSS_METRICS}
    paired: dict[str, Any] = {}
    if baseline in finals:
        for variant, per_metric in finals.items():
            seeds = [s for s in variants[variant]["seeds"] if s in variants[baseline]["seeds"]]
            # a stream of other skills (MT8 against MT5) has no paired difference; another order of the same does
            same_skills = set(variants[variant]["skills"]) == set(variants[baseline]["skills"])
            if variant == baseline or not seeds or not same_skills:
                continue
            paired[variant] = {"seeds": seeds}
            offline = [m for m in LOSS_METRICS if m in per_metric and m in finals[baseline]]
            for m in [*METRICS, *offline]:
                base = finals[baseline][m]
                paired[variant][m] = mean_sem_dict([
                    None if per_metric[m][s] is None or base[s] is None else per_metric[m][s] - base[s]
                    for s in seeds])
    return {"skills": skills, "baseline": baseline, "variants": variants, "paired": paired}


def _fmt(d: Mapping[str, Any]) -> str:
    mean, sem = d["mean"], d["sem"]
    if mean is None or not math.isfinite(mean):
        return "-"
    return f"{mean:.3f}" if sem is None or not math.isfinite(sem) else f"{mean:.3f} +- {sem:.3f}"


def _seeds(row: Mapping[str, Any], seeds: Sequence[str] | None = None) -> str:
    """A row's seeds, each whose ``results.json`` is unsealed (a schema before seals) marked ``*``: a mean never
    mixes sealed and unsealed runs without the mark in its row."""
    unsealed = row.get("unsealed") or {}
    return ",".join(f"{seed}*" if unsealed.get(seed) else str(seed) for seed in (row["seeds"] if seeds is None
                                                                                  else seeds))


def _final_tables(summary: Mapping[str, Any], names: Sequence[str]) -> list[str]:
    """The final-metrics table of ``names`` and their paired differences to the baseline (markdown lines)."""
    variants, paired = summary["variants"], summary["paired"]
    header = "| variant | seeds | " + " | ".join(SHORT[m] for m in METRICS) + " | memory (MB) |"
    rule = "|---" * (len(METRICS) + 3) + "|"
    lines = [header, rule]
    for v in names:
        row = variants[v]
        mb = row["memory_bytes_total"]["mean"] / 1e6
        lines.append(f"| {v} | {_seeds(row)} | " + " | ".join(_fmt(row[m]) for m in METRICS)
                     + f" | {mb:.2f} |")
    if any(v in paired for v in names):
        lines += ["", f"Paired difference variant - {summary['baseline']} (same training seed), mean +- SE:", "",
                  header.removesuffix(" memory (MB) |"), rule.removesuffix("|---|") + "|"]
        for v in names:
            if v in paired:
                row = paired[v]
                lines.append(f"| {v} | {_seeds(variants[v], row['seeds'])} | "
                             + " | ".join(_fmt(row[m]) for m in METRICS) + " |")
    return lines


def _offline_table(summary: Mapping[str, Any]) -> list[str]:
    """Runs without closed-loop evaluation (``--eval.env=none``): their final validation l1 and memory loss
    (:data:`~sr_imitation.reporting.results.LOSS_METRICS`) per variant and paired to the baseline; nothing otherwise."""
    variants, paired, base = summary["variants"], summary["paired"], summary.get("baseline")
    names = [v for v, row in variants.items() if row.get("offline")]
    if not names:
        return []
    lines = ["", "Runs without closed-loop evaluation (--eval.env=none): under the final policy, the mean over skills "
                 "of each skill's validation l1 (behaviour-cloning l1 on its held-out episodes) and of its memory's "
                 f"distillation loss; lower is better. Mean +- SE over training seeds; paired: variant - {base}.", "",
             "| variant | seeds | val_l1 | memory_loss | paired val_l1 | paired memory_loss |", "|---" * 6 + "|"]
    for v in names:
        row, diff = variants[v]["offline"], paired.get(v) or {}
        cells = [_fmt(row[m]) for m in LOSS_METRICS] + [_fmt(diff[m]) if m in diff else "-" for m in LOSS_METRICS]
        lines.append(f"| {v} | {','.join(variants[v]['seeds'])} | " + " | ".join(cells) + " |")
    return lines


def render_markdown(summary: Mapping[str, Any], sections: Mapping[str, Sequence[str]] | None = None) -> str:
    """``summary.md``. ``sections`` (title -> variants, e.g. baselines / ablations / streams) splits the final-metrics
    table into one table per section, each with the baseline's row; variants in no section come last."""
    skills, variants = summary["skills"], summary["variants"]
    lines = ["Final metrics after the full stream, mean +- SE over training seeds. BWT: reference = success on skill "
             "i after stage i (after its sleep); BWT_wake: reference = success on skill i right after its own wake.",
             ""]
    base = summary.get("baseline")
    groups = [(title, [v for v in variants if v in names and v != base]) for title, names in (sections or {}).items()]
    rest = [v for v in variants if v != base and not any(v in g for _, g in groups)]
    groups = [(title, g) for title, g in [*groups, ("Other variants", rest)] if g] if sections else []
    if not groups:
        lines += _final_tables(summary, list(variants))
    for j, (title, names) in enumerate(groups):
        lines += [*([""] if j else []), f"**{title}**", "",
                  *_final_tables(summary, [v for v in variants if v == base] + names)]
    lines += ["", "Per run (each value: the run's mean over its evaluation units):", "",
              "| variant | seed | run | " + " | ".join(SHORT[m] for m in METRICS) + " | time (min) | commit |",
              "|---" * (len(METRICS) + 5) + "|"]
    total = 0.0
    for v, row in variants.items():
        for j, seed in enumerate(row["seeds"]):
            cells = [row[m]["per_seed"][j] for m in METRICS]
            seconds = (row.get("phase_seconds") or {}).get(seed)
            total += seconds or 0.0
            code = (row.get("code") or {}).get(seed) or {}
            commit = code.get("commit") and code["commit"][:7] + (" (dirty)" if code.get("dirty") else "")
            lines.append(f"| {v} | {_seeds(row, [seed])} | {row['runs'][seed]} | "
                         + " | ".join("-" if c is None else f"{c:.3f}" for c in cells)
                         + f" | {'-' if seconds is None else f'{seconds / 60:.1f}'} | {commit or '-'} |")
    lines += ["", f"Time: the sum of each run's completed phases (progress.json; wake, sleep, evaluation). All runs "
                  f"above: {total / 3600:.2f} h. Commit: the code that wrote the run's results (results.json "
                  "`code`; dirty: with uncommitted changes; -: written before it was recorded)."]
    unsealed = [f"{v} seed {seed}" for v, row in variants.items() for seed in row["seeds"]
                if (row.get("unsealed") or {}).get(seed)]
    if unsealed:
        lines += ["", f"Unsealed: {', '.join(unsealed)} (marked * in the seeds: results.json of a schema before "
                      "seals, read because its recorded AFSR is its success matrix's, without a checksum to verify "
                      "it)."]
    lines += _offline_table(summary)
    mixed = any(row["skills"] != skills for row in variants.values())
    for key, title in (("final_success", "Final success per skill (after the last stage)"),
                       ("success_after_own_wake", "Success right after each skill's own wake phase")):
        lines += ["", f"{title}, mean +- SE over training seeds"
                  + (" (-: not in the variant's stream; the streams differ in skills or order)" if mixed else "")
                  + ":", "",
                  "| variant | " + " | ".join(skills) + " |", "|---" * (len(skills) + 1) + "|"]
        for v, row in variants.items():
            lines.append(f"| {v} | " + " | ".join(_fmt(row[key][s]) if s in row[key] else "-" for s in skills)
                         + " |")
    lines += _binomial_lines(variants)
    return "\n".join(lines) + "\n"


def _binomial_lines(variants: Mapping[str, Any]) -> list[str]:
    """The evaluation noise inside one seed's per-skill success rate (binomial, at the episodes it pools), and what
    the SE over training seeds holds; nothing when no run recorded its episode count."""
    counts: dict[tuple[int, ...], list[str]] = {}
    for v, row in variants.items():
        if row.get("episodes_per_cell"):
            counts.setdefault(tuple(row["episodes_per_cell"]), []).append(v)
    if not counts:
        return []
    parts = [f"{' or '.join(map(str, n))} episodes (binomial SE up to "
             f"{' / '.join(f'{binomial_se_bound(x):.3f}' for x in n)} at 0.5 success)"
             + ("" if len(counts) == 1 else f": {', '.join(names)}") for n, names in counts.items()]
    return ["", "Evaluation noise: one seed's success on one skill is a rate over " + "; ".join(parts) + ". The SE "
            "over training seeds in these tables includes that noise and the variation between training seeds; the "
            "per-run SE over evaluation units (results.md) understates it."]


def _colors(names: Sequence[str], baseline: str | None) -> dict[str, Any]:
    """One colour per variant of one figure: the paired baseline black, the others ``tab10`` in order (``tab20``
    beyond ten, so no two bars of a group share a colour)."""
    import matplotlib.pyplot as plt

    others = [n for n in names if n != baseline]
    cmap = plt.get_cmap("tab10" if len(others) <= 10 else "tab20").colors
    return {n: "k" if n == baseline else cmap[others.index(n) % len(cmap)] for n in names}


def plot(summary: Mapping[str, Any], path: Path) -> None:
    """Bars: mean over training seeds with +- SE; dots: the individual seeds; last panel: final success per skill
    (one bar per variant, coloured as in the legend under the panels)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    skills, variants = summary["skills"], summary["variants"]
    names = list(variants)
    colors = _colors(names, summary.get("baseline"))
    fig, axes = plt.subplots(1, len(METRICS) + 1, figsize=(4 * (len(METRICS) + 1), 4.2))
    x = np.arange(len(names))
    for ax, m in zip(axes, METRICS, strict=False):
        cells = [variants[v][m] for v in names]
        ax.bar(x, [c["mean"] for c in cells], yerr=[np.nan_to_num(c["sem"]) for c in cells], capsize=3,
               color="#8fb3d9")
        for i, c in enumerate(cells):
            ys = [y for y in c["per_seed"] if y is not None]
            ax.scatter([i] * len(ys), ys, color="k", s=10, zorder=3)
        ax.set_xticks(x, names, rotation=50, ha="right", fontsize=7)
        ax.set_title(SHORT[m])
        ax.axhline(0.0, color="grey", lw=0.5)
    ax = axes[-1]
    width = 0.8 / max(len(names), 1)
    for j, v in enumerate(names):
        cells = [variants[v]["final_success"].get(s, {"mean": np.nan, "sem": np.nan}) for s in skills]
        ax.bar(np.arange(len(skills)) + j * width, [c["mean"] for c in cells], width,
               yerr=[np.nan_to_num(c["sem"]) for c in cells], capsize=1, label=v, color=colors[v])
    ax.set_xticks(np.arange(len(skills)) + 0.4 - width / 2, skills, rotation=50, ha="right", fontsize=7)
    ax.set_ylim(0, 1.05)
    ax.set_title("final success per skill")
    columns = min(len(names), 10) or 1
    rows = -(-len(names) // columns)
    fig.legend(*ax.get_legend_handles_labels(), loc="lower center", ncol=columns, fontsize=7, frameon=False)
    fig.tight_layout(rect=(0, 0.06 * rows, 1, 1))
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


def plot_dynamics(summary: Mapping[str, Any], path: Path) -> None:
    """The paper's Figure 2: AFSR, PRS, BWT, BWT_wake and SPI after each stage k, one line per variant (mean over
    training seeds, band +- SE); an oracle (no sequence) is a dashed line at its final value. The paired baseline
    (SR) is drawn black, thickest and on top; beyond ten other variants colours repeat with another line style and
    marker; the legend sits under the panels (one entry per variant)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    variants = summary["variants"]
    baseline = summary.get("baseline")
    colors = plt.get_cmap("tab10").colors
    styles = [("-", "o"), (":", "s"), ("-.", "^")]
    fig, axes = plt.subplots(1, len(METRICS), figsize=(3.6 * len(METRICS), 3.4))
    stages = 1
    for ax, m in zip(axes, METRICS, strict=True):
        others = [name for name in variants if name != baseline]
        for name, row in variants.items():
            curve = row.get("curves", {}).get(m) or {"mean": [], "sem": []}
            mean = np.array(curve["mean"], dtype=float)
            if mean.size == 0 or np.isnan(mean).all():
                continue
            j = others.index(name) if name in others else 0
            color = "k" if name == baseline else colors[j % len(colors)]
            line, marker = ("-", "o") if name == baseline else styles[(j // len(colors)) % len(styles)]
            k = np.arange(1, len(mean) + 1)
            stages = max(stages, len(mean))
            if row.get("oracle"):
                ax.axhline(mean[-1], color=color, ls="--", lw=1.2, label=f"{name} (oracle)")
                continue
            main = name == baseline
            sem = np.nan_to_num(np.array(curve["sem"], dtype=float))
            ax.plot(k, mean, ls=line, marker=marker, ms=3, color=color, label=name, lw=2.6 if main else 1.3,
                    zorder=4 if main else 2)
            ax.fill_between(k, mean - sem, mean + sem, color=color, alpha=0.15, lw=0)
        ax.set_title(SHORT[m])
        ax.set_xlabel("after stage k")
        ax.axhline(0.0, color="grey", lw=0.5)
    for ax in axes:
        ax.set_xticks(np.arange(1, stages + 1))
    entries = {}
    for ax in axes:  # every variant once, in the summary's order, whichever panel drew it
        for handle, label in zip(*ax.get_legend_handles_labels(), strict=True):
            entries.setdefault(label, handle)
    columns = min(len(entries), 8) or 1
    rows = -(-len(entries) // columns)
    fig.legend(list(entries.values()), list(entries), loc="lower center", ncol=columns, fontsize=7, frameon=False)
    fig.tight_layout(rect=(0, 0.07 * rows, 1, 1))
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


LEGACY_MEMORY_CONTENTS = {
    "act_actor": "observations (state; wrist images as uint8) + the actor's action chunks on them",
    "act_demonstrations": "demonstration frames (normalized observations + target action chunks and padding masks)",
    "componet_module": "a frozen module per skill (Gaussian head + attention weights)",
    "ewc_fisher": "parameter snapshot theta* + diagonal Fisher",
    "output_distillation": "inputs (states or observations) + the policy's outputs on them",
    "policy_snapshot": "the policy before this skill's wake (one rolling copy of its weights)",
    "sac_critic": "states + the frozen twin critic + the observation normalizer's snapshot",
    "transitions": "transitions (s, a, r, s', done) + the actor's Gaussian on s (behaviour-cloning targets)",
}
"""What each memory kind held, in words, for runs whose results.json predates ``memory_contents`` (frozen: the
memory classes' ``contents`` when those runs were written; a newer run's results carry their own words)."""


def memory_table(summary: Mapping[str, Any], paper_mb: Mapping[str, float] | None = None) -> str:
    """Markdown: per variant the bytes its continual-learning mechanism stores at the end of the stream (first
    seed's run) and what, by memory kind, next to the paper's number where it gives one. A run recorded before
    per-kind accounting says so instead of "nothing"."""
    lines = ["| variant | ours (MB) | what it stores (MB) | paper (MB) |", "|---|---|---|---|"]
    for variant, row in summary["variants"].items():
        kinds = row.get("memory_kinds")
        words = {**LEGACY_MEMORY_CONTENTS, **(row.get("memory_contents") or {})}
        stored = ("not recorded (the run predates per-kind memory accounting)" if kinds is None else
                  "; ".join(f"{words.get(k, k)} ({v / 1e6:.2f})" for k, v in sorted(kinds.items())) or "nothing")
        paper = (paper_mb or {}).get(variant)
        lines.append(f"| {variant} | {row['memory_bytes_total']['mean'] / 1e6:.2f} | {stored} | "
                     f"{'-' if paper is None else f'{paper:.1f}'} |")
    return "\n".join(lines) + "\n"


def section_figures(summary: Mapping[str, Any], sections: Mapping[str, Sequence[str]] | None
                    ) -> dict[str, dict[str, Any]]:
    """Per section with runs (``tag``: its title's first word, lower case, e.g. ``ablations``): ``summary`` cut to
    the baseline and that section's variants, for figures of one table's rows (every variant in one figure is hard
    to read). Sections whose variants are all oracles (no per-stage curve) get none, as does a section that would
    repeat the whole summary."""
    variants, base = summary["variants"], summary.get("baseline")
    out = {}
    for title, names in (sections or {}).items():
        rows = {v: row for v, row in variants.items() if v == base or v in names}
        if any(v != base and not row.get("oracle") for v, row in rows.items()) and len(rows) < len(variants):
            skills = [s for s in summary["skills"] if any(s in row["skills"] for row in rows.values())]
            out[title.split()[0].lower()] = {**summary, "variants": rows, "skills": skills}
    return out


def write_summary(output: Path, summary: Mapping[str, Any], paper_mb: Mapping[str, float] | None = None,
                  sections: Mapping[str, Sequence[str]] | None = None) -> None:
    """``summary.json``, ``summary.md`` (final-metrics tables split by ``sections``, :func:`render_markdown`),
    ``summary.png`` (final metrics), ``dynamics.png`` (per stage), both with every variant and again per section
    (``summary_<tag>.png``, ``dynamics_<tag>.png``, :func:`section_figures`), and ``memory.md`` (the memory-budget
    table) in ``output`` (atomic)."""
    output.mkdir(parents=True, exist_ok=True)
    write_checked_json(output / "summary.json", summary)
    atomic_write_bytes(output / "summary.md", render_markdown(summary, sections).encode())
    atomic_write_bytes(output / "memory.md", memory_table(summary, paper_mb).encode())
    plot(summary, output / "summary.png")
    plot_dynamics(summary, output / "dynamics.png")
    for tag, part in section_figures(summary, sections).items():
        plot(part, output / f"summary_{tag}.png")
        plot_dynamics(part, output / f"dynamics_{tag}.png")


def load_groups(runs: Mapping[str, Mapping[str, Path]]) -> dict[str, dict[str, dict[str, Any]]]:
    """``{variant: {seed: results}}`` of an experiment driver's ``{variant: {seed: run directory}}``."""
    return {variant: {seed: _load_run(run) for seed, run in per_seed.items()} for variant, per_seed in runs.items()}


def print_final_means(summary: Mapping[str, Any], written: Sequence[Path]) -> None:
    """An experiment driver's console output: every variant's final means, then the files written."""
    import json

    print(json.dumps({v: {m: row[m]["mean"] for m in METRICS} for v, row in summary["variants"].items()},  # noqa: T201
                     indent=2))
    print("written " + " and ".join(str(p) for p in written))  # noqa: T201


def main(args: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help="run directories, or NAME=DIR to name a run's variant")
    parser.add_argument("--output", type=Path, default=None, help="also write summary.json/.md/.png here")
    parser.add_argument("--baseline", default=DEFAULT_BASELINE, help="variant of the paired differences")
    ns = parser.parse_args(args)
    summary = summarize(group_runs(ns.runs), ns.baseline)
    if ns.output is not None:
        write_summary(ns.output, summary)
    print(render_markdown(summary))  # noqa: T201 (command output)


if __name__ == "__main__":
    from sr_imitation.infra.cli_errors import run_cli

    run_cli("sr_imitation.reporting.summary", main)
