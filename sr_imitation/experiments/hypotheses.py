"""The paired tests of a comparison, computed from its archived raw results (docs/RESULTS.md).

    python -m sr_imitation.experiments.hypotheses --archive=docs/results/needle_cpu_m16_compare \\
        '--tests=[sr>wake_only,sr!=replay]' --metric=afsr --output=docs/results/needle_cpu_m16_compare/hypotheses

A test ``A>B`` is the one-sided paired t-test of A - B > 0, ``A<B`` of A - B < 0, ``A!=B`` the two-sided one
(:func:`sr_imitation.reporting.stats.paired_test`, with the exact sign-flip p beside it), over the training seeds both
variants have in the archive (``<variant>_seed<S>/results.json``, read and checked by
:func:`sr_imitation.reporting.results.load_results`); ``<folder>::A>B`` reads another archive, and
``<folder>::A!=<other folder>::B`` pairs runs of two archives (one variant under two settings); ``M1=A>B`` names a
test as a protocol declares it (the name heads its row and panel), and ``A>B@0-9`` names the training seeds it is
declared on: it is then computed on exactly those, and refused, before any statistic, while one of them has no
finished run of A or B (a protocol computes no test before all of its runs are archived). Each seed's value is
the run's final metric (its mean over evaluation units), or for runs without closed-loop evaluation
(``--eval.env=none``: a real robot's datasets and no simulator) an offline one (:data:`LOSS_METRICS`: lower is
better, so the test of "sleep helps" is ``sr<wake_only``).
Written: ``hypotheses.md`` and ``hypotheses.json`` (per test: seeds, per-seed values, mean +- SE of the difference,
t, p, bootstrap 95% CI) and ``hypotheses.png`` (per test, each training seed's A and B joined by a line: the pairing
the test uses). """

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sr_imitation.infra.cli_errors import run_cli, setup_logging
from sr_imitation.infra.cli_parsing import parse_command
from sr_imitation.io import atomic_write_bytes, write_checked_json
from sr_imitation.reporting.results import LOSS_METRICS, METRICS, final_loss, load_results
from sr_imitation.reporting.stats import holm, paired_test

logger = logging.getLogger(__name__)
PROG = "python -m sr_imitation.experiments.hypotheses"
"""The command as a user types it (usage errors and ``--help`` name it)."""

_TEST = re.compile(r"^(?:(\w+)=)?(?:([^<>!=@]+)::)?([\w.]+)(>|<|!=)(?:([^<>!=@]+)::)?([\w.]+)(?:@(\d+)-(\d+))?$")
_ALTERNATIVE = {">": "greater", "<": "less", "!=": "two-sided"}
_OPERATOR = {alternative: op for op, alternative in _ALTERNATIVE.items()}


