"""Two runs of one stream side by side: comparison.png (both success matrices and AFSR curves) and results.md."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sr_imitation.io import atomic_write_bytes
from sr_imitation.reporting.results import load_results, save_figure

FIGURE = "comparison.png"
"""The figure's file name in the output folder."""
REPORT = "results.md"
"""The comparison's markdown file name in the output folder."""


def side_by_side(runs: Mapping[str, Path]) -> dict[str, Any]:
    """What the figure and the markdown show of two finished runs of the same stream.

    Args:
        runs: name -> run directory (its ``results.json``), two of them; the first is the one the difference is of.

    Returns:
        ``names``, ``skills``, ``difference`` (the first's final AFSR minus the second's) and, per name, its run
        directory, ``afsr_final``, ``afsr_curve``, ``success_matrix``, ``final_success`` and ``eval_units``.

    Raises:
        ValueError: not two runs, or runs of different skill streams.
    """
    if len(runs) != 2:
        raise ValueError(f"side by side: two runs, got {len(runs)} ({', '.join(runs)})")
    loaded = {name: load_results(Path(run)) for name, run in runs.items()}
    skills = [list(r["skills"]) for r in loaded.values()]
    if skills[0] != skills[1]:
        raise ValueError(f"side by side: the runs learned different streams ({skills[0]} and {skills[1]})")
    out: dict[str, Any] = {"names": list(runs), "skills": skills[0], "runs": {}}
    for name, results in loaded.items():
        afsr = results["metrics"]["afsr"]
        out["runs"][name] = {"dir": str(runs[name]), "afsr_final": afsr["final"], "afsr_curve": list(afsr["curve"]),
                             "success_matrix": results["success_matrix"],
                             "final_success": results["success_matrix"][-1], "eval_units": results["eval_units"]}
    first, second = (out["runs"][name]["afsr_final"] for name in out["names"])
    out["difference"] = first - second
    return out


def difference_sentence(summary: Mapping[str, Any]) -> str:
    """The final AFSR of each run and their difference in words, whatever its sign.

    Args:
        summary: :func:`side_by_side`'s result.

    Returns:
        One sentence, e.g. ``sr ends at AFSR 0.880, wake_only at 0.840: sr is 0.040 ahead.``
    """
    a, b = summary["names"]
    x, y = (summary["runs"][name]["afsr_final"] for name in (a, b))
    diff = round(summary["difference"], 3)
    verdict = (f"{a} is {diff:.3f} ahead" if diff > 0 else f"{a} is {-diff:.3f} behind" if diff < 0
               else "they are level")
    return f"{a} ends at AFSR {x:.3f}, {b} at {y:.3f}: {verdict} (difference {a} - {b} = {diff:+.3f})."


def render_markdown(summary: Mapping[str, Any], title: str, context: str, notes: Sequence[str] = ()) -> str:
    """The comparison's ``results.md``.

    Args:
        summary: :func:`side_by_side`'s result.
        title: the heading.
        context: one paragraph saying what was run (preset, stream, training seed).
        notes: paragraphs after the tables (what one seed can and cannot show, where the evidence is).

    Returns:
        The markdown text.
    """
    names, skills = summary["names"], summary["skills"]
    lines = [f"# {title}", "", context, "", f"**{difference_sentence(summary)}**", "",
             "| run | final AFSR | AFSR after each stage | folder |", "|---|---|---|---|"]
    for name in names:
        run = summary["runs"][name]
        curve = ", ".join(f"{x:.3f}" for x in run["afsr_curve"])
        lines.append(f"| {name} | {run['afsr_final']:.3f} | {curve} | {Path(run['dir']).name}/ |")
    lines += ["", "Final success per skill (after the last stage):", "",
              "| run | " + " | ".join(skills) + " |", "|---" * (len(skills) + 1) + "|"]
    for name in names:
        lines.append(f"| {name} | " + " | ".join(f"{x:.2f}" for x in summary["runs"][name]["final_success"]) + " |")
    lines += ["", *[p for note in notes for p in (note, "")],
              f"Figure: `{FIGURE}`. Each run's own tables, plots and videos are in its folder (its `results.md`).", ""]
    return "\n".join(lines)


def write_figure(summary: Mapping[str, Any], path: Path, title: str, caption: str = "") -> None:
    """Both success matrices (rows: after stage k; columns: skill i) and both AFSR curves, as one PNG (atomic).

    Args:
        summary: :func:`side_by_side`'s result.
        path: the PNG to write.
        title: the figure's first title line (the difference sentence follows it).
        caption: a line under the panels (what the figure can and cannot show); empty: none.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names, skills = summary["names"], summary["skills"]
    n = len(skills)
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.8), gridspec_kw={"width_ratios": [1, 1, 1.1]})
    for ax, name in zip(axes[:2], names, strict=True):
        run = summary["runs"][name]
        s = np.array([[np.nan if x is None or i > k else x for i, x in enumerate(row)]
                      for k, row in enumerate(run["success_matrix"])], dtype=float)
        ax.imshow(np.ma.masked_invalid(s), vmin=0, vmax=1, cmap="viridis")
        for (k, i), v in np.ndenumerate(s):
            if not np.isnan(v):
                ax.text(i, k, f"{v:.2f}", ha="center", va="center", color="w" if v < 0.6 else "k", fontsize=8)
        ax.set_xticks(range(n), skills, rotation=30, ha="right")
        ax.set_yticks(range(n), [f"after {x}" for x in skills])
        ax.set_title(f"{name}: success S[k][i] (final AFSR {run['afsr_final']:.3f})", fontsize=9)
    ax = axes[2]
    for name in names:
        ax.plot(range(1, n + 1), summary["runs"][name]["afsr_curve"], marker="o", label=name)
    ax.set_xticks(range(1, n + 1), [f"{k}\n{s}" for k, s in enumerate(skills, 1)], fontsize=8)
    ax.set_ylim(-0.02, 1.05)
    ax.set_xlabel("skills learned k")
    ax.set_title("AFSR after each stage", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.suptitle(f"{title}\n{difference_sentence(summary)}", fontsize=9)
    if caption:
        fig.supxlabel(caption, fontsize=8)
    save_figure(fig, path)


def write_side_by_side(out: Path, runs: Mapping[str, Path], title: str, context: str,
                       notes: Sequence[str] = (), caption: str = "") -> dict[str, Any]:
    """Write ``comparison.png`` and ``results.md`` of two finished runs into ``out`` (both atomic).

    Args:
        out: the output folder.
        runs: name -> run directory, two of them (the difference is the first's final AFSR minus the second's).
        title: the figure's and the markdown's heading.
        context: the markdown's first paragraph (what was run).
        notes: the markdown's paragraphs after the tables.
        caption: the figure's line under the panels.

    Returns:
        :func:`side_by_side`'s result.
    """
    summary = side_by_side(runs)
    write_figure(summary, Path(out) / FIGURE, title, caption)
    atomic_write_bytes(Path(out) / REPORT, render_markdown(summary, title, context, notes).encode())
    return summary
