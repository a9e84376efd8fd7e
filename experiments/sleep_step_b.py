"""Step B of issue 59's protocol (docs/RESULTS.md, "a SAC sleep that keeps what its wakes learn"): rule B on the
full runs of the step-A winner and of Reset & Distill's wake with SR's consolidation, against the calibration runs.

    python -m experiments.sleep_step_b --archive=docs/results/sac_sleep_step_b \\
        --calibration=docs/results/sac_sleep_calibration --variants=[sr_b1,sr_c_b1]

Reads ``<archive>/<variant>_seed<seed>/results.json`` and ``<calibration>/sr_seed<seed>/results.json`` (checksums
checked) for the calibration seeds 100-102. Before any number is used, each step-B run is checked to be what its name
says: its seed, and its settings equal to the calibration run's of that seed except exactly the keys its variant's
flags set (:data:`~sr_imitation.experiments.mt5_compare.VARIANTS`), each at the flag's value; a run that is not is
one line naming the file and the key. Then ``step_b.json`` / ``step_b.md`` / ``step_b.png`` in ``--output`` (default
the archive): per variant and seed the final AFSR, BWT against both references, success per skill after its own wake
and at the end, each sleep's stop iteration and reason, the code commit and CPU; each sleep's success before and
after, memory losses and Nash weights (:func:`sleeps_of`); per variant the mean +- SE over the
seeds and the paired difference to the calibration SR runs; and rule B as written (:func:`rule_b`), decided only when
every variant has every one of the protocol's seeds (an exact tie: the earlier variant of ``--variants``).
Everything here is exploratory (calibration seeds); it decides which variant V the confirmation runs, and the
decision is written in RESULTS before any test-seed run of V.
"""

from __future__ import annotations

import io
import logging
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from experiments.sleep_screening import PROTOCOL_SEEDS, losses_text, mean_se, se_text, weights_text
from sr_imitation.experiments.mt5_compare import VARIANTS
from sr_imitation.infra.cli_errors import run_cli, setup_logging
from sr_imitation.infra.cli_parsing import parse_command
from sr_imitation.infra.fingerprint import flatten_settings
from sr_imitation.io import atomic_write_bytes, read_checked_json, write_checked_json
from sr_imitation.stream.config import check_choices

logger = logging.getLogger(__name__)
PROG = "python -m experiments.sleep_step_b"

MARGIN = 0.05
"""Rule B: V's mean final AFSR must exceed the calibration SR runs' mean by at least this (the protocol's 0.05)."""
UNCHECKED = frozenset({"output_dir"})
"""Settings that may differ between a step-B run and its calibration run without changing results."""


@dataclass
class StepBConfig:
    """The command line."""

    archive: Path = Path("docs/results/sac_sleep_step_b")
    """The step-B runs' archive (``<variant>_seed<seed>``)."""
    calibration: Path = Path("docs/results/sac_sleep_calibration")
    """The calibration SR runs' archive (``sr_seed<seed>``)."""
    variants: list[str] = field(default_factory=lambda: ["sr_b1", "sr_c_b1"])
    """The step-B variants (``mt5_compare``'s names): the A-winner's ``sr_<x>`` and ``sr_c_<x>``."""
    seeds: list[int] = field(default_factory=lambda: list(PROTOCOL_SEEDS))
    """Calibration seeds; rule B decides only on the protocol's 100-102 (unless ``decide_on_any_seeds``)."""
    output: Path | None = None
    """Where ``step_b.json`` / ``.md`` / ``.png`` go; ``None``: ``archive``."""
    decide_on_any_seeds: bool = False
    """Apply rule B to whatever seeds are given (tests)."""

    def __post_init__(self) -> None:
        check_choices("variants", self.variants, VARIANTS)
        if not self.variants or not self.seeds:
            raise ValueError("variants, seeds: give at least one of each")


def flag_settings(flags: Sequence[str]) -> dict[str, Any]:
    """``["--sleep.early_stop_tol=0", "--method_options={a: b}"]`` -> ``{"sleep.early_stop_tol": 0,
    "method_options": {"a": "b"}}`` (values read as the command line's YAML, as draccus reads them)."""
    out = {}
    for flag in flags:
        key, _, value = flag.removeprefix("--").partition("=")
        out[key] = yaml.safe_load(value)
    return out