@dataclass
class HypothesesConfig:
    archive: Path = Path("docs/results/needle_cpu_m16_compare")
    """A folder of finished runs, ``<variant>_seed<S>/`` each (a comparison's archive)."""
    tests: list[str] = field(default_factory=lambda: ["sr>wake_only", "sr!=replay"])
    """Paired tests ``A>B`` (one-sided, A - B > 0), ``A<B`` or ``A!=B`` (two-sided), on ``archive``'s runs; a test
    ``<folder>::A>B`` reads another archive's runs (one family over several streams, e.g. with ``--holm``), and
    ``<folder>::A!=<other folder>::B`` pairs A's runs in one archive with B's in another (the same variant under two
    settings, paired by training seed). ``NAME=`` before a test names it as its protocol does (``M1=sr>wake_only``);
    ``@<first>-<last>`` after it gives the training seeds it is declared on (``M1=sr>wake_only@0-9``): exactly those
    are used, and the test is refused while any of them lacks a finished run."""
    metric: str = "afsr"
    """The final metric compared: afsr, prs, bwt, bwt_wake, spi (evaluated runs) or val_l1, memory_loss (runs
    without evaluation, lower is better: :data:`LOSS_METRICS`)."""
    alpha: float = 0.05
    """The significance level stated before the runs."""
    output: Path | None = None
    """Where hypotheses.md / .json / .png go (none: print only)."""
    holm: bool = False
    """Also report Holm-Bonferroni adjusted p values over the tests given (one family: give only the pre-registered
    tests in that call) and the verdict on them (family-wise error rate alpha)."""
    preregistered: bool = False
    """Label the tests "pre-registered" in hypotheses.md: only for tests whose text was committed before any run of
    their preset (docs/RESULTS.md says which); otherwise they are labelled "exploratory"."""
    note: str = ""
    """A sentence printed under the label (e.g. what was known when the tests were written)."""

    def __post_init__(self) -> None:
        bad = [t for t in self.tests if not _TEST.match(t)]
        if bad:
            raise ValueError(f"tests: {bad} are not of the form A>B, A<B or A!=B (or <folder>::A>B, "
                             "<folder>::A!=<folder>::B, each optionally named and with its seeds: M1=A>B@0-9)")
        for test in self.tests:
            _, folder, _, _, folder_b, _, first, last = _TEST.match(test).groups()  # type: ignore[union-attr]
            if first is not None and int(first) > int(last):
                raise ValueError(f"tests: {test!r}: the seed range {first}-{last} is empty")
            for where in (folder, folder_b):
                if where is not None and not Path(where).is_dir():
                    raise FileNotFoundError(f"tests: {test!r}: {where} is not a folder")
        if self.metric not in METRICS and self.metric not in LOSS_METRICS:
            raise ValueError(f"metric: {self.metric!r} is not one of {[*METRICS, *LOSS_METRICS]}")
        if not 0 < self.alpha < 1:
            raise ValueError(f"alpha must be in (0, 1), got {self.alpha}")
        if not Path(self.archive).is_dir():
            raise FileNotFoundError(f"archive: {self.archive} is not a folder")


def archived_runs(archive: Path, variant: str) -> dict[int, dict[str, Any]]:
    """``{training seed: results}`` of every finished run ``<variant>_seed<S>`` in ``archive`` (checked)."""
    out = {}
    for run in sorted(Path(archive).glob(f"{variant}_seed*")):
        suffix = run.name[len(variant) + len("_seed"):]
        if suffix.isdigit() and (run / "results.json").is_file():
            out[int(suffix)] = load_results(run)
    return out


def final_value(results: dict[str, Any], metric: str) -> float | None:
    """A run's final ``metric`` (:data:`METRICS` or :data:`LOSS_METRICS`); ``None`` where the run did not measure it
    (no evaluation for the success metrics, an evaluated run for the loss ones)."""
    if metric in METRICS:
        value = results["metrics"][metric]["final"]
        return None if value is None else float(value)
    return final_loss(results, metric)


def archived_values(archive: Path, variant: str, metric: str) -> dict[int, float]:
    """``{training seed: final metric}`` of every finished run of ``variant`` in ``archive`` that measured it."""
    runs = archived_runs(archive, variant)
    finals = {seed: final_value(r, metric) for seed, r in runs.items()}
    values = {seed: v for seed, v in finals.items() if v is not None}
    if runs and not values:
        hint = "--metric=val_l1 for runs without evaluation" if metric in METRICS else "a success metric"
        logger.warning("%s: %d finished runs in %s, none measured %s (%s)", variant, len(runs), archive, metric, hint)
    return values


