"""Recompute ``bwt`` and ``bwt_wake`` of finished runs from their raw ``results.json`` files.

    python -m experiments.recompute_bwt --runs=docs/results/needle_cpu_compare
    python -m experiments.recompute_bwt --runs=docs/results/needle_cpu_main \\
        --runs=docs/results/needle_cpu_seed1000 --runs=docs/results/sac_mt5_cpu --output=outputs/bwt.md

``--runs`` is a run directory (it holds ``results.json``) or a folder of them (``<variant>_seed<N>`` as
``needle_compare`` writes them, or ``<variant>_s<N>``); it may be repeated. Runs written before ``bwt_wake``
existed are handled too:

* needle stream (``sr-train``): S = ``success_matrix`` (mean over evaluation seeds after each stage), W_i = the
  diagonal of ``success_matrix_after_wake`` (the ``wake.eval`` of stage i; else ``phases["<i>.wake.eval"]``);
* SAC stream (``sr-rl-train``): S = ``success_matrix``, W_i = ``stages[i].eval_after_wake`` when it was measured,
  else S[i, i] for a stage without sleep (the same policy); a sleep stage without it leaves ``bwt_wake`` n/a.

bwt = mean_{i<K} (S[K, i] - S[i, i]) and bwt_wake = mean_{i<K} (S[K, i] - W_i) (``core.metrics.bwt_curve``; both are
linear in S, so on the seed-mean matrices they equal the mean of the per-evaluation-seed values). Printed: one row
per run (with the stored ``bwt`` for a check), mean +- SE over training seeds per variant, and the paired
difference of each variant minus the baseline variant (``--baseline``, default ``wake_only``; ``wake`` for the SAC
folders) over the training seeds both have.
"""

from __future__ import annotations

import argparse
import math
import re
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sr_imitation.core.metrics import bwt_curve, mean_sem
from sr_imitation.io import atomic_write_bytes, atomic_write_json, read_json

_NAME = re.compile(r"^(?P<variant>.+?)_(?:seed|s)(?P<seed>\d+)$")


@dataclass
class RunBWT:
    """Both BWTs of one run (final stage K), with what they were computed from."""

    run: str
    variant: str
    seed: int
    substrate: str
    bwt: float
    bwt_wake: float | None
    stored_bwt: float | None
    after_stage_diagonal: list[float]
    after_wake_diagonal: list[float | None]
    after_wake_source: str


def _matrix(rows: Sequence[Sequence[float | None]]) -> np.ndarray:
    return np.array([[np.nan if x is None else float(x) for x in row] for row in rows], dtype=np.float64)


def _stored_bwt(results: dict[str, Any]) -> float | None:
    value = results.get("metrics", {}).get("bwt")
    if isinstance(value, dict):  # needle stream: summary over evaluation seeds
        value = value.get("final_mean")
    return None if value is None else float(value)


def _needle_wake_diagonal(results: dict[str, Any], path: Path) -> tuple[list[float | None], str]:
    skills = results["skills"]
    if results.get("success_matrix_after_wake") is not None:
        w = _matrix(results["success_matrix_after_wake"])
        return [float(w[i, i]) for i in range(len(skills))], "success_matrix_after_wake"
    phases = results.get("phases", {})
    try:
        return [float(phases[f"{i + 1}.wake.eval"]["success"][s]) for i, s in enumerate(skills)], "phases"
    except KeyError as exc:
        raise ValueError(f"{path}: no after-wake evaluation of skill {exc} (success_matrix_after_wake or "
                         "phases[<k>.wake.eval])") from None


def _rl_wake_diagonal(results: dict[str, Any], s: np.ndarray) -> tuple[list[float | None], str]:
    out: list[float | None] = []
    sources = set()
    for i, stage in enumerate(results["stages"]):
        if "eval_after_wake" in stage:
            out.append(float(stage["eval_after_wake"]["success_rate"]))
            sources.add("eval_after_wake")
        elif "sleep" not in stage:
            out.append(float(s[i, i]))  # no sleep at this stage: the after-wake policy is the stage policy
            sources.add("stage evaluation (no sleep)")
        else:
            out.append(None)
            sources.add("missing (sleep stage not evaluated after wake)")
    return out, " + ".join(sorted(sources))


