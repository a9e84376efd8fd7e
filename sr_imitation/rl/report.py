"""Summarize finished ``sr-rl-train`` runs as markdown: ``python -m sr_imitation.rl.report RUN_DIR [RUN_DIR ...]``.

Groups runs by method (``sleeping_robots`` / ``wake_only``), prints every run's final metrics and success-matrix
diagonal/last row, and mean +- SEM over seeds per method (``sr_imitation.core.metrics.mean_sem``). Numbers are
read from each run's ``results.json``; nothing is computed that the run did not measure.
"""

from __future__ import annotations

import argparse
from collections import defaultdict
from pathlib import Path
from typing import Any

from sr_imitation.core.io import read_json
from sr_imitation.core.metrics import mean_sem

METRICS = ("afsr", "prs", "bwt", "spi")


def load_results(run_dir: Path) -> dict[str, Any]:
    path = Path(run_dir) / "results.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no results (unfinished run?)")
    return read_json(path)


def _fmt(x: float | None) -> str:
    return "-" if x is None else f"{x:.3f}"


def summarize(run_dirs: list[Path]) -> str:
    runs = [(Path(d), load_results(d)) for d in run_dirs]
    lines = ["| run | method | seed | " + " | ".join(m.upper() for m in METRICS)
             + " | final success per skill | diagonal (just learned) |",
             "|---" * (5 + len(METRICS)) + "|"]
    by_method: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for d, r in runs:
        by_method[r["method"]].append(r)
        matrix = r["success_matrix"]
        last = ", ".join(f"{s}={_fmt(x)}" for s, x in zip(r["skills"], matrix[-1], strict=True))
        diag = ", ".join(_fmt(matrix[i][i]) for i in range(len(matrix)))
        lines.append(f"| {d.name} | {r['method']} | {r['seed']} | "
                     + " | ".join(_fmt(r["metrics"].get(m)) for m in METRICS) + f" | {last} | {diag} |")
    lines += ["", "| method | seeds | " + " | ".join(m.upper() for m in METRICS) + " |",
              "|---" * (2 + len(METRICS)) + "|"]
    for method, rs in sorted(by_method.items()):
        cells = []
        for m in METRICS:
            mean, sem = mean_sem([float("nan") if r["metrics"].get(m) is None else r["metrics"][m] for r in rs])
            cells.append(f"{mean:.3f}" + ("" if sem != sem else f" +- {sem:.3f}"))
        lines.append(f"| {method} | {len(rs)} ({', '.join(str(r['seed']) for r in rs)}) | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path)
    args = parser.parse_args()
    print(summarize(args.runs))  # noqa: T201 (CLI output)


if __name__ == "__main__":
    main()
