"""Did a stream's ranking hold in another order: the descriptive part of the stream-order protocol (exploratory).

    python -m experiments.stream_orders \\
        '--orders=[needle/forward=docs/results/lerobot06_needle_m16+docs/results/order_needle_m16_forward,
                   needle/reverse=docs/results/order_needle_m16_reverse]' --output=docs/results/stream_orders

Each ``<stream>/<order>=<archive>[+<archive>...]`` names the archives whose finished runs (``<variant>_seed<S>/``,
read and checked by :func:`sr_imitation.reporting.results.load_results`) make that stream in that order. Per stream:
every method's final AFSR (mean +- SE over its seeds) in each order and its rank there; whether the ranking held (the
methods present in both orders sorted alike by mean); the interaction (SR - wake-only in one order) - (SR - wake-only
in the first order named), paired by training seed; SR - sr_no_anchor per order, paired by seed (the anchor's
share); and per order what the SR runs' final sleep did (:mod:`sr_imitation.reporting.last_sleep`): the newest skill's
change, the older skills' mean change with the anchor and, where re-slept, without it. Descriptive only: the
protocol's tests (O1-O3) are :mod:`sr_imitation.experiments.hypotheses`'.
Written: ``orders.json`` (checked), ``orders.md`` and ``orders.png`` in ``--output``.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sr_imitation.core.metrics import mean_sem
from sr_imitation.experiments.hypotheses import archived_values
from sr_imitation.infra.cli_errors import run_cli, setup_logging
from sr_imitation.infra.cli_parsing import parse_command
from sr_imitation.io import atomic_write_bytes, write_checked_json
from sr_imitation.reporting.last_sleep import anchor_off_row, last_sleep_row
from sr_imitation.reporting.results import save_figure

logger = logging.getLogger(__name__)
PROG = "python -m experiments.stream_orders"
_ORDER = re.compile(r"^([\w-]+)/([\w-]+)=(.+)$")
METHODS = ("sr", "sr_no_anchor", "replay", "wake_only")
"""The variants looked for in every archive (those with no finished run are left out)."""


@dataclass
class OrdersConfig:
    orders: list[str] = field(default_factory=list)
    """``<stream>/<order>=<archive>[+<archive>...]``: the first order named for a stream is its reference (forward)."""
    output: Path | None = None
    """Where orders.json / .md / .png go (none: print only)."""

    def __post_init__(self) -> None:
        if not self.orders:
            raise ValueError("orders: give at least one <stream>/<order>=<archive>")
        for entry in self.orders:
            m = _ORDER.match(entry)
            if m is None:
                raise ValueError(f"orders: {entry!r} is not <stream>/<order>=<archive>[+<archive>...]")
            for archive in m.group(3).split("+"):
                if not Path(archive).is_dir():
                    raise FileNotFoundError(f"orders: {entry!r}: {archive} is not a folder")


def parse_orders(entries: Sequence[str]) -> dict[str, dict[str, list[Path]]]:
    """``{stream: {order: [archives]}}``, streams and orders in the order given."""
    out: dict[str, dict[str, list[Path]]] = {}
    for entry in entries:
        stream, order, archives = _ORDER.match(entry).groups()  # type: ignore[union-attr]
        if order in out.setdefault(stream, {}):
            raise ValueError(f"orders: {stream}/{order} is named twice")
        out[stream][order] = [Path(a) for a in archives.split("+")]
    return out


def order_values(archives: Sequence[Path]) -> dict[str, dict[int, float]]:
    """``{method: {training seed: final AFSR}}`` over ``archives`` (a seed archived twice for one method is refused)."""
    values: dict[str, dict[int, float]] = {}
    for archive in archives:
        for method in METHODS:
            for seed, value in archived_values(archive, method, "afsr").items():
                if seed in values.setdefault(method, {}):
                    raise ValueError(f"{method} seed {seed} is archived twice ({archive} and another)")
                values[method][seed] = value
    return {m: v for m, v in values.items() if v}


def paired(a: Mapping[int, float], b: Mapping[int, float]) -> dict[str, Any] | None:
    """Mean +- SE of a - b over the seeds both have (``None`` when none)."""
    seeds = sorted(set(a) & set(b))
    if not seeds:
        return None
    diffs = [a[s] - b[s] for s in seeds]
    mean, sem = mean_sem(diffs)
    return {"seeds": seeds, "diffs": diffs, "mean": mean, "sem": sem}


def interaction(ref: Mapping[str, Mapping[int, float]], new: Mapping[str, Mapping[int, float]],
                a: str = "sr", b: str = "wake_only") -> dict[str, Any] | None:
    """(a - b in ``new``) - (a - b in ``ref``), paired by training seed (seeds with all four runs)."""
    if not all(m in d for d in (ref, new) for m in (a, b)):
        return None
    seeds = sorted(set(ref[a]) & set(ref[b]) & set(new[a]) & set(new[b]))
    if not seeds:
        return None
    diffs = [(new[a][s] - new[b][s]) - (ref[a][s] - ref[b][s]) for s in seeds]
    mean, sem = mean_sem(diffs)
    return {"seeds": seeds, "diffs": diffs, "mean": mean, "sem": sem}


def last_sleep(archives: Sequence[Path]) -> dict[str, Any] | None:
    """What the final sleep of every archived SR run did (``None`` when the order has no SR run): per seed the newest
    skill's and the older skills' mean change across it, and the same for the anchor-off re-sleeps beside the runs."""
    runs = {seed: Path(archive) / f"sr_seed{seed}" for archive in archives
            for seed in archived_values(archive, "sr", "afsr")}
    if not runs:
        return None
    rows = {seed: last_sleep_row(run) for seed, run in sorted(runs.items())}
    off = {seed: row for seed, run in sorted(runs.items()) if (row := anchor_off_row(run)) is not None}

    def stat(table: Mapping[int, Mapping[str, Any]], key: str) -> dict[str, Any] | None:
        return paired({s: r[key] for s, r in table.items()}, dict.fromkeys(table, 0.0))

    return {"newest": rows[min(rows)]["newest"], "newest_change": stat(rows, "newest_change"),
            "older_change": stat(rows, "older_mean_change"), "newest_change_anchor_off": stat(off, "newest_change"),
            "older_change_anchor_off": stat(off, "older_mean_change"),
            "older_with_minus_without": paired({s: rows[s]["older_mean_change"] for s in off},
                                               {s: r["older_mean_change"] for s, r in off.items()})}


def ranking(values: Mapping[str, Mapping[int, float]]) -> list[str]:
    """Methods by mean final AFSR, best first (ties kept in :data:`METHODS` order)."""
    means = {m: sum(v.values()) / len(v) for m, v in values.items()}
    return sorted(means, key=lambda m: (-means[m], METHODS.index(m)))


def summarize_stream(orders: Mapping[str, Mapping[str, Mapping[int, float]]],
                     sleeps: Mapping[str, dict[str, Any] | None] | None = None) -> dict[str, Any]:
    """One stream's table: per order every method's mean +- SE and rank, whether the ranking held against the first
    order, the interaction against the first order, SR - sr_no_anchor per order and (``sleeps``, by order) what the
    last sleep did."""
    names = list(orders)
    ref = orders[names[0]]
    out: dict[str, Any] = {"reference": names[0], "orders": {}}
    for name in names:
        vals = orders[name]
        order_rank = ranking(vals)
        methods = {}
        for m in order_rank:
            mean, sem = mean_sem(list(vals[m].values()))
            methods[m] = {"seeds": sorted(vals[m]), "values": [vals[m][s] for s in sorted(vals[m])], "mean": mean,
                          "sem": sem, "rank": order_rank.index(m) + 1}
        common = [m for m in ranking(ref) if m in vals]
        entry = {"methods": methods, "ranking": order_rank,
                 "anchor": paired(vals.get("sr", {}), vals.get("sr_no_anchor", {})),
                 "last_sleep": (sleeps or {}).get(name)}
        if name != names[0]:
            entry["ranking_held"] = [m for m in order_rank if m in common] == common
            entry["ranking_compared"] = common
            entry["interaction_sr_wake_only"] = interaction(ref, vals)
        out["orders"][name] = entry
    return out


def _pm(x: Mapping[str, Any] | None) -> str:
    return "-" if x is None else f"{x['mean']:+.3f} +- {x['sem']:.3f} (n={len(x['seeds'])})"


def render(summary: Mapping[str, Mapping[str, Any]]) -> str:
    lines = ["Exploratory (descriptive part of the stream-order protocol; its tests are hypotheses.md's).", ""]
    for stream, s in summary.items():
        orders = list(s["orders"])
        lines += [f"## {stream}", "", "| method | " + " | ".join(f"{o}: final AFSR (rank)" for o in orders) + " |",
                  "|---|" + "---|" * len(orders)]
        methods = [m for m in METHODS if any(m in s["orders"][o]["methods"] for o in orders)]
        for m in methods:
            cells = []
            for o in orders:
                r = s["orders"][o]["methods"].get(m)
                cells.append("-" if r is None else f"{r['mean']:.3f} +- {r['sem']:.3f} (n={len(r['seeds'])}; "
                             f"#{r['rank']})")
            lines.append(f"| {m} | " + " | ".join(cells) + " |")
        lines.append("")
        for o in orders:
            e = s["orders"][o]
            anchor = "not run" if e["anchor"] is None else _pm(e["anchor"])
            lines.append(f"- {o}: ranking {' > '.join(e['ranking'])}; SR - sr_no_anchor {anchor}")
            if e.get("last_sleep"):
                ls = e["last_sleep"]
                lines.append(f"  - the last sleep of its SR runs: the newest skill ({ls['newest']}) "
                             f"{_pm(ls['newest_change'])}, the older skills {_pm(ls['older_change'])}; re-slept with "
                             f"the anchor off: newest {_pm(ls['newest_change_anchor_off'])}, older "
                             f"{_pm(ls['older_change_anchor_off'])}; older with - without the anchor "
                             f"{_pm(ls['older_with_minus_without'])}")
            if o != s["reference"]:
                held = "held" if e["ranking_held"] else "changed"
                lines.append(f"  - against {s['reference']}: the ranking of {', '.join(e['ranking_compared'])} "
                             f"{held}; (SR - wake-only here) - (SR - wake-only in {s['reference']}) "
                             f"{_pm(e['interaction_sr_wake_only'])}")
        lines.append("")
    return "\n".join(lines)


def plot(summary: Mapping[str, Mapping[str, Any]], path: Path) -> None:
    """Per stream, each method's final AFSR per order: every seed a dot, the mean a bar."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(summary), figsize=(5.5 * len(summary), 3.6), squeeze=False)
    for ax, (stream, s) in zip(axes[0], summary.items(), strict=True):
        orders = list(s["orders"])
        methods = [m for m in METHODS if any(m in s["orders"][o]["methods"] for o in orders)]
        width = 0.8 / len(orders)
        for j, o in enumerate(orders):
            for i, m in enumerate(methods):
                r = s["orders"][o]["methods"].get(m)
                if r is None:
                    continue
                x = i + (j - (len(orders) - 1) / 2) * width
                ax.bar(x, r["mean"], width * 0.9, color=f"C{j}", alpha=0.5, label=o if i == 0 else None)
                ax.scatter([x] * len(r["values"]), r["values"], s=10, color=f"C{j}", zorder=3)
        ax.set_xticks(range(len(methods)), methods)
        ax.set_ylim(0, 1.05)
        ax.set_ylabel("final AFSR")
        ax.set_title(stream)
        ax.legend(fontsize=8)
    save_figure(fig, path)


def run_orders(cfg: OrdersConfig) -> dict[str, Any]:
    streams = parse_orders(cfg.orders)
    return {stream: summarize_stream({o: order_values(a) for o, a in orders.items()},
                                     {o: last_sleep(a) for o, a in orders.items()})
            for stream, orders in streams.items()}


def main(args: list[str] | None = None) -> None:
    setup_logging()
    cfg = parse_command(OrdersConfig, args, prog=PROG)
    summary = run_orders(cfg)
    text = render(summary)
    if cfg.output is not None:
        write_checked_json(cfg.output / "orders.json", {"orders": cfg.orders, "streams": summary})
        atomic_write_bytes(cfg.output / "orders.md", text.encode())
        plot(summary, cfg.output / "orders.png")
    print(text)  # noqa: T201 (command output)


if __name__ == "__main__":
    run_cli(PROG, main)