def recompute_run(run_dir: Path) -> RunBWT:
    """Both BWTs of the run in ``run_dir`` from its ``results.json``.

    Raises:
        FileNotFoundError: no ``results.json``.
        ValueError: the file is neither a needle nor a SAC stream result, or lacks the needle after-wake data.
    """
    path = Path(run_dir) / "results.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no results (unfinished run?)")
    results = read_json(path)
    if "success_matrix" not in results or "skills" not in results:
        raise ValueError(f"{path}: not a stream result (no success_matrix / skills)")
    s = _matrix(results["success_matrix"])
    if "stages" in results:
        substrate = "sac"
        wake, source = _rl_wake_diagonal(results, s)
    elif "phases" in results or "success_matrix_after_wake" in results:
        substrate = "needle"
        wake, source = _needle_wake_diagonal(results, path)
    else:
        raise ValueError(f"{path}: neither a needle (phases) nor a SAC (stages) stream result")
    n = s.shape[0]
    bwt = float(bwt_curve(s)[-1])
    needed = wake[: n - 1]
    bwt_wake = None
    if all(x is not None for x in needed):
        bwt_wake = float(bwt_curve(s, [np.nan if x is None else x for x in wake])[-1])
    match = _NAME.match(Path(run_dir).name)
    variant = match["variant"] if match else str(results.get("method", Path(run_dir).name))
    seed = int(match["seed"]) if match else int(results.get("seed", 0))
    return RunBWT(str(run_dir), variant, seed, substrate, bwt, bwt_wake, _stored_bwt(results),
                  [float(s[i, i]) for i in range(n)], wake, source)


def find_runs(roots: Sequence[Path]) -> list[Path]:
    """Each root itself if it holds ``results.json``, else its sub-directories that do (sorted).

    Raises:
        FileNotFoundError: a root holds no run.
    """
    runs: list[Path] = []
    for root in roots:
        root = Path(root)
        if (root / "results.json").is_file():
            runs.append(root)
            continue
        found = sorted(d for d in root.iterdir() if (d / "results.json").is_file()) if root.is_dir() else []
        if not found:
            raise FileNotFoundError(f"{root}: no results.json in it or in its sub-directories")
        runs += found
    return runs


def _stats(values: Sequence[float | None]) -> dict[str, Any]:
    present = [float(v) for v in values if v is not None and math.isfinite(v)]
    mean, sem = mean_sem(present) if present else (float("nan"), float("nan"))
    return {"mean": mean, "sem": sem, "n": len(present), "values": list(values)}


def summarize_runs(runs: Sequence[RunBWT], baseline: str | None = None) -> dict[str, Any]:
    """Per variant mean +- SE over training seeds, and paired differences (variant - baseline, same seeds)."""
    by_variant: dict[str, dict[int, RunBWT]] = defaultdict(dict)
    for r in runs:
        by_variant[r.variant][r.seed] = r
    variants = {v: {"seeds": sorted(rs), "bwt": _stats([rs[s].bwt for s in sorted(rs)]),
                    "bwt_wake": _stats([rs[s].bwt_wake for s in sorted(rs)])}
                for v, rs in by_variant.items()}
    if baseline is None:
        baseline = next((b for b in ("wake_only", "wake") if b in by_variant), None)
    paired: dict[str, Any] = {}
    if baseline in by_variant:
        base = by_variant[baseline]
        for v, rs in by_variant.items():
            common = sorted(set(rs) & set(base))
            if v == baseline or not common:
                continue
            row: dict[str, Any] = {"seeds": common}
            for key in ("bwt", "bwt_wake"):
                diffs = [None if getattr(rs[s], key) is None or getattr(base[s], key) is None
                         else getattr(rs[s], key) - getattr(base[s], key) for s in common]
                row[key] = _stats(diffs)
            paired[v] = row
    return {"baseline": baseline, "variants": variants, "paired_minus_baseline": paired}


