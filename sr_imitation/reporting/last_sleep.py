"""What a stream's last sleep did: the newest skill and the older ones across the final sleep.

    python -m sr_imitation.reporting.last_sleep RUN_DIR [RUN_DIR ...] --output=DIR

For every run with a final sleep: the newest skill's success right after its own wake and after the final sleep,
each older skill's change across that sleep (after the sleep minus right after the last wake), the memories' losses
before and after it, the anchor's weight and where the sleep stopped. Success values are means over evaluation units
(the run's ``success_matrix`` and ``extra.success_matrix_after_wake``). Where the run's final stage was re-slept with
the anchor off (``sr-sleep`` output beside the run as ``<run>_final_sleep_anchor_off/``,
``tools/experiments/resleep_anchor_off.sh``), a second row reports that sleep the same way. Written as
``last_sleep.json`` (sealed), ``last_sleep.md`` and ``last_sleep.png`` (the older skills' and the newest skill's change,
with the anchor and without it, paired by run).
"""

from __future__ import annotations

import argparse
import io
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from sr_imitation.core.metrics import mean_sem
from sr_imitation.io import atomic_write_bytes, read_checked_json, write_checked_json
from sr_imitation.reporting.results import load_results


def last_sleep_row(run: Path) -> dict[str, Any]:
    """The final sleep of one run.

    Args:
        run: a run directory holding ``results.json`` (any schema version the reporting modules read).

    Returns:
        The run's order, the newest skill's success after its wake and after the sleep, each older skill's change,
        the summed and newest memory losses before and after, ``anchor_lambda``, ``stop_iteration``.

    Raises:
        ValueError: naming the run if it has no final sleep or no success after the last wake.
    """
    results = load_results(Path(run))
    skills = list(results["skills"])
    final_stage = results["stages"][-1]
    sleep = final_stage.get("sleep")
    after_wake = (results.get("extra") or {}).get("success_matrix_after_wake")
    if not sleep or after_wake is None:
        raise ValueError(f"{run}: no final sleep recorded (a run without sleep, or one that has not finished)")
    woke, slept = after_wake[-1], results["success_matrix"][-1]
    if any(v is None for v in (*woke, *slept)):
        raise ValueError(f"{run}: the last stage was not evaluated on every skill")
    return _row(str(run), results.get("label", results.get("method")), results.get("seed"), skills, woke, slept, sleep)


def _row(run: str, method: Any, seed: Any, skills: Sequence[str], woke: Sequence[float], slept: Sequence[float],
         sleep: dict[str, Any]) -> dict[str, Any]:
    """One row from the success right after the last wake and after the final sleep, and the sleep's record."""
    before, after = sleep["initial_memory_losses"], sleep["final_memory_losses"]
    older = {s: slept[i] - woke[i] for i, s in enumerate(skills[:-1])}
    return {
        "run": run, "method": method, "seed": seed, "skills": list(skills), "newest": skills[-1],
        "newest_after_wake": woke[-1], "newest_after_sleep": slept[-1], "newest_change": slept[-1] - woke[-1],
        "older_change": older, "older_mean_change": sum(older.values()) / len(older) if older else 0.0,
        "loss_before": sum(before), "loss_after": sum(after),
        "newest_loss_before": before[-1], "newest_loss_after": after[-1],
        "anchor_lambda": sleep.get("anchor_lambda"), "stop_iteration": sleep.get("stop_iteration"),
    }


ANCHOR_OFF = "_final_sleep_anchor_off"
"""The suffix of a run's anchor-off re-sleep folder (beside the run)."""


def resleep_row(folder: Path) -> dict[str, Any]:
    """The same row for an ``sr-sleep`` re-sleep of a run's final stage (its ``sleep.json``, evaluated before and
    after on every skill).

    Args:
        folder: the ``sr-sleep`` output folder.

    Returns:
        The row, ``run`` naming the folder, ``method`` the sleep's anchor strength.
    """
    record = read_checked_json(Path(folder) / "sleep.json")
    sleep, success = record["sleep"], record["success"]
    skills = list(sleep["skills"])
    if any(s not in success for s in skills):
        raise ValueError(f"{folder}: the re-sleep was not evaluated on every skill (--eval.skills)")
    woke = [success[s]["before"] for s in skills]
    slept = [success[s]["after"] for s in skills]
    method = f"re-sleep, anchor strength {record['sleep_settings']['anchor_strength']}"
    return _row(str(folder), method, None, skills, woke, slept, sleep)


def anchor_off_row(run: Path) -> dict[str, Any] | None:
    """:func:`resleep_row` of the anchor-off re-sleep kept beside ``run`` (``<run>_final_sleep_anchor_off/``), or
    ``None`` when the run was not re-slept."""
    folder = Path(run).with_name(Path(run).name + ANCHOR_OFF)
    return resleep_row(folder) if (folder / "sleep.json").is_file() else None


