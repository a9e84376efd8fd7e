"""Step A of issue 59's protocol (docs/RESULTS.md, "a SAC sleep that keeps what its wakes learn"): screen sleep
candidates by re-sleeping the last stage of stored calibration runs.

    python -m experiments.sleep_screening --archive=docs/results/sac_sleep_calibration \\
        --seeds=[100,101,102] --output_root=outputs/sac_sleep_screening \\
        --screening=docs/results/sac_sleep_screening

For every seed and candidate (:data:`CANDIDATES`: ``control`` repeats the run's own sleep; ``a1``, ``a2``, ``b1``,
``b2`` as the protocol states them) one :func:`~sr_imitation.substrates.sac.resleep.resleep` of the archived run's last
stage from its weight store (checked against the archive's ``weights.json`` first), in
``<output_root>/<candidate>_seed<seed>``; a finished re-sleep is skipped, a killed one continued. Each is archived in
``--screening`` (report files only). Per seed the actor entering the sleep (the stored last wake) is evaluated once
on every skill, on the same paired configurations (``before_seed<seed>.json``). Then ``screening.json`` / ``.md``:
per candidate and seed the final AFSR and per-skill success, before and after, the stop iteration and reason, each
memory's loss at the first and last iteration, the final Nash weights; per candidate the mean +- SE over seeds and
the difference to the control; whether each control reproduced its archived run (the protocol stops the screening if
one does not); and rule A applied as written (:func:`rule_a`). Everything here is exploratory (calibration seeds).
"""

from __future__ import annotations

import logging
import math
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sr_imitation.core.metrics import mean_sem
from sr_imitation.experiments.archive import archive_run
from sr_imitation.experiments.mt5_compare import SLEEP_CANDIDATES
from sr_imitation.infra.cli_errors import run_cli, setup_logging
from sr_imitation.infra.cli_parsing import parse_command
from sr_imitation.infra.weight_store import verify_weights, weight_store
from sr_imitation.io import atomic_write_bytes, read_checked_json, write_checked_json
from sr_imitation.stream.config import check_choices

logger = logging.getLogger(__name__)
PROG = "python -m experiments.sleep_screening"

CANDIDATES = SLEEP_CANDIDATES
"""candidate -> the ``sr-train`` flags its re-sleep changes (the protocol's a1, a2, b1, b2; ``control``: none): the
comparison's own list (:data:`sr_imitation.experiments.mt5_compare.SLEEP_CANDIDATES`), whose ``sr_<name>`` variants
run them as full streams."""
ORDER = ("a1", "a2", "b1", "b2")
"""Rule A's order of preference among candidates within ``TIE`` of the best."""
MARGIN = 0.05
"""Rule A: the winner's mean final AFSR must exceed the control's by at least this."""
TIE = 0.01
"""Rule A: candidates within this of the best mean count as tied (the earlier in :data:`ORDER` wins)."""
NO_VIDEOS = "--eval.videos_per_skill=0"
PROTOCOL_SEEDS = (100, 101, 102)
"""Rule A decides on these calibration seeds together; a screening of fewer (e.g. while a run is still going) is
reported, not decided."""


@dataclass
class ScreeningConfig:
    """The screening's command line."""

    archive: Path = Path("docs/results/sac_sleep_calibration")
    """The calibration runs' archive (``sr_seed<seed>``), their weights in ``<archive>.weights``."""
    seeds: list[int] = field(default_factory=lambda: [100, 101, 102])
    """Calibration seeds (the protocol's: 100-102 only)."""
    candidates: list[str] = field(default_factory=lambda: list(CANDIDATES))
    """Candidates to re-sleep, in this order (:data:`CANDIDATES`)."""
    output_root: Path = Path("outputs/sac_sleep_screening")
    """Where the re-slept runs go (``<candidate>_seed<seed>``)."""
    screening: Path | None = Path("docs/results/sac_sleep_screening")
    """Where the re-slept runs' report files and the screening table are archived; ``None``: ``output_root``."""
    decide_on_any_seeds: bool = False
    """Apply rule A to whatever seeds are given (tests); by default only to the protocol's seeds 100-102."""

    def __post_init__(self) -> None:
        check_choices("candidates", self.candidates, CANDIDATES)
        if not self.seeds:
            raise ValueError("seeds: give at least one calibration seed")


def run_name(candidate: str, seed: int) -> str:
    return f"{candidate}_seed{seed}"


def resleep_one(cfg: ScreeningConfig, candidate: str, seed: int) -> dict[str, Any]:
    """The re-sleep of ``candidate`` on seed ``seed`` (skipped if finished, continued if killed); its results."""
    from sr_imitation.substrates.sac.resleep import ResleepConfig, resleep

    out = cfg.output_root / run_name(candidate, seed)
    if (out / "results.json").is_file():
        logger.info("%s: finished, skipped", out)
        return read_checked_json(out / "results.json")
    archived = cfg.archive / f"sr_seed{seed}"
    return resleep(ResleepConfig(source=weight_store(cfg.archive) / archived.name, archived=archived, output_dir=out,
                                 changes=[*CANDIDATES[candidate], NO_VIDEOS]))