def run_tests(cfg: HypothesesConfig) -> list[dict[str, Any]]:
    rows = []
    for test in cfg.tests:
        name, folder, a, op, folder_b, b, first, last = _TEST.match(test).groups()  # type: ignore[union-attr]
        archive = Path(folder) if folder is not None else Path(cfg.archive)
        archive_b = Path(folder_b) if folder_b is not None else archive  # ``<folder>::A>B``: both in that folder
        va, vb = archived_values(archive, a, cfg.metric), archived_values(archive_b, b, cfg.metric)
        for variant, values, where in ((a, va, archive), (b, vb, archive_b)):
            if not values:
                logger.warning("%s: no finished %s runs in %s (yet)", test, variant, where)
        seeds = sorted(set(va) & set(vb))
        if first is not None:  # declared seeds: exactly those, all of them archived
            declared = list(range(int(first), int(last) + 1))
            missing = [(v, [s for s in declared if s not in values], where)
                       for v, values, where in ((a, va, archive), (b, vb, archive_b))]
            if any(m for _, m, _ in missing):
                gaps = "; ".join(f"{v} seeds {m} (in {where})" for v, m, where in missing if m)
                raise ValueError(f"tests: {test!r} is declared on seeds {first}-{last}, and these have no finished "
                                 f"run yet: {gaps}; no statistic is computed before all of a test's runs are archived")
            seeds = declared
        result = paired_test([va[s] for s in seeds], [vb[s] for s in seeds], _ALTERNATIVE[op])
        where = str(archive) if archive_b == archive else f"{archive} vs {archive_b}"
        rows.append({"test": test, "name": name, "archive": where, "archive_a": str(archive),
                     "archive_b": str(archive_b), "a": a, "b": b, "metric": cfg.metric, "seeds": seeds,
                     "a_values": [va[s] for s in seeds], "b_values": [vb[s] for s in seeds], **result.to_dict(),
                     "alpha": cfg.alpha, "significant": bool(result.p < cfg.alpha)})
    if cfg.holm:
        for row, adjusted in zip(rows, holm([r["p"] for r in rows]), strict=True):
            row["p_holm"], row["significant_holm"] = adjusted, bool(adjusted < cfg.alpha)
        for row, adjusted in zip(rows, holm([r["sign_flip_p"] for r in rows]), strict=True):
            row["sign_flip_p_holm"] = adjusted
    return rows


def format_p(p: float) -> str:
    """A p value as the tables and figures print it: 4 decimals, or 2 significant digits below 1e-4 (our choice:
    "0.0000" reads as an impossible p of zero)."""
    return f"{p:.4f}" if p >= 1e-4 else f"{p:.1e}"


def _label(row: dict[str, Any]) -> str:
    """A row's test as the table shows it: ``M1: sr>wake_only`` for a named test (``M1=sr>wake_only``)."""
    name, test = row.get("name"), row["test"]
    return f"{name}: {test[len(name) + 1:]}" if name else test


def render(rows: list[dict[str, Any]], archive: Path, preregistered: bool = False, note: str = "") -> str:
    adjusted = any("p_holm" in r for r in rows)
    header = "| test | metric | seeds | mean diff +- SE | 95% bootstrap CI | t | p | sign-flip p | at alpha |"
    header += " Holm p | Holm sign-flip p | at alpha, Holm |" if adjusted else ""
    label = "Pre-registered" if preregistered else "Exploratory (not pre-registered)"
    lines = [f"{label} paired tests over training seeds ({archive}):", *(["", note] if note else []), "", header,
             "|---" * (12 if adjusted else 9) + "|"]

    def verdict(r: dict[str, Any], significant: bool) -> str:
        return "-" if r["n"] < 2 else ("reject H0" if significant else "not significant")

    for r in rows:
        line = (f"| {_label(r)} ({r['alternative']}) | {r['metric']} | {','.join(map(str, r['seeds']))} | "
                f"{r['mean']:+.3f} +- {r['sem']:.3f} | [{r['ci_low']:+.3f}, {r['ci_high']:+.3f}] | "
                f"{r['t']:.2f} | {format_p(r['p'])} | {format_p(r['sign_flip_p'])} | {verdict(r, r['significant'])} "
                f"({r['alpha']}) |")
        if adjusted:
            line += (f" {format_p(r['p_holm'])} | {format_p(r['sign_flip_p_holm'])} | "
                     f"{verdict(r, r['significant_holm'])} |")
        lines.append(line)
    if adjusted:
        lines += ["", f"Holm: adjusted over the {len(rows)} tests above as one family (the verdict on the t-test p; "
                  "the sign-flip p beside it)."]
    if any(r["archive"] != str(archive) for r in rows):
        lines += ["", "Archives: " + "; ".join(sorted({f"{r['test']}: {r['archive']}" for r in rows}))]
    return "\n".join(lines) + "\n"


