"""Benchmark of the consolidation core: Nash solve time and sleep-iteration overhead.

    python -m sr_imitation.benchmarks.core [--threads 2] [--repeats 200]

Prints two markdown tables (copied into docs/BENCHMARKS.md):

1. Nash solve time per call for k = 2..16 at 5 and 50 Frank-Wolfe iterations (cold start, duality-gap stop
   disabled so every iteration runs; and warm-started as in a sleep phase), next to one forward+backward pass
   of the paper's 2x256 MLP actor (39-d Meta-World state, Gaussian head for 4-d actions) at batch 64.
2. One full sleep iteration (:func:`sleep_consolidate`, k memories, batch 64 each) against the floor of k
   forward+backward passes on the same batches, measured in the same run; the ratio is the overhead of
   gradient flattening, the Gram matrix, the solve, the combination and the Adam step.
"""

from __future__ import annotations

import argparse
import platform
import statistics

import numpy as np
import torch
from torch import nn

from sr_imitation.benchmarks.timing import median_ms
from sr_imitation.core.aggregation import FrankWolfeNashAggregator, NashAggregator
from sr_imitation.core.memory import OutputDistillationMemory
from sr_imitation.core.sleep import SleepConfig, sleep_consolidate

STATE_DIM, ACTION_DIM, HIDDEN, BATCH = 39, 4, 256, 64


def mlp_actor(hidden: int = HIDDEN) -> nn.Module:
    """The paper's actor size by default: 2 x 256 ReLU, outputs mean and log-std of a 4-d Gaussian."""
    return nn.Sequential(
        nn.Linear(STATE_DIM, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
        nn.Linear(hidden, 2 * ACTION_DIM),
    )


def bench_nash(repeats: int) -> list[dict[str, float]]:
    rng = np.random.default_rng(0)
    rows = []
    for k in (2, 3, 4, 5, 8, 12, 16):
        jac = rng.normal(size=(k, 1000))
        gram = jac @ jac.T
        row: dict[str, float] = {"k": k}
        for iters in ("exact", 5, 50):
            make = (lambda **kw: NashAggregator(**kw)) if iters == "exact" else (
                lambda i=iters, **kw: FrankWolfeNashAggregator(iterations=i, **kw))
            cold = make(warm_start=False) if iters == "exact" else make(tol=0.0, warm_start=False)
            row[f"cold_{iters}"] = median_ms(lambda a=cold, g=gram: a(g), repeats, warmup=5)
            warm = make()
            # Warm start as in sleep: consecutive Gram matrices from noisy minibatch gradients.
            grams = [(jac + 0.3 * rng.normal(size=jac.shape)) for _ in range(repeats + 5)]
            grams = [g @ g.T for g in grams]
            it = iter(grams)
            row[f"warm_{iters}"] = median_ms(lambda a=warm, it=it: a(next(it)), repeats, warmup=5)
        rows.append(row)
    return rows


def bench_actor_step(repeats: int) -> float:
    actor = mlp_actor()
    x, y = torch.randn(BATCH, STATE_DIM), torch.randn(BATCH, 2 * ACTION_DIM)

    def step() -> None:
        actor.zero_grad(set_to_none=True)
        nn.functional.mse_loss(actor(x), y).backward()

    return median_ms(step, repeats, warmup=5)


def bench_sleep(k: int, iterations: int, hidden: int = HIDDEN, batch: int = BATCH, rounds: int = 5) -> dict:
    """Per-iteration time of a sleep phase against two floors, alternating ``rounds`` times:

    * ``floor``: k forward+backward passes on fixed batches (the floor of any per-memory method);
    * ``floor_step``: what any k-memory gradient step must do besides: drawing the k batches from the buffers
      and one Adam step on the summed gradient.
    """
    torch.manual_seed(0)
    actor = mlp_actor(hidden)
    snapshots = [mlp_actor(hidden) for _ in range(k)]
    memories = [
        OutputDistillationMemory.from_snapshot(f"s{i}", lambda o, a=snap: a(o["state"]),
                                               {"state": torch.randn(1000, STATE_DIM)})
        for i, snap in enumerate(snapshots)
    ]
    policy = lambda obs: actor(obs["state"])  # noqa: E731
    params = list(actor.parameters())
    gen = torch.Generator().manual_seed(0)
    batches = [m.sample(batch, gen) for m in memories]
    # Plateau stopping off so that every iteration runs; anchor on (the full update of Algorithm 1, line 11).
    cfg = SleepConfig(max_iterations=iterations, batch_size=batch, fw_iterations=50, anchor_tau=None,
                      early_stop_tol=0.0)
    anchor = [p.detach().clone() for p in params]
    adam = torch.optim.Adam(params, lr=1e-9, fused=True)

    def floor() -> None:  # k forward+backward passes on fixed batches, nothing else
        for _ in range(iterations):
            for m, b in zip(memories, batches, strict=True):
                torch.autograd.grad(m.loss(policy, b), params)

    def floor_step() -> None:  # + batch sampling and one Adam step: a plain summed-loss update
        for _ in range(iterations):
            adam.zero_grad(set_to_none=True)
            for m in memories:
                m.objective(policy, batch, gen).backward()
            adam.step()

    def sleep() -> None:
        sleep_consolidate(params, policy, memories, cfg, anchor_params=anchor, progress=False)

    times: dict[str, list[float]] = {"floor": [], "floor_step": [], "sleep": []}
    for _ in range(rounds):
        for name, fn in (("floor", floor), ("floor_step", floor_step), ("sleep", sleep)):
            times[name].append(median_ms(fn, 1, warmup=0) / iterations)
    return {"k": k, **{name: statistics.median(v) for name, v in times.items()}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    parser.add_argument("--repeats", type=int, default=200)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(f"# core benchmark: torch {torch.__version__}, {args.threads} threads, "
          f"{platform.processor() or platform.machine()}, python {platform.python_version()}\n")
    actor_ms = bench_actor_step(args.repeats)
    print(f"2x256 MLP actor forward+backward, batch {BATCH}: {actor_ms:.3f} ms\n")
    print("| k | exact cold (ms) | exact warm (ms) | FW-5 cold | FW-50 cold | FW-5 warm | FW-50 warm "
          "| exact warm / actor f+b |")
    print("|---|---|---|---|---|---|---|---|")
    for r in bench_nash(args.repeats):
        print(f"| {r['k']} | {r['cold_exact']:.3f} | {r['warm_exact']:.3f} | {r['cold_5']:.3f} | {r['cold_50']:.3f} "
              f"| {r['warm_5']:.3f} | {r['warm_50']:.3f} | {r['warm_exact'] / actor_ms:.2f} |")
    print("\n| actor | batch | k | k x (fwd+bwd) (ms) | + sampling + Adam (ms) | sleep iteration (ms) "
          "| sleep / k x (fwd+bwd) | sleep / (+ sampling + Adam) |")
    print("|---|---|---|---|---|---|---|---|")
    for hidden, batch, ks in ((HIDDEN, BATCH, (2, 3, 5, 8)), (1024, 256, (2, 5))):
        for k in ks:
            r = bench_sleep(k, iterations=max(10, args.repeats // (4 if hidden > HIDDEN else 1)), hidden=hidden,
                            batch=batch)
            print(f"| 2x{hidden} | {batch} | {k} | {r['floor']:.3f} | {r['floor_step']:.3f} | {r['sleep']:.3f} "
                  f"| {r['sleep'] / r['floor']:.2f} | {r['sleep'] / r['floor_step']:.2f} |")


if __name__ == "__main__":
    main()
