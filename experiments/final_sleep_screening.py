"""Issue 89 item 4: the final-sleep screening (docs/RESULTS.md, "a final sleep that keeps the newest skill") read
from its archives, and its decision rule applied as written (exploratory: calibration seeds only).

    python -m experiments.final_sleep_screening --trigger_order=reverse \\
        '--orders=[forward=docs/results/order_mt5_screening_forward,
                   reverse=docs/results/order_mt5_screening_reverse]' \\
        --output=docs/results/order_mt5_screening

Every archived SR run ``sr_seed<S>/`` of each order is C0 (its own final sleep, as the run recorded it:
:func:`~sr_imitation.reporting.last_sleep.last_sleep_row`); each candidate is the re-sleep kept beside it as
``sr_seed<S>_final_sleep_<candidate>/`` (``tools/experiments/resleep_archived.sh --candidate=...``; C1 ``anchor_off``,
C2 ``anchor_newest``, C3 ``guard``; ``own``, the run's sleep repeated by ``sr-sleep``, is reported beside C0 as a
check and never a candidate). Per order, candidate and seed: the final AFSR after the final stage (mean success over
the stream's skills), the newest skill's change across that sleep and the older skills' mean change. Then
:func:`decide`: the protocol's rule. Written: ``screening.json`` (checked), ``screening.md``, ``screening.png``.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sr_imitation.core.metrics import mean_sem
from sr_imitation.infra.cli_errors import run_cli, setup_logging
from sr_imitation.infra.cli_parsing import parse_command
from sr_imitation.io import atomic_write_bytes, read_checked_json, write_checked_json
from sr_imitation.reporting.last_sleep import last_sleep_row, resleep_row
from sr_imitation.reporting.results import load_results, save_figure

PROG = "python -m experiments.final_sleep_screening"
CANDIDATES = ("anchor_off", "anchor_newest", "guard")
"""C1-C3 in the protocol's tie order (the simplest first)."""
CHECK = "own"
"""The run's own sleep repeated by ``sr-sleep``: how far a re-sleep reproduces C0 (not a candidate)."""
GAIN, NEWEST_FLOOR, OTHER_LOSS = 0.03, -0.10, 0.03
"""The rule's thresholds: (i) the mean gain over C0 in the trigger's order, (ii) the newest skill's mean change there
must be above this, (iii) the most the other order's mean may fall below C0's."""
_EPS = 1e-9  # success values are multiples of 1/(episodes x seeds): no threshold is met exactly, this only absorbs
#              float rounding
_SEED = re.compile(r"^sr_seed(\d+)$")


@dataclass
class ScreeningConfig:
    orders: list[str] = field(default_factory=list)
    """``<order>=<archive>``, two of them: the archives of the screening's SR runs in each order."""
    trigger_order: str = ""
    """The order where the trigger fired (one of the orders' names): rules (i) and (ii) are read there."""
    output: Path | None = None
    """Where screening.json / .md / .png go (none: print only)."""
    seeds: list[int] = field(default_factory=lambda: [100, 101, 102])
    """The protocol's calibration seeds: the rule names a winner only when every one has its run and every
    candidate's re-sleep in both orders."""

    def __post_init__(self) -> None:
        names = []
        for entry in self.orders:
            name, sep, archive = entry.partition("=")
            if not sep or not name or not Path(archive).is_dir():
                raise ValueError(f"orders: {entry!r} is not <order>=<archive folder>")
            names.append(name)
        if len(names) != 2 or len(set(names)) != 2:
            raise ValueError(f"orders: give two orders, each once (got {names})")
        if self.trigger_order not in names:
            raise ValueError(f"trigger_order: {self.trigger_order!r} is not one of the orders {names}")


def _run_success(run: Path) -> tuple[list[str], list[float], list[float]]:
    """C0: the run's skills, each one's success right after the last wake and after the final sleep."""
    last_sleep_row(run)  # refuses, naming the run, one without a final sleep or not evaluated on every skill
    results = load_results(run)
    return list(results["skills"]), results["extra"]["success_matrix_after_wake"][-1], results["success_matrix"][-1]


def _resleep_success(folder: Path) -> tuple[list[str], list[float], list[float]]:
    """A re-sleep: the skills, each one's success before and after the sleep (``sr-sleep``'s evaluation)."""
    resleep_row(folder)  # refuses, naming the folder, a re-sleep not evaluated on every skill
    record = read_checked_json(folder / "sleep.json")
    skills = list(record["sleep"]["skills"])
    return skills, [record["success"][s]["before"] for s in skills], [record["success"][s]["after"] for s in skills]


def _measures(woke: Sequence[float], slept: Sequence[float]) -> dict[str, float]:
    """Final AFSR after the final stage, the newest skill's change across the sleep, the older skills' mean change."""
    older = [a - b for a, b in zip(slept[:-1], woke[:-1], strict=True)]
    return {"afsr": sum(slept) / len(slept), "newest_change": slept[-1] - woke[-1],
            "older_change": sum(older) / len(older)}