def check_run(path: Path, results: Mapping[str, Any], calibration: Mapping[str, Any], variant: str,
              seed: int) -> None:
    """Raise ``ValueError`` (one line naming the file and the key) unless ``results`` is ``variant`` on ``seed``:
    the calibration run's settings (dotted keys, :func:`~sr_imitation.infra.fingerprint.flatten_settings`), except
    that every key at or below one of ``variant``'s flags holds the flag's value instead."""
    flags = flag_settings(VARIANTS[variant])
    expected = flatten_settings(flags) if flags else {}
    mine, theirs = flatten_settings(results["config"]), flatten_settings(calibration["config"])
    if theirs.get("seed") != seed:
        raise ValueError(f"{path}: its calibration run's seed is {theirs.get('seed')}, not {seed}")
    for key in sorted((set(mine) | set(theirs)) - UNCHECKED):
        flagged = any(key == f or key.startswith(f"{f}.") for f in flags)
        want = expected.get(key) if flagged else theirs.get(key)
        if mine.get(key) != want:
            raise ValueError(f"{path}: {key} is {mine.get(key)!r}, {variant} on seed {seed} needs {want!r} "
                             f"(the calibration run's, with {' '.join(VARIANTS[variant]) or 'no flags'})")


def sleeps_of(results: Mapping[str, Any]) -> list[dict[str, Any]]:
    """Each sleep of a run, as issue 59's item 3 asks it reported: the stage, what the newest skill's success was
    after its wake and after the sleep (the only skill evaluated between the two), every learned skill's success at
    the end of the previous stage and of this one (wake and sleep together: older skills are not evaluated after the
    wake), each memory's loss at the sleep's first and last iteration (frozen-critic memories: the negated critic
    value; ``expert_memory: instead``: the distillation loss), the Nash weights at the end, and the stop."""
    matrix = results["success_matrix"]
    out = []
    for stage in results["stages"]:
        sleep = stage.get("sleep")
        if not sleep:
            continue
        k = int(stage["stage"])
        out.append({"stage": k, "skill": stage["skill"],
                    "newest_after_wake": results["success_after_own_wake"][k],
                    "newest_after_sleep": matrix[k][k],
                    "success_before_stage": [matrix[k - 1][j] for j in range(k)] if k else [],
                    "success_after_stage": [matrix[k][j] for j in range(k + 1)],
                    "memory_skills": list(sleep["skills"]),
                    "initial_memory_losses": list(sleep.get("initial_memory_losses") or []),
                    "final_memory_losses": list(sleep.get("final_memory_losses") or []),
                    "final_alpha": list(sleep.get("final_alpha") or []),
                    "stop_iteration": sleep["stop_iteration"], "stop_reason": sleep["stop_reason"]})
    return out


def row_of(variant: str, seed: int, results: Mapping[str, Any]) -> dict[str, Any]:
    """One run's line of the table, with its sleeps (:func:`sleeps_of`)."""
    metrics = results["metrics"]
    sleeps = sleeps_of(results)
    return {"variant": variant, "seed": seed, "final_afsr": metrics["afsr"]["final"],
            "bwt": metrics["bwt"]["final"], "bwt_wake": metrics["bwt_wake"]["final"],
            "success_after_own_wake": list(results["success_after_own_wake"]),
            "final_success": list(results["success_matrix"][-1]),
            "sleep_stops": [[s["stop_iteration"], s["stop_reason"]] for s in sleeps], "sleeps": sleeps,
            "commit": results["code"]["commit"], "machine": results.get("machine")}


def rule_b(means: Mapping[str, float], calibration_mean: float) -> dict[str, Any]:
    """The protocol's rule B: V is the variant with the highest mean final AFSR if that mean exceeds the calibration
    SR runs' mean by at least :data:`MARGIN`; otherwise no variant (and no confirmatory run). The protocol names no
    order for two exactly equal means; our choice, written in RESULTS' record (2026-11-30 02:37 UTC) before any
    step-B result: the earlier in ``means``' order wins (``sr_b1`` before ``sr_c_b1``: one change from SR, not two)."""
    if not means:
        return {"variant": None, "reason": "no variant"}
    best = max(means.values())
    tied = [v for v, m in means.items() if m == best]
    pick, gain = tied[0], best - calibration_mean
    tie = f" ({' and '.join(tied)} tie: the earlier in the order wins)" if len(tied) > 1 else ""
    if gain >= MARGIN:
        return {"variant": pick, "gain": gain,
                "reason": f"{pick} {best:.3f} >= calibration SR {calibration_mean:.3f} + {MARGIN}{tie}"}
    return {"variant": None, "best": pick, "gain": gain,
            "reason": f"no variant exceeds the calibration SR runs by {MARGIN} (best {pick}: {gain:+.3f})"}