def before_sleep(cfg: ScreeningConfig, seed: int) -> dict[str, Any]:
    """Every skill's success of the actor entering the last sleep (the stored last wake's checkpoint), on the
    paired configurations of the run's own evaluations; written once to ``before_seed<seed>.json``."""
    from sr_imitation.substrates.sac.cli import parse
    from sr_imitation.substrates.sac.substrate import SACSubstrate

    path = (cfg.screening or cfg.output_root) / f"before_seed{seed}.json"
    if path.is_file():
        return read_checked_json(path)
    store = verify_weights(cfg.archive / f"sr_seed{seed}")
    run_cfg = parse([f"--config_path={store / 'train_config.json'}", f"--output_dir={store}", NO_VIDEOS])
    substrate = SACSubstrate(run_cfg)
    substrate.setup()
    last = len(substrate.skills) - 1
    substrate.load_policy(last, "wake")
    rows, _ = substrate.evaluate_rows(last, list(range(last + 1)), videos=False, trajectories=False)
    record = {"seed": seed, "stage": last + 1, "checkpoint": f"{substrate.stage_dir(last).name}/wake",
              "skills": [substrate.memory_skill(i) for i in range(last + 1)],
              "success": [r["success_rate"] for r in rows]}
    write_checked_json(path, record)
    return record


def row_of(candidate: str, seed: int, results: Mapping[str, Any], archived: Mapping[str, Any] | None
           ) -> dict[str, Any]:
    """One line of the screening table from a re-slept run's results."""
    sleep = results["stages"][-1]["sleep"]
    first, last = sleep.get("initial_memory_losses") or [], sleep.get("final_memory_losses") or []
    row = {"candidate": candidate, "seed": seed, "final_afsr": results["metrics"]["afsr"]["final"],
           "final_success": list(results["success_matrix"][-1]), "stop_iteration": sleep["stop_iteration"],
           "stop_reason": sleep["stop_reason"], "memory_skills": sleep["skills"], "initial_memory_losses": first,
           "final_memory_losses": last, "final_alpha": sleep.get("final_alpha"),
           "early_stop_scale": sleep.get("early_stop_scale")}
    if archived is not None:
        row["reproduces_archive"] = (results["success_matrix"] == archived["success_matrix"]
                                     and results["metrics"]["afsr"] == archived["metrics"]["afsr"])
    return row


def mean_se(values: Sequence[float]) -> dict[str, float | None]:
    """Mean and standard error over seeds (:func:`~sr_imitation.core.metrics.mean_sem`; ``se`` none for one seed,
    so that the JSON holds no NaN)."""
    mean, sem = mean_sem(values)
    return {"mean": mean, "se": None if math.isnan(sem) else sem}


def rule_a(means: Mapping[str, float]) -> dict[str, Any]:
    """The protocol's rule A on the candidates' mean final AFSR (``control`` among them): the best candidate, the
    earlier in :data:`ORDER` among those within :data:`TIE` of it; it wins if it exceeds the control by at least
    :data:`MARGIN`, else there is no A-winner."""
    tried = [c for c in ORDER if c in means]
    if "control" not in means or not tried:
        return {"winner": None, "reason": "the control and at least one candidate are needed"}
    best = max(means[c] for c in tried)
    pick = next(c for c in tried if means[c] >= best - TIE)
    gain = means[pick] - means["control"]
    if gain >= MARGIN:
        return {"winner": pick, "gain": gain, "reason": f"{pick} {means[pick]:.3f} >= control "
                                                         f"{means['control']:.3f} + {MARGIN}"}
    return {"winner": None, "best": pick, "gain": gain,
            "reason": f"no candidate exceeds the control by {MARGIN} (best {pick}: {gain:+.3f})"}


def summarize(rows: Sequence[Mapping[str, Any]], before: Mapping[int, Mapping[str, Any]], candidates: Sequence[str],
              seeds: Sequence[int], decide_on_any_seeds: bool = False) -> dict[str, Any]:
    """Per candidate the mean +- SE over seeds of the final AFSR and its paired difference to the control, the
    controls' reproduction, and rule A (only when every candidate has every seed, and the seeds are the protocol's
    :data:`PROTOCOL_SEEDS` unless ``decide_on_any_seeds``: tests)."""
    by = {(r["candidate"], r["seed"]): r for r in rows}
    per: dict[str, Any] = {}
    for c in candidates:
        values = [by[(c, s)]["final_afsr"] for s in seeds if (c, s) in by]
        if not values:
            continue
        entry: dict[str, Any] = {"seeds": [s for s in seeds if (c, s) in by], **mean_se(values)}
        if c != "control" and all(("control", s) in by for s in entry["seeds"]):
            entry["minus_control"] = mean_se([by[(c, s)]["final_afsr"] - by[("control", s)]["final_afsr"]
                                              for s in entry["seeds"]])
        per[c] = entry
    complete = all((c, s) in by for c in candidates for s in seeds)
    controls = [by[("control", s)].get("reproduces_archive") for s in seeds if ("control", s) in by]
    if not complete:
        decision = {"winner": None, "reason": "incomplete: rule A waits for every candidate on every seed"}
    elif tuple(sorted(seeds)) != PROTOCOL_SEEDS and not decide_on_any_seeds:
        decision = {"winner": None, "reason": f"rule A decides on seeds {list(PROTOCOL_SEEDS)} together; these are "
                                              f"{list(seeds)}"}
    else:
        decision = rule_a({c: e["mean"] for c, e in per.items()})
    if not all(controls):
        decision = {"winner": None, "reason": "a control did not reproduce its archived run: the screening stops"}
    return {"seeds": list(seeds), "candidates": per, "controls_reproduce": controls, "complete": complete,
            "rule_a": decision, "before": {str(s): dict(b) for s, b in before.items()}, "rows": list(rows)}