def order_rows(archive: Path) -> dict[str, dict[int, dict[str, float]]]:
    """Per candidate (``C0``, each of :data:`CANDIDATES` and :data:`CHECK` where present) and seed, the measures.

    Raises:
        ValueError: naming the folder, if a re-sleep does not start from its run's last wake (its success before the
            sleep differs from the run's after the last wake: another run, or another evaluation).
    """
    out: dict[str, dict[int, dict[str, float]]] = {}
    for run in sorted(p for p in Path(archive).iterdir() if _SEED.match(p.name)):
        seed = int(_SEED.match(run.name).group(1))
        skills, woke, slept = _run_success(run)
        out.setdefault("C0", {})[seed] = _measures(woke, slept)
        for candidate in (*CANDIDATES, CHECK):
            folder = run.with_name(f"{run.name}_final_sleep_{candidate}")
            if not (folder / "sleep.json").is_file():
                continue
            re_skills, before, after = _resleep_success(folder)
            if re_skills != skills or max(abs(a - b) for a, b in zip(before, woke, strict=True)) > _EPS:
                raise ValueError(f"{folder}: its success before the sleep is not {run.name}'s after the last wake")
            out.setdefault(candidate, {})[seed] = _measures(before, after)
    if "C0" not in out:
        raise ValueError(f"{archive}: no SR run (sr_seed<S>/) in it")
    return out


def decide(orders: Mapping[str, Mapping[str, Mapping[int, Mapping[str, float]]]], trigger: str,
           seeds: Sequence[int] = ()) -> dict[str, Any]:
    """The protocol's decision rule over the seeds each candidate shares with C0 in both orders.

    Args:
        orders: per order, :func:`order_rows`' result.
        trigger: the order where the trigger fired.
        seeds: the seeds the rule reads (beside every C0 seed of either order).

    Returns:
        Per candidate its means, differences to C0, seeds above C0 in the trigger's order, rules (i)-(iii) and
        ``passes``; ``winner`` (the passing candidate with the highest mean in the trigger's order, ties to the
        earlier in :data:`CANDIDATES`; ``None`` when none passes, or while ``missing`` names a run or re-sleep the
        rule still needs).
    """
    (other,) = [o for o in orders if o != trigger]
    verdicts: dict[str, Any] = {}
    for c in CANDIDATES:
        if not all(c in orders[o] for o in orders):
            continue
        per = {}
        for o in orders:
            shared = sorted(set(orders[o][c]) & set(orders[o]["C0"]))
            diffs = [orders[o][c][s]["afsr"] - orders[o]["C0"][s]["afsr"] for s in shared]
            per[o] = {"seeds": shared, "mean": sum(orders[o][c][s]["afsr"] for s in shared) / len(shared),
                      "c0_mean": sum(orders[o]["C0"][s]["afsr"] for s in shared) / len(shared),
                      "diff": sum(diffs) / len(diffs), "seeds_above": sum(d > _EPS for d in diffs),
                      "newest_change": sum(orders[o][c][s]["newest_change"] for s in shared) / len(shared)}
        t, u = per[trigger], per[other]
        rules = {"i": t["diff"] >= GAIN - _EPS and t["seeds_above"] >= 2,
                 "ii": t["newest_change"] > NEWEST_FLOOR + _EPS,
                 "iii": u["diff"] >= -OTHER_LOSS - _EPS}
        verdicts[c] = {"orders": per, "rules": rules, "passes": all(rules.values())}
    missing = _missing(orders, seeds)
    passing = [c for c in CANDIDATES if verdicts.get(c, {}).get("passes")] if not missing else []
    winner = max(passing, key=lambda c: (verdicts[c]["orders"][trigger]["mean"], -CANDIDATES.index(c)), default=None)
    repeats = {o: {s: orders[o][CHECK][s] == orders[o]["C0"][s] for s in sorted(orders[o].get(CHECK, {}))}
               for o in orders}
    return {"trigger_order": trigger, "candidates": verdicts, "winner": winner, "own_repeats_c0": repeats,
            "missing": missing}


def _missing(orders: Mapping[str, Mapping[str, Mapping[int, Any]]], seeds: Sequence[int]) -> list[str]:
    """What the rule still lacks: C0 and every candidate in each order on every seed of ``seeds`` and of either
    order's C0 (the rule reads means over the protocol's seeds; a partial screening names no winner)."""
    every = sorted(set(seeds).union(*(rows["C0"] for rows in orders.values())))
    return [f"{o} {c} seed {s}" for o, rows in orders.items() for c in ("C0", *CANDIDATES) for s in every
            if s not in rows.get(c, {})]


def _pm(values: Sequence[float]) -> str:
    mean, sem = mean_sem(values)
    return f"{mean:.3f}" if len(values) < 2 else f"{mean:.3f} +- {sem:.3f}"