def summarize(rows: Sequence[Mapping[str, Any]], calibration: Sequence[Mapping[str, Any]], variants: Sequence[str],
              seeds: Sequence[int], decide_on_any_seeds: bool = False) -> dict[str, Any]:
    """Per variant the mean +- SE over its seeds and the paired difference to the calibration runs; rule B only when
    complete and on the protocol's seeds (unless ``decide_on_any_seeds``)."""
    by = {(r["variant"], r["seed"]): r for r in rows}
    base = {r["seed"]: r for r in calibration}
    per: dict[str, Any] = {}
    for v in variants:
        done = [s for s in seeds if (v, s) in by]
        if done:
            per[v] = {"seeds": done, **mean_se([by[(v, s)]["final_afsr"] for s in done]),
                      "minus_calibration": mean_se([by[(v, s)]["final_afsr"] - base[s]["final_afsr"] for s in done])}
    cal = mean_se([base[s]["final_afsr"] for s in seeds])
    missing = [f"{v}_seed{s}" for v in variants for s in seeds if (v, s) not in by]
    if missing:
        decision = {"variant": None, "reason": f"incomplete: rule B waits for {', '.join(missing)}"}
    elif tuple(sorted(seeds)) != PROTOCOL_SEEDS and not decide_on_any_seeds:
        decision = {"variant": None, "reason": f"rule B decides on seeds {list(PROTOCOL_SEEDS)} together; these "
                                               f"are {list(seeds)}"}
    else:
        decision = rule_b({v: e["mean"] for v, e in per.items()}, cal["mean"])
    return {"seeds": list(seeds), "calibration": {**cal, "rows": list(calibration)}, "variants": per,
            "missing": missing, "rule_b": decision, "rows": list(rows),
            "commits": sorted({r["commit"] for r in rows}),
            "cpus": sorted({(r.get("machine") or {}).get("cpu", "not recorded") for r in rows})}


def _skills(values: Sequence[float]) -> str:
    return " / ".join(f"{x:.2f}" for x in values)


def render(summary: Mapping[str, Any]) -> str:
    """``step_b.md``."""
    cal = summary["calibration"]
    lines = ["# Issue 59, step B: full runs on the calibration seeds (exploratory)", "",
             f"Seeds {summary['seeds']}. Calibration SR (`sr`): {cal['mean']:.3f} +- {se_text(cal['se'])}.", "",
             "| variant | flags | mean final AFSR +- SE | minus calibration SR +- SE (paired) | seeds |",
             "|---|---|---|---|---|"]
    for v, e in summary["variants"].items():
        d = e["minus_calibration"]
        lines.append(f"| {v} | `{' '.join(VARIANTS[v])}` | {e['mean']:.3f} +- {se_text(e['se'])} | "
                     f"{d['mean']:+.3f} +- {se_text(d['se'])} | {e['seeds']} |")
    decision = summary["rule_b"]
    one = "every step-B run" if len(summary["commits"]) == 1 else "NOT one commit: the runs are not comparable as made"
    lines += ["", f"Code of the step-B runs: {', '.join(c[:7] for c in summary['commits'])} ({one}); CPU: "
                  f"{'; '.join(summary['cpus'])}."]
    lines += ["", f"Rule B: {decision['reason']}" + (f" -> **V = {decision['variant']}**" if decision.get("variant")
                                                     else ""), "",
              "| run | seed | final AFSR | BWT / BWT_wake | success after own wake | final success | sleeps stop at "
              "| commit | CPU |", "|---|---|---|---|---|---|---|---|---|"]
    for r in [*[{**c, "variant": "sr (calibration)"} for c in cal["rows"]],
              *sorted(summary["rows"], key=lambda r: (r["variant"], r["seed"]))]:
        stops = ", ".join(f"{i} ({why})" for i, why in r["sleep_stops"])
        cpu = (r.get("machine") or {}).get("cpu", "not recorded")
        lines.append(f"| {r['variant']} | {r['seed']} | {r['final_afsr']:.3f} | {r['bwt']:+.3f} / "
                     f"{r['bwt_wake']:+.3f} | {_skills(r['success_after_own_wake'])} | {_skills(r['final_success'])} "
                     f"| {stops} | {r['commit'][:7]} | {cpu} |")
    lines += ["", "Each sleep (newest skill: success after its wake -> after the sleep; the skills before it: at the "
                  "end of the previous stage -> of this one, the wake and the sleep together, since they are not "
                  "evaluated after the wake; each memory's loss at the sleep's first -> last iteration: the negated "
                  "frozen-critic value, or the distillation loss under `expert_memory: instead`):", "",
              "| run | seed | stage | newest skill | earlier skills | memory losses | Nash weights | stop |",
              "|---|---|---|---|---|---|---|---|"]
    for r in [*[{**c, "variant": "sr (calibration)"} for c in cal["rows"]],
              *sorted(summary["rows"], key=lambda r: (r["variant"], r["seed"]))]:
        for s in r["sleeps"]:
            pairs = zip(s["success_before_stage"], s["success_after_stage"][:-1], strict=True)
            earlier = ", ".join(f"{a:.2f} -> {b:.2f}" for a, b in pairs) or "none"
            lines.append(f"| {r['variant']} | {r['seed']} | {s['stage'] + 1} ({s['skill']}) | "
                         f"{s['newest_after_wake']:.2f} -> {s['newest_after_sleep']:.2f} | {earlier} | "
                         f"{losses_text(s['initial_memory_losses'], s['final_memory_losses'])} | "
                         f"{weights_text(s['final_alpha'])} | {s['stop_iteration']} ({s['stop_reason']}) |")
    if summary["missing"]:
        lines += ["", f"Not archived yet: {', '.join(summary['missing'])}."]
    return "\n".join(lines) + "\n"


