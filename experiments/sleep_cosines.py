"""Why the SAC sleeps' Nash weights stay at 1/k (issue 59; exploratory): the cosine matrix C of the memory gradients
that Eq. 1 bargains over, read from re-sleeps of archived stages.

    python -m experiments.sleep_cosines --archive=docs/results/sac_sleep_cosines \\
        --runs=[outputs/resleep_cosines/sr_c_b1_seed102_s5]

A re-sleep (``sr-sac-sleep`` with the source's settings: it repeats the source's sleep) records C at the sleep's first
and last applied iteration in its ``sleep_diagnostics.json`` (:class:`~sr_imitation.core.sleep.SleepResult`), which
runs made before that record existed lack. ``--runs``: finished re-sleeps, each copied first into
``<archive>/<its folder name>/`` (:func:`collect`: its ``resleep.json``, results and settings, the re-slept stage's
diagnostics as ``stage<k>_sleep_diagnostics.json``, each checksum-checked on the way, and ``compare.txt``, the
re-sleep against the run it repeats, as ``python -m sr_imitation.reporting.compare`` prints it; the folder replaced
atomically). Then, for every re-sleep in the archive (:func:`summarize_run`): whether it repeated its run (no
measured value differs), C at the first and last iteration, its largest |off-diagonal| entry, Eq. 1's optimum on C
(a cold exact solve, :func:`~sr_imitation.core.aggregation.nash_weights`), the weights the sleep recorded at its last
iteration, and their largest distance from 1/k over every iteration after the first (at the first, a memory of the
actor the sleep starts from has a zero gradient and is masked). Written to ``cosines.json`` / ``cosines.md`` /
``cosines.png`` in the archive.

What it tells: on unit directions Eq. 1 maximizes sum_i log (C alpha)_i over the simplex (``aggregation/_nash.py``);
for C = I the optimum is alpha = 1/k, the mean of the normalized gradients. So weights at 1/k with C near I say the
memories' gradients barely interact (nothing to bargain over), not that the solver is stuck; for k = 2 the weights are
1/2 whatever C is (the closed form). The converse does not hold: 1/k is also the optimum for some C far from I (an
aligned pair beside an orthogonal third, for one), which is why C itself is reported.
"""

from __future__ import annotations

import io
import logging
import re
import shutil
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sr_imitation.core.aggregation import nash_weights
from sr_imitation.infra.cli_errors import run_cli, setup_logging
from sr_imitation.infra.cli_parsing import parse_command
from sr_imitation.infra.fingerprint import FINGERPRINT_FILE, read_fingerprint
from sr_imitation.infra.weight_store import staged_replacement
from sr_imitation.io import atomic_write_bytes, read_checked_json, write_checked_json
from sr_imitation.reporting.compare import report_text

logger = logging.getLogger(__name__)
PROG = "python -m experiments.sleep_cosines"

DIAGNOSTICS = "sleep_diagnostics.json"
KEPT = ("resleep.json", "results.json", FINGERPRINT_FILE)
"""What the archive keeps of a re-sleep besides the stage's diagnostics and ``compare.txt``: what was re-slept from
what, its results and its settings."""
COMPARE = "compare.txt"


def archived_diagnostics(folder: Path, stage: int) -> Path:
    """Where the archive keeps a re-sleep's stage-``stage`` sleep diagnostics (RESULTS' 2026-11-30 06:30 layout)."""
    return folder / f"stage{stage}_{DIAGNOSTICS}"


@dataclass
class CosinesConfig:
    """The command line."""

    archive: Path = Path("docs/results/sac_sleep_cosines")
    """Where the re-sleeps are kept and the summary is written."""
    runs: list[Path] = field(default_factory=list)
    """Finished re-sleeps to copy into the archive first (their folder names name them there)."""


def stage_diagnostics(run: Path) -> Path:
    """The re-slept stage's ``sleep_diagnostics.json`` of the re-sleep ``run`` (its ``resleep.json`` names the
    stage); ``FileNotFoundError`` naming what is missing."""
    stage = read_checked_json(run / "resleep.json")["stage"]
    found = sorted(run.glob(f"stages/{stage:02d}_*/sleep/{DIAGNOSTICS}"))
    if len(found) != 1:
        raise FileNotFoundError(f"{run}: no stages/{stage:02d}_*/sleep/{DIAGNOSTICS} (not a finished re-sleep?)")
    return found[0]