def render(orders: Mapping[str, Mapping[str, Mapping[int, Mapping[str, float]]]], decision: Mapping[str, Any]) -> str:
    """The per-seed table, each candidate's means, the rule's verdict."""
    lines = ["# Final-sleep screening (exploratory; calibration seeds)", "",
             "| order | sleep | seeds | final AFSR (mean +- SE) | per seed | newest skill's change "
             "| older skills' change |",
             "|---|---|---|---|---|---|---|"]
    for o, rows in orders.items():
        for c in ("C0", *CANDIDATES, CHECK):
            if c not in rows:
                continue
            seeds = sorted(rows[c])
            lines.append(f"| {o} | {c} | {','.join(map(str, seeds))} | {_pm([rows[c][s]['afsr'] for s in seeds])} | "
                         + " ".join(f"{rows[c][s]['afsr']:.3f}" for s in seeds)
                         + f" | {_pm([rows[c][s]['newest_change'] for s in seeds])} | "
                           f"{_pm([rows[c][s]['older_change'] for s in seeds])} |")
    lines += ["", f"Decision rule (trigger's order: {decision['trigger_order']}): (i) mean final AFSR above C0's by "
                  f">= {GAIN} there and above it on >= 2 seeds; (ii) the newest skill's mean change there > "
                  f"{NEWEST_FLOOR}; (iii) in the other order not below C0 by more than {OTHER_LOSS}.", ""]
    for c, v in decision["candidates"].items():
        diffs = ", ".join(f"{o} {p['diff']:+.3f} ({p['seeds_above']}/{len(p['seeds'])} seeds above)"
                          for o, p in v["orders"].items())
        rules = ", ".join(f"({k}) {'yes' if ok else 'no'}" for k, ok in v["rules"].items())
        lines.append(f"- {c}: minus C0 {diffs}; {rules}: {'passes' if v['passes'] else 'does not pass'}.")
    for o, seeds in decision["own_repeats_c0"].items():
        if seeds:
            same = [s for s, ok in seeds.items() if ok]
            lines.append(f"- {o}: sr-sleep repeating the run's own final sleep ({CHECK}) gives C0's measures "
                         f"exactly on {len(same)} of {len(seeds)} seeds ({', '.join(map(str, seeds))}).")
    if decision["missing"]:
        lines += ["", f"Not read: the screening is incomplete (missing: {', '.join(decision['missing'])}); "
                      "the rule names a winner only over every seed of both orders."]
    else:
        lines += ["", f"Winner: {decision['winner']}." if decision["winner"] else
                  "No candidate passes: the final sleep's cost to the newest skill stands."]
    return "\n".join(lines) + "\n"


def plot(orders: Mapping[str, Mapping[str, Mapping[int, Mapping[str, float]]]], path: Path) -> None:
    """Per order, each candidate's final AFSR minus C0's, a point per seed and a bar at the mean."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(orders), figsize=(4 * len(orders), 3.4), sharey=True, squeeze=False)
    for ax, (o, rows) in zip(axes[0], orders.items(), strict=True):
        ax.axhline(0, color="grey", lw=0.8)
        for x, c in enumerate(CANDIDATES):
            seeds = sorted(set(rows.get(c, {})) & set(rows["C0"]))
            diffs = [rows[c][s]["afsr"] - rows["C0"][s]["afsr"] for s in seeds]
            if diffs:
                ax.bar(x, sum(diffs) / len(diffs), width=0.6, alpha=0.35, color="tab:blue")
                ax.plot([x] * len(diffs), diffs, "o", color="black", ms=4)
        ax.axhline(GAIN, color="tab:green", lw=0.8, ls="--")
        ax.set_xticks(range(len(CANDIDATES)), ["C1 anchor off", "C2 newest", "C3 guard"], fontsize=8)
        ax.set_title(o, fontsize=10)
    axes[0][0].set_ylabel("final AFSR minus C0's (run's own sleep)")
    save_figure(fig, path)


def run_screening(cfg: ScreeningConfig) -> tuple[dict[str, Any], dict[str, Any]]:
    orders = {e.partition("=")[0]: order_rows(Path(e.partition("=")[2])) for e in cfg.orders}
    return orders, decide(orders, cfg.trigger_order, cfg.seeds)


def main(args: list[str] | None = None) -> None:
    setup_logging()
    cfg = parse_command(ScreeningConfig, args, prog=PROG)
    orders, decision = run_screening(cfg)
    text = render(orders, decision)
    if cfg.output is not None:
        rows = {o: {c: {str(s): m for s, m in r.items()} for c, r in rows.items()} for o, rows in orders.items()}
        write_checked_json(cfg.output / "screening.json", {"orders": cfg.orders, "rows": rows, "decision": decision})
        atomic_write_bytes(cfg.output / "screening.md", text.encode())
        plot(orders, cfg.output / "screening.png")
    print(text)  # noqa: T201 (command output)


if __name__ == "__main__":
    run_cli(PROG, main)