def panel_title(name: str, r: dict[str, Any]) -> str:
    """A test's panel title: mean difference +- SE, CI, p and sign-flip p; with a Holm adjustment, a third line with
    the adjusted p's and the family's verdict (the one the test is judged by)."""
    if r["n"] < 2:
        return f"{name}: {r['n']} paired seed(s), no test"
    title = (f"{name}: {r['mean']:+.3f} +- {r['sem']:.3f}\nCI [{r['ci_low']:+.3f}, {r['ci_high']:+.3f}], "
             f"p = {format_p(r['p'])}, sign-flip {format_p(r['sign_flip_p'])}")
    if "p_holm" in r:
        verdict = "rejected" if r["significant_holm"] else "not rejected"
        title += f"\nHolm: p = {format_p(r['p_holm'])}, sign-flip {format_p(r['sign_flip_p_holm'])}: {verdict}"
    return title


def plot(rows: list[dict[str, Any]], path: Path) -> None:
    """One panel per test: each seed's A and B values joined by a line (green where A - B has the tested sign, or
    for a two-sided test the mean difference's sign; red where not), labelled with its training seed, the means +-
    SE beside them, and :func:`panel_title` above it."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(rows), figsize=(3.6 * len(rows), 3.8), squeeze=False)
    for ax, r in zip(axes[0], rows, strict=True):
        a, b = np.asarray(r["a_values"], dtype=float), np.asarray(r["b_values"], dtype=float)
        sign = {"greater": 1.0, "less": -1.0}.get(r["alternative"], np.sign(r["mean"]) if r["n"] else 0.0)
        labels: dict[float, list[str]] = {}
        for seed, ya, yb in zip(r["seeds"], a, b, strict=True):
            agrees = np.sign(ya - yb) == sign != 0
            ax.plot([0, 1], [ya, yb], "-o", color="tab:green" if agrees else "tab:red", ms=4, lw=1, alpha=0.8)
            labels.setdefault(round(float(ya), 3), []).append(str(seed))
        for y, seeds in labels.items():  # seeds with the same A value share one label
            ax.annotate(",".join(seeds), (0, y), xytext=(-6, 0), textcoords="offset points", fontsize=7,
                        va="center", ha="right")
        for x, values in ((-0.25, a), (1.25, b)):
            if len(values):
                sem = values.std(ddof=1) / np.sqrt(len(values)) if len(values) > 1 else 0.0
                ax.errorbar([x], [values.mean()], yerr=[sem], fmt="s", color="k", capsize=4, ms=5)
        name, ticks = f"{r['a']}{_OPERATOR[r['alternative']]}{r['b']}", [r["a"], r["b"]]
        if r.get("name"):
            name = f"{r['name']}: {name}"
        if r["archive_a"] != r["archive_b"]:  # one variant, two archives: name them under the variants
            ticks = [f"{r['a']}\n{Path(r['archive_a']).name}", f"{r['b']}\n{Path(r['archive_b']).name}"]
        ax.set_xticks([0, 1], ticks, fontsize=6)
        ax.set_xlim(-0.6, 1.6)
        ax.set_ylabel(f"final {r['metric']}")
        ax.set_title(panel_title(name, r), fontsize=8)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


def main(args: list[str] | None = None) -> None:
    setup_logging()
    cfg = parse_command(HypothesesConfig, args, prog=PROG)
    rows = run_tests(cfg)
    text = render(rows, cfg.archive, cfg.preregistered, cfg.note)
    if cfg.output is not None:
        write_checked_json(cfg.output / "hypotheses.json", {"archive": str(cfg.archive), "tests": rows})
        atomic_write_bytes(cfg.output / "hypotheses.md", text.encode())
        if rows:
            plot(rows, cfg.output / "hypotheses.png")
    print(text)  # noqa: T201 (command output)


if __name__ == "__main__":
    run_cli(PROG, main)