def collect(run: Path, archive: Path) -> Path:
    """Copy the re-sleep ``run`` into ``archive / run.name`` (see the module docstring; every file checked first, the
    run it repeats compared), replacing an older copy atomically; returns the archived folder."""
    run = Path(run)
    resleep = read_checked_json(run / "resleep.json")
    files = {name: run / name for name in KEPT}
    files[archived_diagnostics(Path(), resleep["stage"]).name] = stage_diagnostics(run)
    for name, path in files.items():  # a damaged file stops here, before the archive changes
        read_fingerprint(path) if name == FINGERPRINT_FILE else read_checked_json(path)
    repeated = Path(resleep["archived"])
    if not (repeated / "results.json").is_file():
        raise FileNotFoundError(f"{repeated}: the run {run / 'resleep.json'} repeats is not here (run from the "
                                "repository root)")
    compare, _ = report_text(repeated, run)
    target = archive / run.name
    with staged_replacement(target) as tmp:
        for name, path in files.items():
            shutil.copy2(path, tmp / name)
        atomic_write_bytes(tmp / COMPARE, compare.encode())
    logger.info("archived %s -> %s", run, target)
    return target


def differing_values(compare: str) -> int | None:
    """How many measured values ``compare.txt`` says differ (0 when the runs agree); None when it says neither."""
    found = re.search(r"measured values compared: (?:the runs (agree)|the runs differ in (\d+) values)", compare)
    if found is None:
        return None
    return 0 if found.group(1) else int(found.group(2))


def largest_off_diagonal(cosine: np.ndarray) -> float:
    """max |C_ij| over i != j among the memories with a non-zero gradient (a zero gradient's diagonal entry is 0)."""
    live = np.diag(cosine) > 0.5
    sub = cosine[np.ix_(live, live)]
    off = sub[~np.eye(len(sub), dtype=bool)]
    return float(np.abs(off).max()) if off.size else 0.0


def summarize_run(folder: Path) -> dict[str, Any]:
    """One archived re-sleep's row (see the module docstring)."""
    resleep = read_checked_json(folder / "resleep.json")
    path = archived_diagnostics(folder, resleep["stage"])
    diagnostics = read_checked_json(path)
    results = read_checked_json(folder / "results.json")
    matrices = [np.asarray(c, dtype=float) for c in diagnostics.get("cosines_first_last", [])]
    if len(matrices) != 2:
        raise ValueError(f"{path}: no cosine matrices (a sleep recorded before they existed)")
    alpha = np.asarray(diagnostics["alpha"], dtype=float)
    k = alpha.shape[1]
    optimum = nash_weights(matrices[1]).alpha
    return {
        "run": folder.name,
        "source": resleep["source"],
        "repeats": resleep["archived"],
        "settings_changed": resleep["changed"],
        "differing_values": differing_values((folder / COMPARE).read_text()),
        "stage": resleep["stage"],
        "skills": diagnostics["skills"],
        "commit": results["code"]["commit"][:7],
        "final_afsr": results["metrics"]["afsr"]["final"],
        "stop_iteration": diagnostics["stop_iteration"],
        "stop_reason": diagnostics["stop_reason"],
        "cosines_first": matrices[0].tolist(),
        "cosines_last": matrices[1].tolist(),
        "largest_off_diagonal_first": largest_off_diagonal(matrices[0]),
        "largest_off_diagonal_last": largest_off_diagonal(matrices[1]),
        "nash_optimum_on_last": [float(a) for a in optimum],
        "weights_last": [float(a) for a in alpha[-1]],
        "largest_weight_deviation": float(np.abs(alpha[1:] - 1 / k).max()) if len(alpha) > 1 else 0.0,
    }


def archived_runs(archive: Path) -> list[Path]:
    """The archive's re-sleep folders (those with a ``resleep.json``), by name."""
    return sorted(p.parent for p in Path(archive).glob("*/resleep.json"))


def _vector(values: Sequence[float]) -> str:
    return " / ".join(f"{v:.2f}" for v in values)


