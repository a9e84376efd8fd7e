"""Throughput of a grid of runs: the plain loop (one run after another, as the comparison drivers ran them before
``sr-grid``) against ``sr-grid`` on a local Ray and against the machine's ceiling, the same runs.

    python -m sr_imitation.experiments.grid_benchmark [--variants sr wake_only] [--seeds 0 1] [--cpus 2] [--root DIR]
                                           [--wake_epochs 80] [--runners loop ray processes]

A small state-only needle preset (two skills, about 1000 wake steps each, 100 sleep iterations, 3 evaluation
episodes per skill; about half a minute a run on one core) is written under ``--root`` and its datasets recorded
first (not timed). Then the grid of ``variants x seeds`` runs once per runner, each into a fresh folder: ``loop``, in
this process (one torch thread, as ``OMP_NUM_THREADS=1``); ``ray``, ``sr-grid`` on a Ray started for it with
``--cpus`` cores (one run per core, one thread each); ``processes``, ``--cpus`` plain processes started together,
each running its share of the runs one after another (no scheduler: what the cores give at best, the ceiling for
``ray``). Each time is the wall time of the whole grid, end to end (for Ray: starting and stopping it, a fresh worker
process with its imports per run). The grids' results are compared (every run's results.json metrics and every
checkpoint's weights, bit for bit). Prints a markdown table for docs/BENCHMARKS.md with the load average before each
runner and the runs' own phase seconds (``progress.json``) under each runner: their ratio says how much the runs
slowed each other down.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

PRESET = {
    "record": {"num_episodes": 4, "image_size": 32},
    "train": {
        "policy": {"type": "act_sr", "device": "cpu", "use_images": False, "use_vae": False, "dropout": 0.0,
                   "dim_model": 64, "n_heads": 4, "dim_feedforward": 256, "n_encoder_layers": 2,
                   "n_decoder_layers": 1, "chunk_size": 16, "n_action_steps": 8},
        "memory": {"buffer_size": 64},
        "sleep": {"max_iterations": 100, "batch_size": 16, "early_stop_window": 200},
        "stream": {"skills": ["approach", "place"]},
        "wake": {"max_epochs": 80, "min_epochs": 80, "batch_size": 32, "max_steps_per_epoch": 40},
        "eval": {"episodes": 3, "seeds": [0], "max_steps": 120, "videos_per_skill": 0},
        "progress": False,
    },
}
"""The benchmark's preset (``record.root`` and nothing else is added)."""


def _same_results(a: Path, b: Path) -> bool:
    import torch
    from safetensors.torch import load_file

    for run in sorted(p.name for p in a.iterdir() if (p / "results.json").is_file()):
        ra, rb = (json.loads((root / run / "results.json").read_text()) for root in (a, b))
        if ra["metrics"] != rb["metrics"] or ra["success_matrix"] != rb["success_matrix"]:
            return False
        files = sorted(p.relative_to(a / run) for p in (a / run).rglob("*.safetensors"))
        if files != sorted(p.relative_to(b / run) for p in (b / run).rglob("*.safetensors")):
            return False
        for f in files:
            x, y = load_file(a / run / f), load_file(b / run / f)
            if x.keys() != y.keys() or not all(torch.equal(x[k], y[k]) for k in x):
                return False
    return True


def _phase_seconds(root: Path) -> float:
    """The runs' own compute time (:func:`~sr_imitation.reporting.summary.phase_seconds`), summed over the runs."""
    from sr_imitation.reporting.summary import phase_seconds

    return sum(phase_seconds(progress.parent) or 0.0 for progress in root.glob("*/progress.json"))


RUNNERS = ("loop", "ray", "processes")


