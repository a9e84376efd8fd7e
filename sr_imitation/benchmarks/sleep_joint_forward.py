"""Whole ACT-SR sleep iterations with and without ``--sleep.joint_forward``, at the stream's sizes, memories as the
stream writes them.

    python -m sr_imitation.benchmarks.sleep_joint_forward [--device auto|cpu|cuda] [--repeats 20] [--threads N]
        [--k 3] [--batch 32] [--vision]

Rows (milliseconds per iteration of :func:`~sr_imitation.core.sleep.sleep_consolidate`: the k per-memory gradients,
the Gram matrix, the Nash solve, the Adam step; :func:`~sr_imitation.benchmarks.device.bench_act_sleep`):

- the k forward and k backward passes (the default);
- ``joint_forward``: one forward over the k batches, one backward batched over the k losses;
- ``joint_forward`` with the memories in groups of one, as the stream had them before 2026-11-27: each memory's
  config names its own checkpoint (``snapshot``), and memories were grouped for one forward by their whole config,
  so the stream ran k forwards and then the batched backward, k times the backward arithmetic for nothing. On an H200
  the per-memory-gradient benchmark had joint forward 2.1-3.3x faster while the stream's sleeps were up to 1.7x
  slower with it (docs/BENCHMARKS.md); ``ActorMemory.provenance_keys`` now leaves the name out of the grouping.

The defaults are the first-look and state-only CPU presets' sleeps (k = 3 memories at the third skill, batch 32).
"""

from __future__ import annotations

import argparse

import torch

from lerobot_policy_act_sr.actor_memory import ActorMemory
from sr_imitation.benchmarks.device import bench_act_sleep, device_name, parse_device_args


class GroupsOfOne(ActorMemory):
    """An ActorMemory whose checkpoint name counts in the grouping (how every ActorMemory grouped before
    2026-11-27): memories of different skills never share a forward pass."""

    provenance_keys = ()


def main() -> None:
    def sizes(parser: argparse.ArgumentParser) -> None:
        parser.add_argument("--k", type=int, default=3, help="memories per iteration")
        parser.add_argument("--batch", type=int, default=32, help="observations per memory batch")
        parser.add_argument("--vision", action="store_true", help="the vision preset's policy and memories")

    device, args = parse_device_args(__doc__, repeats=20, extra=sizes)
    common = {"vision": args.vision, "k": args.k, "batch": args.batch}
    rows = [
        ("k forward + k backward passes (the default)", lambda: bench_act_sleep(device, args.repeats, **common)),
        ("joint forward (one forward, one batched backward)",
         lambda: bench_act_sleep(device, args.repeats, joint_forward=True, **common)),
        ("joint forward, memories in groups of one (before 2026-11-27)",
         lambda: bench_act_sleep(device, args.repeats, joint_forward=True, memory_class=GroupsOfOne, **common)),
    ]
    policy = "vision (64x64 wrist camera)" if args.vision else "state-only"
    print(f"device: {device_name(device)}; torch {torch.__version__}; ACT-SR {policy}; k = {args.k} memories, "  # noqa: T201
          f"batch {args.batch}; mean of {args.repeats} + 3 iterations\n")
    print("| sleep iteration | ms |\n|---|---|")  # noqa: T201
    for name, fn in rows:
        print(f"| {name} | {fn():.2f} |", flush=True)  # noqa: T201


if __name__ == "__main__":
    main()