def render_markdown(rows: Sequence[dict[str, Any]]) -> str:
    """One table row per run, then the mean +- SE of the newest and the older skills' changes."""
    lines = ["| run | newest | after its wake | after the final sleep | change | older skills' mean change | "
             "memory loss before -> after (sum) | newest's memory loss before -> after | anchor lambda | stopped |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {Path(r['run']).name} | {r['newest']} | {r['newest_after_wake']:.3f} | "
                     f"{r['newest_after_sleep']:.3f} | {r['newest_change']:+.3f} | {r['older_mean_change']:+.3f} | "
                     f"{r['loss_before']:.3g} -> {r['loss_after']:.3g} | {r['newest_loss_before']:.3g} -> "
                     f"{r['newest_loss_after']:.3g} | {r['anchor_lambda']} | {r['stop_iteration']} |")
    for what, group in (("runs", [r for r in rows if not r["run"].endswith(ANCHOR_OFF)]),
                        ("anchor-off re-sleeps", [r for r in rows if r["run"].endswith(ANCHOR_OFF)])):
        if group:
            newest = _pm([r["newest_change"] for r in group])
            older = _pm([r["older_mean_change"] for r in group])
            lines += ["", f"Over {len(group)} {what}: the newest skill changed {newest} across the final sleep, the "
                          f"older skills {older} on average ({'mean +- SE' if len(group) > 1 else 'one run: no SE'})."]
    return "\n".join(lines) + "\n"


def _pm(values: Sequence[float]) -> str:
    """``+0.092 +- 0.025``; a single value without its (undefined) SE."""
    mean, sem = mean_sem(values)
    return f"{mean:+.3f}" if len(values) < 2 else f"{mean:+.3f} +- {sem:.3f}"


def write_figure(rows: Sequence[dict[str, Any]], path: Path) -> None:
    """Two panels, the older skills' mean change and the newest skill's change across the final sleep: per run a point
    with the anchor (the run's own sleep) and, where it was re-slept, one without it, joined by a line; a bar at each
    group's mean."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = [r for r in rows if not r["run"].endswith(ANCHOR_OFF)]
    off = {r["run"][: -len(ANCHOR_OFF)]: r for r in rows if r["run"].endswith(ANCHOR_OFF)}
    fig, axes = plt.subplots(1, 2, figsize=(8, 3.6), sharey=True)
    for ax, key, title in zip(axes, ("older_mean_change", "newest_change"),
                              ("older skills' mean change", "newest skill's change"), strict=True):
        ax.axhline(0, color="grey", lw=0.8)
        groups = {"with the anchor": [r[key] for r in runs],
                  "anchor off": [off[r["run"]][key] for r in runs if r["run"] in off]}
        for x, values in enumerate(groups.values()):
            if values:
                ax.bar(x, sum(values) / len(values), width=0.6, alpha=0.35, color=("tab:blue", "tab:orange")[x])
        for r in runs:
            if r["run"] in off:
                ax.plot([0, 1], [r[key], off[r["run"]][key]], color="grey", lw=0.8, marker="o", ms=4)
            else:
                ax.plot([0], [r[key]], color="grey", marker="o", ms=4)
        ax.set_xticks([0, 1], list(groups))
        ax.set_title(title, fontsize=10)
    values = [r[k] for r in rows for k in ("older_mean_change", "newest_change")] + [0.0]
    pad = 0.1 * (max(values) - min(values)) or 0.05
    axes[0].set_ylim(min(values) - pad, max(values) + pad)  # a change of 0 stays inside the frame
    axes[0].set_ylabel("success change across the final sleep")
    fig.suptitle(f"What the last sleep did ({len(runs)} runs; a line joins a run and its re-sleep)", fontsize=10)
    buf = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buf, format="png", dpi=120)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


def write_report(runs: Sequence[Path], out: Path) -> list[dict[str, Any]]:
    """Rows of every run, written to ``out`` as ``last_sleep.json`` (sealed), ``.md`` and ``.png``."""
    rows = []
    for run in map(Path, runs):
        rows.append(last_sleep_row(run))
        off = anchor_off_row(run)
        if off is not None:
            rows.append(off)
    out.mkdir(parents=True, exist_ok=True)
    write_checked_json(out / "last_sleep.json", {"rows": rows})
    atomic_write_bytes(out / "last_sleep.md", render_markdown(rows).encode())
    write_figure(rows, out / "last_sleep.png")
    return rows


def main(args: Sequence[str] | None = None) -> None:
    """``python -m sr_imitation.reporting.last_sleep RUN_DIR ... --output=DIR``."""
    parser = argparse.ArgumentParser(prog="python -m sr_imitation.reporting.last_sleep", description=__doc__)
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--output", type=Path, required=True)
    ns = parser.parse_args(args)
    rows = write_report(ns.runs, ns.output)
    print(render_markdown(rows))  # noqa: T201 (command output)


if __name__ == "__main__":
    from sr_imitation.infra.cli_errors import run_cli

    run_cli("sr_imitation.reporting.last_sleep", main)
