"""A stream's calibration criteria, read from the archived calibration runs (the protocol in docs/RESULTS.md).

    python -m experiments.calibration --archive=docs/results/metaworld_mt5_imitation_calibration \\
        --seeds=[100,101,102] --output=docs/results/metaworld_mt5_imitation_calibration/calibration

Each criterion is read on the mean over the calibration seeds (each seed's value its mean over the evaluation units):

- C1, the oracle learns the stream: ``mt_joint``'s final AFSR >= ``oracle_afsr`` and every skill's final success
  >= ``oracle_skill``;
- C2, every skill is learnable in its own wake: in the ``sequential_bc`` runs (plain behaviour-cloning wakes) every
  skill's success right after its own wake >= ``own_wake``;
- C3, the stream forgets without protection, on sequential BC's stage-wise success (not its final AFSR, which
  backward transfer from the last skill can lift): for every skill i but the last, its success after stage i + 1
  is at most ``forget_ratio`` times its success right after its own wake;
- C4, room for consolidation: ``wake_only``'s final AFSR <= ``wake_only_afsr``.

A criterion whose runs are missing is "not measured". Written: ``calibration.md`` and ``calibration.json`` (every
number the verdicts rest on).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sr_imitation.experiments.hypotheses import archived_runs
from sr_imitation.infra.cli_errors import run_cli, setup_logging
from sr_imitation.infra.cli_parsing import parse_command
from sr_imitation.io import atomic_write_bytes, write_checked_json

logger = logging.getLogger(__name__)
PROG = "python -m experiments.calibration"
"""The command as a user types it (usage errors and ``--help`` name it)."""


@dataclass
class CalibrationConfig:
    archive: Path = Path("docs/results/metaworld_mt5_imitation_calibration")
    """A folder of finished calibration runs, ``<variant>_seed<S>/`` each."""
    seeds: list[int] = field(default_factory=lambda: [100, 101, 102])
    """The calibration seeds (never test seeds)."""
    oracle_afsr: float = 0.9
    """C1: MT-Joint's final AFSR at least this."""
    oracle_skill: float = 0.8
    """C1: every skill's final MT-Joint success at least this."""
    own_wake: float = 0.9
    """C2: every skill's success right after its own wake (sequential BC) at least this."""
    forget_ratio: float = 0.5
    """C3: each earlier skill's success after the next stage at most this fraction of its own-wake success."""
    wake_only_afsr: float = 0.85
    """C4: wake-only's final AFSR at most this."""
    output: Path | None = None
    """Where calibration.md / .json go (none: print only)."""

    def __post_init__(self) -> None:
        if not Path(self.archive).is_dir():
            raise FileNotFoundError(f"archive: {self.archive} is not a folder")
        if not self.seeds:
            raise ValueError("seeds: name at least one calibration seed")


def _runs(cfg: CalibrationConfig, variant: str) -> list[dict[str, Any]]:
    runs = archived_runs(cfg.archive, variant)
    missing = [s for s in cfg.seeds if s not in runs]
    if missing:
        logger.warning("%s: no finished run for seeds %s in %s", variant, missing, cfg.archive)
    return [runs[s] for s in cfg.seeds if s in runs]


def _mean(rows: list[list[float]]) -> list[float]:
    return np.asarray(rows, dtype=float).mean(axis=0).tolist()