def plot(summary: Mapping[str, Any], path: Path) -> None:
    """One column per arm (calibration SR, then each variant): each seed's final AFSR as a dot, joined across arms
    by seed (the pairing), the mean as a bar; the dashed line is rule B's bar (calibration mean + margin)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cal = summary["calibration"]
    arms = {"sr (calibration)": {r["seed"]: r["final_afsr"] for r in cal["rows"]}}
    for v in summary["variants"]:
        arms[v] = {r["seed"]: r["final_afsr"] for r in summary["rows"] if r["variant"] == v}
    fig, ax = plt.subplots(figsize=(1.6 + 1.4 * len(arms), 3.6))
    names = list(arms)
    for i, name in enumerate(names):
        values = list(arms[name].values())
        ax.bar(i, sum(values) / len(values), color="#c9d9ec", width=0.6)
    for seed in summary["seeds"]:
        xs = [i for i, n in enumerate(names) if seed in arms[n]]
        ax.plot(xs, [arms[names[i]][seed] for i in xs], marker="o", ms=4, lw=0.8, label=f"seed {seed}")
    ax.axhline(cal["mean"] + MARGIN, color="k", ls="--", lw=0.8, label=f"calibration mean + {MARGIN}")
    ax.set_xticks(range(len(names)), names, fontsize=8)
    ax.set_ylim(0, 1.02)
    ax.set_ylabel("final AFSR")
    ax.set_title("step B (calibration seeds, exploratory)", fontsize=9)
    ax.legend(fontsize=7, frameon=False, loc="lower right")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


def read_runs(cfg: StepBConfig) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """``(rows, calibration)``: every archived step-B run of ``cfg``, each checked (:func:`check_run`), and the
    calibration SR runs, as table rows. A missing step-B run is left out (reported); a missing calibration run is an
    error."""
    calibration, rows = [], []
    for seed in cfg.seeds:
        cal = read_checked_json(cfg.calibration / f"sr_seed{seed}" / "results.json")
        calibration.append(row_of("sr", seed, cal))
        for v in cfg.variants:
            path = cfg.archive / f"{v}_seed{seed}" / "results.json"
            if path.is_file():
                results = read_checked_json(path)
                check_run(path, results, cal, v, seed)
                rows.append(row_of(v, seed, results))
    return rows, calibration


def run_step_b(cfg: StepBConfig) -> dict[str, Any]:
    """Read and check every archived run (:func:`read_runs`), then write the table, the figure and the decision."""
    summary = summarize(*read_runs(cfg), cfg.variants, cfg.seeds, cfg.decide_on_any_seeds)
    target = cfg.output or cfg.archive
    write_checked_json(target / "step_b.json", summary)
    atomic_write_bytes(target / "step_b.md", render(summary).encode())
    plot(summary, target / "step_b.png")
    logger.info("rule B: %s", summary["rule_b"]["reason"])
    return summary


def main(args: list[str] | None = None) -> None:
    setup_logging()
    run_step_b(parse_command(StepBConfig, list(sys.argv[1:] if args is None else args), prog=PROG))


if __name__ == "__main__":
    run_cli(PROG, main)
