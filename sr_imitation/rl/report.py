"""Summarize finished ``sr-rl-train`` runs as markdown: ``python -m sr_imitation.rl.report RUN_DIR [RUN_DIR ...]``.

Groups runs by method (``sleeping_robots`` / ``wake_only``), prints every run's final metrics, success-matrix
diagonal/last row and success right after each skill's own wake, and mean +- SEM over seeds per method
(``sr_imitation.core.metrics.mean_sem``). ``BWT`` uses the success after stage i as reference, ``BWT_wake`` the
success right after skill i's own wake (``core.metrics``). Numbers are read from each run's ``results.json``;
nothing is computed that the run did not measure (runs written before ``bwt_wake`` existed show "-", except
wake-only runs, whose after-wake and after-stage policies are the same, so ``bwt_wake`` = ``bwt``).
"""

from __future__ import annotations

import argparse
from collections import defaultdict
from pathlib import Path
from typing import Any

from sr_imitation.core.io import read_json
from sr_imitation.core.metrics import mean_sem

METRICS = ("afsr", "prs", "bwt", "bwt_wake", "spi")
LABELS = {"afsr": "AFSR", "prs": "PRS", "bwt": "BWT", "bwt_wake": "BWT_wake", "spi": "SPI"}


def load_results(run_dir: Path) -> dict[str, Any]:
    path = Path(run_dir) / "results.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no results (unfinished run?)")
    return read_json(path)


def _fmt(x: float | None) -> str:
    return "-" if x is None else f"{x:.3f}"


def _metric(results: dict[str, Any], name: str) -> float | None:
    """A final metric of one run; ``bwt_wake`` of a wake-only run written before it existed equals its ``bwt``."""
    m = results["metrics"]
    if name == "bwt_wake" and name not in m and results.get("method") == "wake_only":
        return m.get("bwt")
    return m.get(name)


def summarize(run_dirs: list[Path]) -> str:
    runs = [(Path(d), load_results(d)) for d in run_dirs]
    lines = ["| run | method | seed | " + " | ".join(LABELS[m] for m in METRICS)
             + " | final success per skill | diagonal (just learned) | right after own wake |",
             "|---" * (6 + len(METRICS)) + "|"]
    by_method: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for d, r in runs:
        by_method[r["method"]].append(r)
        matrix = r["success_matrix"]
        last = ", ".join(f"{s}={_fmt(x)}" for s, x in zip(r["skills"], matrix[-1], strict=True))
        diag = ", ".join(_fmt(matrix[i][i]) for i in range(len(matrix)))
        wake = ", ".join(_fmt(x) for x in r.get("success_after_own_wake") or [None] * len(matrix))
        lines.append(f"| {d.name} | {r['method']} | {r['seed']} | "
                     + " | ".join(_fmt(_metric(r, m)) for m in METRICS) + f" | {last} | {diag} | {wake} |")
    lines += ["", "| method | seeds | " + " | ".join(LABELS[m] for m in METRICS) + " |",
              "|---" * (2 + len(METRICS)) + "|"]
    for method, rs in sorted(by_method.items()):
        cells = []
        for m in METRICS:
            mean, sem = mean_sem([float("nan") if _metric(r, m) is None else _metric(r, m) for r in rs])
            cells.append("-" if mean != mean else f"{mean:.3f}" + ("" if sem != sem else f" +- {sem:.3f}"))
        lines.append(f"| {method} | {len(rs)} ({', '.join(str(r['seed']) for r in rs)}) | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path)
    args = parser.parse_args()
    print(summarize(args.runs))  # noqa: T201 (CLI output)


if __name__ == "__main__":
    main()