def read_calibration(cfg: CalibrationConfig) -> dict[str, Any]:
    """Every criterion's numbers and verdict (``True``/``False``, ``None`` where its runs are missing)."""
    out: dict[str, Any] = {"archive": str(cfg.archive), "seeds": list(cfg.seeds), "criteria": {}}
    oracle, seq, wake_only = _runs(cfg, "mt_joint"), _runs(cfg, "sequential_bc"), _runs(cfg, "wake_only")
    skills = next((r["skills"] for r in (*oracle, *seq, *wake_only)), [])
    out["skills"] = skills
    crit = out["criteria"]
    if oracle:
        afsr = float(np.mean([r["metrics"]["afsr"]["final"] for r in oracle]))
        final = _mean([r["success_matrix"][-1] for r in oracle])
        crit["C1"] = {"seeds": len(oracle), "mt_joint_afsr": afsr, "mt_joint_final_per_skill": final,
                      "met": afsr >= cfg.oracle_afsr and min(final) >= cfg.oracle_skill}
    if seq:
        own = _mean([r["success_after_own_wake"] for r in seq])
        crit["C2"] = {"seeds": len(seq), "own_wake_per_skill": own, "met": min(own) >= cfg.own_wake}
        after_next = _mean([[r["success_matrix"][i + 1][i] for i in range(len(skills) - 1)] for r in seq])
        crit["C3"] = {"seeds": len(seq), "after_next_stage": after_next, "own_wake": own[:-1],
                      "met": all(a <= cfg.forget_ratio * w for a, w in zip(after_next, own, strict=False)),
                      "final_afsr": float(np.mean([r["metrics"]["afsr"]["final"] for r in seq]))}
    if wake_only:
        afsr = float(np.mean([r["metrics"]["afsr"]["final"] for r in wake_only]))
        crit["C4"] = {"seeds": len(wake_only), "wake_only_afsr": afsr,
                      "wake_only_final_per_skill": _mean([r["success_matrix"][-1] for r in wake_only]),
                      "met": afsr <= cfg.wake_only_afsr}
    for name in ("C1", "C2", "C3", "C4"):
        crit.setdefault(name, {"seeds": 0, "met": None})
        crit[name]["complete"] = crit[name]["seeds"] == len(cfg.seeds)
    return out


def render(reading: dict[str, Any], cfg: CalibrationConfig) -> str:
    skills = reading["skills"]

    def per_skill(values: list[float]) -> str:
        return " / ".join(f"{v:.2f}" for v in values)

    def verdict(c: dict[str, Any]) -> str:
        if c["met"] is None:
            return "not measured"
        return ("met" if c["met"] else "NOT met") + ("" if c["complete"] else f" (only {c['seeds']} seed(s))")

    crit = reading["criteria"]
    lines = [f"Calibration criteria on seeds {reading['seeds']} ({reading['archive']}); skills {' / '.join(skills)}:",
             "", "| criterion | measured (mean over seeds) | threshold | verdict |", "|---|---|---|---|"]
    c = crit["C1"]
    if c["met"] is not None:
        lines.append(f"| C1 oracle | MT-Joint AFSR {c['mt_joint_afsr']:.3f}; final "
                     f"{per_skill(c['mt_joint_final_per_skill'])} | >= {cfg.oracle_afsr}, every skill >= "
                     f"{cfg.oracle_skill} | {verdict(c)} |")
    c = crit["C2"]
    if c["met"] is not None:
        lines.append(f"| C2 own wake | sequential BC right after own wake {per_skill(c['own_wake_per_skill'])} | "
                     f">= {cfg.own_wake} each | {verdict(c)} |")
    c = crit["C3"]
    if c["met"] is not None:
        lines.append(f"| C3 forgetting | sequential BC after the next stage {per_skill(c['after_next_stage'])} "
                     f"(final AFSR {c['final_afsr']:.3f}) | <= {cfg.forget_ratio} x own wake each | {verdict(c)} |")
    c = crit["C4"]
    if c["met"] is not None:
        lines.append(f"| C4 room | wake-only AFSR {c['wake_only_afsr']:.3f}; final "
                     f"{per_skill(c['wake_only_final_per_skill'])} | <= {cfg.wake_only_afsr} | {verdict(c)} |")
    return "\n".join(lines) + "\n"


def main(args: list[str] | None = None) -> None:
    setup_logging()
    cfg = parse_command(CalibrationConfig, args, prog=PROG)
    reading = read_calibration(cfg)
    text = render(reading, cfg)
    if cfg.output is not None:
        write_checked_json(cfg.output / "calibration.json", reading)
        atomic_write_bytes(cfg.output / "calibration.md", text.encode())
    print(text)  # noqa: T201 (command output)


if __name__ == "__main__":
    run_cli(PROG, main)
