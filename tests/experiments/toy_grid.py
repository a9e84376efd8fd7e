"""A toy grid substrate (no training: each run writes its fingerprint and a results.json in a fraction of a second),
for the grid runner's scheduling: runs that wait for another, runs that fail. Imported by Ray's workers by name
(``tests.experiments.toy_grid``; the workers start in the driver's directory, the repository root)."""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sr_imitation.experiments.grid import GridConfig, run_name
from sr_imitation.infra.fingerprint import FINGERPRINT_FILE, settings_fingerprint, write_fingerprint
from sr_imitation.stream.config import check_choices

AFTER = {"after_a": "a", "after_fails": "fails"}
MEET = ("meet_a", "meet_b")


@dataclass
class ToyRun:
    output_dir: Path
    seed: int
    resume: bool = False
    torch_threads: int | None = None


def _ray_health_checks() -> list[int] | None:
    """The Ray settings this worker's node runs with (period in ms, missed checks before a node is dead); ``None``
    outside Ray."""
    import ray

    if not ray.is_initialized():
        return None
    from ray._raylet import Config

    return [Config.health_check_period_ms(), Config.health_check_failure_threshold()]


class ToyGrid:
    """Runs of the :data:`MEET` variants each leave a mark beside their folder and wait (up to
    ``$TOY_GRID_MEET_TIMEOUT`` s, default 120) for the marks of the others, recording ``met``: true only when the runs
    were alive at the same time, however slowly their processes started (a load-independent test of running at once)."""

    variants = {"a": None, "b": None, "fails": None, **dict.fromkeys(AFTER), **dict.fromkeys(MEET)}
    default_variants = ["a", "b"]
    default_seeds = [0]

    def validate(self, variants: list[str]) -> None:
        check_choices("variants", variants, self.variants)

    def plan(self, cfg: GridConfig) -> dict[tuple[str, int], ToyRun]:
        return {(v, s): ToyRun(cfg.output_root / run_name(v, s), s) for v in cfg.variants for s in cfg.seeds}

    def fingerprint(self, variant: str, run: ToyRun) -> Any:
        return settings_fingerprint({"variant": variant, "seed": run.seed}, ())

    def check(self, plan: Any, archived: Any) -> None:
        pass

    def after(self, variant: str, seed: int) -> tuple[str, int] | None:
        return (AFTER[variant], seed) if variant in AFTER else None

    def device(self, run: ToyRun) -> str:
        return "cpu"

    def run(self, variant: str, run: ToyRun) -> None:
        out = Path(run.output_dir)
        out.mkdir(parents=True, exist_ok=True)
        write_fingerprint(out / FINGERPRINT_FILE, self.fingerprint(variant, run))
        if variant == "fails":
            raise ValueError("toy failure")
        start = time.time()
        before = AFTER.get(variant)
        waited = before is None or (out.parent / run_name(before, run.seed) / "results.json").is_file()
        time.sleep(0.3)
        met = self._meet(variant, run) if variant in MEET else None
        results = {"metrics": {"afsr": {"final": 0.5}}, "start": start, "end": time.time(), "waited": waited,
                   "met": met,
                   "ray_health_checks": _ray_health_checks()}
        (out / "results.json").write_text(json.dumps(results))

    def _meet(self, variant: str, run: ToyRun) -> bool:
        marks = Path(run.output_dir).parent
        (marks / f".{variant}_seed{run.seed}.here").touch()
        deadline = time.monotonic() + float(os.environ.get("TOY_GRID_MEET_TIMEOUT", "120"))
        while time.monotonic() < deadline:
            if all((marks / f".{v}_seed{run.seed}.here").exists() for v in MEET):
                return True
            time.sleep(0.05)
        return False

    def summarize(self, runs: dict[str, dict[str, Path]], output_root: Path) -> dict[str, Any]:
        return {"runs": {v: {s: str(p) for s, p in seeds.items()} for v, seeds in runs.items()}}


GRID = ToyGrid()


TINY_NEEDLE_TRAIN = {
    "policy": {"type": "act_sr", "device": "cpu", "use_images": False, "dim_model": 32, "n_heads": 2,
               "dim_feedforward": 64, "n_encoder_layers": 1, "n_vae_encoder_layers": 1, "chunk_size": 8,
               "n_action_steps": 8},
    "memory": {"buffer_size": 32},
    "sleep": {"max_iterations": 4, "batch_size": 4, "early_stop_window": 2},
    "stream": {"skills": ["approach", "place"]},
    "wake": {"max_epochs": 2, "min_epochs": 1, "batch_size": 8, "max_steps_per_epoch": 3},
    "eval": {"episodes": 1, "seeds": [0], "max_steps": 40, "videos_per_skill": 0},
    "progress": False,
}
"""The train section of a two-skill state-only needle preset of seconds a run (the grid's and the comparison job's
tests; each overrides what it needs)."""