def render(summary: Mapping[str, Any]) -> str:
    lines = [
        "# Issue 59: the cosine matrix the SAC sleeps bargain over (exploratory)", "",
        "Re-sleeps of archived stages with the source's settings (`sr-sac-sleep`), which repeat the source's sleep and",
        "record the cosine matrix C of the memory gradients at its first and last applied iteration. Eq. 1's optimum",
        "for C = I is 1/k (the mean of the normalized gradients).", "",
        "| re-sleep | repeats | values differing from it | stage | final AFSR | stop |"
        " largest off-diagonal abs(C): first / last | weights at the end |"
        " Eq. 1's optimum on the last C | weights' largest distance from 1/k (after iteration 0) | commit |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in summary["runs"]:
        same = "not read" if r["differing_values"] is None else r["differing_values"]
        lines.append(f"| {r['run']} | `{r['repeats']}` | {same} | {r['stage']} | {r['final_afsr']:.3f}"
                     f" | {r['stop_iteration']} ({r['stop_reason']})"
                     f" | {r['largest_off_diagonal_first']:.3f} / {r['largest_off_diagonal_last']:.3f}"
                     f" | {_vector(r['weights_last'])} | {_vector(r['nash_optimum_on_last'])}"
                     f" | {r['largest_weight_deviation']:.3f} | {r['commit']} |")
    for r in summary["runs"]:
        lines += ["", f"{r['run']} (source `{r['source']}`, stage {r['stage']}; memories {', '.join(r['skills'])}):"]
        for name in ("first", "last"):
            lines += ["", f"C at the {name} iteration:", "", "```"]
            lines += ["  ".join(f"{v:+.3f}" for v in row) for row in r[f"cosines_{name}"]]
            lines += ["```"]
    return "\n".join(lines) + "\n"


def plot(summary: Mapping[str, Any], path: Path) -> None:
    """One row per re-sleep: C at the first and at the last iteration as heat maps (-1 blue, +1 red), values
    written in the cells."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = summary["runs"]
    fig, axes = plt.subplots(len(runs), 2, figsize=(6.4, 3.0 * len(runs)), squeeze=False)
    for row, r in zip(axes, runs, strict=True):
        for ax, name in zip(row, ("first", "last"), strict=True):
            c = np.asarray(r[f"cosines_{name}"])
            ax.imshow(c, cmap="RdBu_r", vmin=-1, vmax=1)
            for (i, j), v in np.ndenumerate(c):
                ax.text(j, i, f"{v:.2f}", ha="center", va="center", fontsize=6,
                        color="white" if abs(v) > 0.6 else "black")
            ticks = [s.split("-")[0] for s in r["skills"]]
            ax.set_xticks(range(len(ticks)), ticks, fontsize=6, rotation=45)
            ax.set_yticks(range(len(ticks)), ticks, fontsize=6)
            ax.set_title(f"{r['run']}: C, {name} iteration", fontsize=7)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


def run_cosines(cfg: CosinesConfig) -> dict[str, Any]:
    """Collect ``cfg.runs``, then summarize every re-sleep in the archive into cosines.{json,md,png}."""
    for run in cfg.runs:
        collect(Path(run), cfg.archive)
    folders = archived_runs(cfg.archive)
    if not folders:
        raise FileNotFoundError(f"{cfg.archive}: no re-sleeps (folders with resleep.json); give --runs")
    summary = {"runs": [summarize_run(f) for f in folders]}
    write_checked_json(cfg.archive / "cosines.json", summary)
    atomic_write_bytes(cfg.archive / "cosines.md", render(summary).encode())
    plot(summary, cfg.archive / "cosines.png")
    for r in summary["runs"]:
        logger.info("%s: largest off-diagonal cosine %.3f first, %.3f last; weights within %.3f of 1/k", r["run"],
                    r["largest_off_diagonal_first"], r["largest_off_diagonal_last"], r["largest_weight_deviation"])
    return summary


def main(args: list[str] | None = None) -> None:
    setup_logging()
    run_cosines(parse_command(CosinesConfig, list(sys.argv[1:] if args is None else args), prog=PROG))


if __name__ == "__main__":
    run_cli(PROG, main)