def _fmt(value: float | None, sem: float | None = None) -> str:
    if value is None or not math.isfinite(value):
        return "n/a"
    if sem is None or not math.isfinite(sem):
        return f"{value:+.3f}"
    return f"{value:+.3f} +- {sem:.3f}"


def render(runs: Sequence[RunBWT], summary: dict[str, Any]) -> str:
    lines = ["BWT with two references: `bwt` (after stage i, i.e. after its sleep when there is one) and `bwt_wake`",
             "(right after skill i's own wake). Final stage; each run's value is the mean over its evaluation seeds.",
             "", "| run | variant | seed | stored bwt | bwt | bwt_wake | S[i,i] after stage i | W_i after own wake |"
             " W from |", "|---|---|---|---|---|---|---|---|---|"]
    for r in runs:
        diag = ", ".join(f"{x:.2f}" for x in r.after_stage_diagonal)
        wake = ", ".join("-" if x is None else f"{x:.2f}" for x in r.after_wake_diagonal)
        lines.append(f"| {Path(r.run).name} | {r.variant} | {r.seed} | {_fmt(r.stored_bwt)} | {_fmt(r.bwt)} | "
                     f"{_fmt(r.bwt_wake)} | {diag} | {wake} | {r.after_wake_source} |")
    lines += ["", "Mean +- SE over training seeds:", "", "| variant | seeds | bwt | bwt_wake |", "|---|---|---|---|"]
    for v, row in summary["variants"].items():
        lines.append(f"| {v} | {', '.join(map(str, row['seeds']))} | {_fmt(row['bwt']['mean'], row['bwt']['sem'])}"
                     f" | {_fmt(row['bwt_wake']['mean'], row['bwt_wake']['sem'])} |")
    if summary["paired_minus_baseline"]:
        lines += ["", f"Paired difference variant - {summary['baseline']} (same training seed), mean +- SE:", "",
                  "| variant | seeds | bwt | bwt_wake |", "|---|---|---|---|"]
        for v, row in summary["paired_minus_baseline"].items():
            lines.append(f"| {v} | {', '.join(map(str, row['seeds']))} | "
                         f"{_fmt(row['bwt']['mean'], row['bwt']['sem'])} | "
                         f"{_fmt(row['bwt_wake']['mean'], row['bwt_wake']['sem'])} |")
    mismatched = [Path(r.run).name for r in runs
                  if r.stored_bwt is not None and not math.isclose(r.stored_bwt, r.bwt, abs_tol=1e-9)]
    lines += ["", "Stored bwt reproduced for every run." if not mismatched
              else f"Stored bwt NOT reproduced for: {', '.join(mismatched)}."]
    return "\n".join(lines) + "\n"


def main(args: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=Path, action="append", required=True,
                        help="a run directory or a folder of run directories (repeatable)")
    parser.add_argument("--baseline", default=None, help="variant for paired differences (default: wake_only)")
    parser.add_argument("--output", type=Path, default=None, help="also write the table (.md) and a .json beside it")
    ns = parser.parse_args(args)
    try:
        runs = [recompute_run(d) for d in find_runs(ns.runs)]
    except (FileNotFoundError, ValueError) as exc:
        parser.exit(2, f"recompute_bwt: {exc}\n")
    summary = summarize_runs(runs, ns.baseline)
    text = render(runs, summary)
    print(text, end="")  # noqa: T201 (CLI output)
    if ns.output is not None:
        atomic_write_bytes(ns.output.with_suffix(".md"), text.encode())
        atomic_write_json(ns.output.with_suffix(".json"), {"runs": [asdict(r) for r in runs], **summary})
        print(f"written {ns.output.with_suffix('.md')} and {ns.output.with_suffix('.json')}")  # noqa: T201


if __name__ == "__main__":
    main()