def _side_by_side(preset: Path, runs: list[tuple[str, int]], cpus: int, out: Path) -> None:
    """The runs in ``cpus`` plain processes started together, each ``sr-grid --runner=loop`` over its share of the
    runs in turn (round robin), one torch thread each: what the cores give without any scheduler."""
    shares = [runs[i::cpus] for i in range(cpus)]
    procs = []
    for share in shares:
        if not share:
            continue
        steps = [f"{sys.executable} -m sr_imitation.experiments.grid --preset={preset} --variants=[{v}] "
                 f"--seeds=[{s}] --output_root={out} --runner=loop" for v, s in share]
        procs.append(subprocess.Popen(["bash", "-c", " && ".join(steps)], stdout=subprocess.DEVNULL,
                                      stderr=subprocess.DEVNULL, env={**os.environ, "OMP_NUM_THREADS": "1"}))
    codes = [p.wait() for p in procs]
    if any(codes):
        raise RuntimeError(f"side-by-side processes failed with exit codes {codes}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--variants", nargs="+", default=["sr", "wake_only"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1])
    parser.add_argument("--cpus", type=int, default=2, help="cores of the local Ray (one run each)")
    parser.add_argument("--root", type=Path, default=None, help="working folder (default: a temporary one)")
    parser.add_argument("--wake_epochs", type=int, default=PRESET["train"]["wake"]["max_epochs"],
                        help="wake epochs per skill (the runs' length; about 12 steps an epoch)")
    parser.add_argument("--runners", nargs="+", default=["loop", "ray", "processes"], choices=RUNNERS,
                        help="loop: one process, one run at a time; ray: sr-grid on a local Ray; processes: the "
                             "machine's ceiling, --cpus plain processes side by side, each a loop over its share of "
                             "the runs (no Ray)")
    args = parser.parse_args()
    os.environ["OMP_NUM_THREADS"] = "1"  # the loop's process and, inherited, Ray's workers
    from sr_imitation.infra.cli_errors import setup_logging
    from sr_imitation.offscreen import setup_offscreen_rendering

    setup_offscreen_rendering()
    setup_logging(logging.WARNING)
    import torch

    from sr_imitation.experiments.grid import GridConfig, RayOptions, run_grid
    from sr_imitation.main_job import preset_with_datasets

    torch.set_num_threads(1)
    root = args.root or Path(tempfile.mkdtemp(prefix="grid_bench_"))
    root.mkdir(parents=True, exist_ok=True)
    preset = root / "preset.json"
    train = {**PRESET["train"], "wake": {**PRESET["train"]["wake"], "max_epochs": args.wake_epochs,
                                          "min_epochs": args.wake_epochs}}
    preset.write_text(json.dumps({"record": {**PRESET["record"], "root": str(root / "datasets")}, "train": train}))
    preset_with_datasets(preset, [])  # recorded before any timing
    runs = len(args.variants) * len(args.seeds)
    times, loads = {}, {}
    runners = [r for r in RUNNERS if r in args.runners]
    for runner in runners:
        out = root / runner
        shutil.rmtree(out, ignore_errors=True)
        loads[runner] = os.getloadavg()[0]
        start = time.perf_counter()
        if runner == "processes":
            _side_by_side(preset, [(v, s) for v in args.variants for s in args.seeds], args.cpus, out)
        else:
            run_grid(GridConfig(preset=preset, variants=list(args.variants), seeds=list(args.seeds), output_root=out,
                                runner=runner, ray=RayOptions(local_cpus=args.cpus)))
        times[runner] = time.perf_counter() - start
    loads["end"] = os.getloadavg()[0]
    base = runners[0]
    same = all(_same_results(root / base, root / r) for r in runners[1:])
    print(f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__}, "
          f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}; {runs} runs ({' '.join(args.variants)} x seeds "
          f"{' '.join(map(str, args.seeds))}); {args.cpus} cores; load average (1 min) before each runner "
          + ", ".join(f"{r} {loads[r]:.1f}" for r in runners) + f", at the end {loads['end']:.1f}")
    print()
    phases = {runner: _phase_seconds(root / runner) for runner in times}
    labels = {"loop": "loop (one process, one run at a time)", "ray": f"sr-grid, local Ray on {args.cpus} cores",
              "processes": f"{args.cpus} plain processes side by side, no Ray (the machine's ceiling)"}
    print(f"| runner | wall s (grid) | runs per hour | throughput (vs {base}) | the runs' phases, s (summed) |")
    print("|---|---|---|---|---|")
    for runner in runners:
        print(f"| {labels[runner]} | {times[runner]:.1f} | {3600 * runs / times[runner]:.0f} | "
              f"{times[base] / times[runner]:.2f}x | {phases[runner]:.1f} |")
    print()
    for runner in runners[1:]:
        print(f"{runner}: each run's phases took {phases[runner] / phases[base]:.2f}x as long as under {base} (1.0: "
              f"the runs do not slow each other); the rest of the wall time, "
              f"{times[runner] - phases[runner] / min(args.cpus, runs):.1f} s, is start-up (Ray, fresh processes and "
              "their imports) and the runs' set-up outside their phases")
    print()
    print(f"results identical (metrics and every checkpoint's weights): {'yes' if same else 'NO'}")


if __name__ == "__main__":
    main()