def se_text(se: float | None) -> str:
    """A standard error for a table (``None``: one seed, no SE)."""
    return "n/a (one seed)" if se is None else f"{se:.3f}"


def losses_text(first: Sequence[float], last: Sequence[float]) -> str:
    """Each memory's loss at a sleep's first and last iteration, for a table cell."""
    return ", ".join(f"{a:.3g} -> {b:.3g}" for a, b in zip(first, last, strict=True))


def weights_text(alpha: Sequence[float] | None) -> str:
    """A sleep's final Nash weights, for a table cell."""
    return " / ".join(f"{a:.2f}" for a in (alpha or []))


def render(summary: Mapping[str, Any]) -> str:
    """``screening.md``."""
    named = [f"{c} ({' '.join(CANDIDATES[c]) or 'the run as it was'})" for c in summary["candidates"]]
    lines = ["# Issue 59, step A: re-sleeping the last stage of the calibration runs (exploratory)", "",
             f"Seeds {summary['seeds']}; candidates {', '.join(named)}.", "",
             "| candidate | mean final AFSR +- SE | minus control +- SE | seeds |", "|---|---|---|---|"]
    for c, e in summary["candidates"].items():
        diff = e.get("minus_control")
        minus = "" if diff is None else f"{diff['mean']:+.3f} +- {se_text(diff['se'])}"
        lines.append(f"| {c} | {e['mean']:.3f} +- {se_text(e['se'])} | {minus} | {e['seeds']} |")
    lines += ["", f"Controls reproduce their archived runs: {summary['controls_reproduce']}.",
              f"Rule A: {summary['rule_a']['reason']}" + (f" -> **{summary['rule_a']['winner']}**"
                                                         if summary["rule_a"].get("winner") else ""), "",
              "| candidate | seed | final success per skill (before the sleep) | final AFSR | stop "
              "| memory losses first -> last | final Nash weights |", "|---|---|---|---|---|---|---|"]
    for r in summary["rows"]:
        before = summary["before"].get(str(r["seed"]), {}).get("success")
        skills = " / ".join(f"{a:.2f}" + (f" ({b:.2f})" if before else "")
                            for a, b in zip(r["final_success"], before or r["final_success"], strict=True))
        lines.append(f"| {r['candidate']} | {r['seed']} | {skills} | {r['final_afsr']:.3f} | {r['stop_iteration']} "
                     f"({r['stop_reason']}) | {losses_text(r['initial_memory_losses'], r['final_memory_losses'])} | "
                     f"{weights_text(r['final_alpha'])} |")
    return "\n".join(lines) + "\n"


def run_screening(cfg: ScreeningConfig) -> dict[str, Any]:
    """Every re-sleep (seeds outer, candidates inner), each archived as it ends, then the table."""
    target = cfg.screening or cfg.output_root
    rows, before = [], {}
    for seed in cfg.seeds:
        archived = read_checked_json(cfg.archive / f"sr_seed{seed}" / "results.json")
        before[seed] = before_sleep(cfg, seed)
        for candidate in cfg.candidates:
            results = resleep_one(cfg, candidate, seed)
            if cfg.screening is not None:
                archive_run(cfg.output_root / run_name(candidate, seed), cfg.screening, run_name(candidate, seed))
            rows.append(row_of(candidate, seed, results, archived if candidate == "control" else None))
            logger.info("screened %s seed %d: final AFSR %.3f", candidate, seed, rows[-1]["final_afsr"])
    summary = summarize(rows, before, cfg.candidates, cfg.seeds, cfg.decide_on_any_seeds)
    write_checked_json(target / "screening.json", summary)
    atomic_write_bytes(target / "screening.md", render(summary).encode())
    logger.info("rule A: %s", summary["rule_a"]["reason"])
    return summary


def main(args: list[str] | None = None) -> None:
    setup_logging()
    run_screening(parse_command(ScreeningConfig, list(sys.argv[1:] if args is None else args), prog=PROG))


if __name__ == "__main__":
    run_cli(PROG, main)
