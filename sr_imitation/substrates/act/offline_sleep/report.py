"""What sr-sleep writes beside the consolidated policy: sleep.json's record and sleep.md."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from sr_imitation.core.sleep import SleepResult
from sr_imitation.infra.fingerprint import to_jsonable
from sr_imitation.substrates.act.offline_sleep.config import (
    RESULTS_FORMAT,
    RESULTS_VERSION,
    OfflineSleepConfig,
)
from sr_imitation.substrates.act.offline_sleep.inputs import (
    SleepInputs,
)

logger = logging.getLogger(__name__)

def _record(cfg: OfflineSleepConfig, inputs: SleepInputs, result: SleepResult, seconds: float,
            before: list[float], after: list[float], success_before: dict[str, Any] | None,
            success_after: dict[str, Any] | None) -> dict[str, Any]:
    memories = [{"file": str(m.path), "skill": m.memory.skill, "size": m.memory.size,
                 "reduction": m.memory.config.get("reduction"), "snapshot": None if m.snapshot is None
                 else str(m.snapshot), "targets": m.targets, "loss_before": b, "loss_after": a}
                for m, b, a in zip(inputs.memories, before, after, strict=True)]
    success = None
    if success_before is not None and success_after is not None:
        success = {s: {"before": success_before[s]["success"], "after": success_after[s]["success"],
                       "before_per_seed": success_before[s]["success_per_seed"],
                       "after_per_seed": success_after[s]["success_per_seed"],
                       "videos": success_before[s]["videos"] + success_after[s]["videos"]}
                   for s in success_before}
    return {
        "format": RESULTS_FORMAT,
        "version": RESULTS_VERSION,
        "policy": str(cfg.policy.path),
        "anchor": None if cfg.sleep.anchor_strength == 0 else (str(cfg.anchor.path) if cfg.anchor.path else
                                                               "the deployed policy"),
        "final_skill": cfg.final_skill,
        "gate_snapshots": len(inputs.wake_snapshots),
        "statistics": inputs.statistics or "as deployed",
        "sleep_settings": to_jsonable(cfg.sleep),
        "memories": memories,
        "summed_loss": {"before": sum(before), "after": sum(after)},
        "sleep": {"seconds": seconds, **result.summary()},
        "success": success,
        "evaluation": list(cfg.eval.skills) or "off (no --eval.skills)",
        "checkpoint": "pretrained_model",
    }


def report_markdown(record: dict[str, Any]) -> str:
    """``sleep.md``: the before/after tables of a :func:`run_offline_sleep` record."""
    sleep = record["sleep"]
    lines = [
        "# sr-sleep", "",
        f"Policy `{record['policy']}`, anchor: {record['anchor'] or 'none (sleep.anchor_strength=0)'}; "
        f"{sleep['stop_iteration']} iterations ({sleep['stop_reason']}), anchor coefficient "
        f"{sleep['anchor_lambda']:g}, {sleep['seconds']:.1f} s. Consolidated checkpoint: `{record['checkpoint']}/`.",
        "", f"Normalization statistics: {record.get('statistics', 'as deployed')}.",
        "", "Memory losses L_i on each memory's whole buffer (squared action-chunk difference to its frozen snapshot, "
        "in the policy's normalized action space):", "",
        "| # | memory | skill | size | targets | loss before | loss after | change |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for i, m in enumerate(record["memories"], start=1):
        lines.append(f"| {i} | `{Path(m['file']).name}` | {m['skill']} | {m['size']} | {m['targets']} | "
                     f"{m['loss_before']:.4g} | {m['loss_after']:.4g} | {m['loss_after'] - m['loss_before']:+.3g} |")
    total = record["summed_loss"]
    lines.append(f"| | **sum** | | | | {total['before']:.4g} | {total['after']:.4g} | "
                 f"{total['after'] - total['before']:+.3g} |")
    lines.append("")
    if record["success"] is None:
        lines.append("Success: not evaluated (no --eval.skills).")
    else:
        lines += ["| skill | success before | success after |", "| --- | --- | --- |"]
        lines += [f"| {s} | {r['before']:.3f} | {r['after']:.3f} |" for s, r in record["success"].items()]
    return "\n".join(lines) + "\n"
