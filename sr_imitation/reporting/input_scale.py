"""How large an ACT-SR policy's state input weights are at each stage of a run:
``python -m sr_imitation.reporting.input_scale RUN [RUN ...] [--output FILE.json]``.

For each stage's wake and sleep checkpoint (``skill_<k>_<name>/{wake,sleep}/pretrained_model``, checked against its
``checksums.json`` first) the column norms of ``model.encoder_robot_state_input_proj.weight``: one number per state
dimension, the size of what that normalized input contributes to the encoder's tokens. Under
``--stream.stats=union`` the statistics never change and the norms stay about where training leaves them; under
``seen`` each widening of the statistics re-expresses the weights exactly (the input weights of a dimension grow by the
factor its standard deviation grows, :func:`~sr_imitation.substrates.act.normalization.reexpress_state_dict`), so this
shows how far a run's weights have been rescaled (docs/RESULTS.md, "The normalization default measured"). Reads
only; with ``--output`` writes one checked JSON."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from sr_imitation.infra.cli_errors import run_cli
from sr_imitation.io import load_checkpoint_weights, write_checked_json

STATE_INPUT = "model.encoder_robot_state_input_proj.weight"
"""ACT's linear layer that reads the normalized robot state into the encoder (dim_model x state dimensions)."""


def stage_input_norms(run: Path) -> list[dict[str, Any]]:
    """One row per checkpoint of ``run`` in stage order: stage, skill, phase and the column norms of
    :data:`STATE_INPUT` (with their largest value, its dimension and their median)."""
    rows = []
    stages = sorted((p for p in Path(run).glob("skill_*_*") if p.is_dir()), key=lambda p: int(p.name.split("_")[1]))
    if not stages:
        raise FileNotFoundError(f"{run}: no stage folders skill_<k>_<name> (not a finished or started ACT-SR run?)")
    for stage in stages:
        for phase in ("wake", "sleep"):
            checkpoint = stage / phase
            model = checkpoint / "pretrained_model" / "model.safetensors"
            if not model.is_file():
                continue
            norms = load_checkpoint_weights(checkpoint)[STATE_INPUT].double().norm(dim=0)
            rows.append({"stage": int(stage.name.split("_")[1]), "skill": stage.name.split("_", 2)[2], "phase": phase,
                         "max": float(norms.max()), "argmax": int(norms.argmax()), "median": float(norms.median()),
                         "column_norms": [float(x) for x in norms]})
    return rows


def render(run: Path, rows: Sequence[dict[str, Any]]) -> str:
    lines = [f"{run}: column norms of {STATE_INPUT}", "| stage | skill | phase | largest (dimension) | median |",
             "|---|---|---|---|---|"]
    lines += [f"| {r['stage']} | {r['skill']} | {r['phase']} | {r['max']:.2f} ({r['argmax']}) | {r['median']:.2f} |"
              for r in rows]
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m sr_imitation.reporting.input_scale", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path, help="run directories (ACT-SR, any --stream.stats)")
    parser.add_argument("--output", type=Path, default=None, help="a checked JSON with every run's rows")
    args = parser.parse_args(list(sys.argv[1:] if argv is None else argv))
    table = {str(run): stage_input_norms(run) for run in args.runs}
    if args.output is not None:
        write_checked_json(args.output, {"layer": STATE_INPUT, "runs": table})
    sys.stdout.write("\n".join(render(Path(run), rows) for run, rows in table.items()))


if __name__ == "__main__":
    run_cli("sr_imitation.reporting.input_scale", main)
