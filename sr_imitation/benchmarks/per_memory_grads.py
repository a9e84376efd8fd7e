"""Per-memory gradients of a sleep iteration: k backward passes, one batched backward, one vmap pass.

    python -m sr_imitation.benchmarks.per_memory_grads [--device auto|cpu|cuda] [--repeats 10] [--threads N]
        [--k 5] [--batch 8]

A sleep iteration needs the k per-memory gradients g_i = grad L_i(theta) (the rows of the Gram matrix, Eq. 5). The
sleep computes them with k forward/backward passes of batch 8 (:func:`sr_imitation.core.sleep.sleep_consolidate`),
or with ``joint_forward`` from one forward over the k batches and one backward batched over the k losses;
``torch.func.vmap(torch.func.grad(L))`` over the k memories' batches is a third way. This benchmark times the three
on the CPU needle presets' ACT-SR (state-only and vision, k = 5, batch 8 unless ``--k`` / ``--batch`` say
otherwise; the state-only presets' sleeps draw batches of 32 from 2-5 memories; random targets), counts the ATen
operations each launches (on a GPU at small sizes, the cost; the batched backward also does k times the loop's
backward arithmetic, which grows with the batch) and reports the largest difference to the k passes
relative to the largest gradient entry (float summation order only), on any device (``docs/BENCHMARKS.md``).
"""

from __future__ import annotations

import argparse

import torch
from torch.func import functional_call, grad, vmap
from torch.utils._python_dispatch import TorchDispatchMode

from sr_imitation.benchmarks.device import (
    ACTION_DIM,
    CHUNK,
    STATE_DIM,
    K,
    act_policy,
    device_name,
    parse_device_args,
    timed_ms,
)

BATCH = 8


class OpCount(TorchDispatchMode):
    """Counts the ATen operations that reach the kernels (after autograd and vmap's batching): on a GPU at these sizes
    each is a kernel launch or a view, so the count is the launch-bound cost, measured without a GPU."""

    def __init__(self) -> None:
        super().__init__()
        self.ops = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.ops += 1
        return func(*args, **(kwargs or {}))


def count_ops(fn) -> int:
    with OpCount() as counter:
        fn()
    return counter.ops


METHODS = {
    "loop": "k forward + k backward passes (the sleep's default)",
    "joint": "one forward + one backward batched over the k losses (sleep.joint_forward)",
    "vmap": "torch.func.vmap(torch.func.grad(...)) over the k batches",
}


def per_memory_gradients(device: torch.device, vision: bool, repeats: int, k: int = K,
                         batch: int = BATCH) -> dict[str, dict[str, float]]:
    """For each of :data:`METHODS`: milliseconds, ATen operations and largest difference to ``loop`` (relative to the
    largest gradient entry) of the ``k`` per-memory gradients of the ACT-SR chunk loss, ``batch`` observations each."""
    K, BATCH = k, batch  # noqa: N806 - the module's defaults, overridden
    torch.manual_seed(0)
    policy = act_policy(device, vision)
    policy.eval()
    model = policy.model
    g = torch.Generator().manual_seed(0)
    obs = {"observation.state": torch.randn(K, BATCH, STATE_DIM, generator=g)}
    if vision:
        obs["observation.images.wrist"] = torch.rand(K, BATCH, 3, 64, 64, generator=g)
    else:
        obs["observation.environment_state"] = obs["observation.state"].clone()
    obs = {k: v.to(device) for k, v in obs.items()}
    target = torch.randn(K, BATCH, CHUNK, ACTION_DIM, generator=g).to(device)
    names = [n for n, p in model.named_parameters() if p.requires_grad]
    buffers = dict(model.named_buffers())

    def chunk(params: dict[str, torch.Tensor], o: dict[str, torch.Tensor]) -> torch.Tensor:
        batch = dict(o)
        if vision:
            batch["observation.images"] = [o["observation.images.wrist"]]
        return functional_call(model, (params, buffers), (batch,))[0]

    def loss(params: dict[str, torch.Tensor], o: dict[str, torch.Tensor], t: torch.Tensor) -> torch.Tensor:
        return (chunk(params, o) - t).pow(2).mean()

    live = dict(model.named_parameters())
    frozen = {n: live[n].detach() for n in names}
    eye = torch.eye(K, device=device)

    def loop() -> list[tuple[torch.Tensor, ...]]:  # [memory][parameter]
        return [torch.autograd.grad(loss(live, {k: v[i] for k, v in obs.items()}, target[i]),
                                    [live[n] for n in names]) for i in range(K)]

    def joint() -> tuple[torch.Tensor, ...]:  # [parameter][memory, ...]
        flat = {k: v.reshape(K * BATCH, *v.shape[2:]) for k, v in obs.items()}
        losses = (chunk(live, flat) - target.reshape(K * BATCH, CHUNK, ACTION_DIM)).pow(2).reshape(K, -1).mean(1)
        return torch.autograd.grad(losses, [live[n] for n in names], grad_outputs=eye, is_grads_batched=True)

    def vectorized() -> dict[str, torch.Tensor]:  # {parameter: [memory, ...]}
        return vmap(grad(loss), in_dims=(None, 0, 0))(frozen, obs, target)

    ref = loop()
    scale = max(float(r.abs().max()) for grads in ref for r in grads)
    as_ref = {"loop": lambda got: got, "joint": lambda got: [[gr[i] for gr in got] for i in range(K)],
              "vmap": lambda got: [[got[n][i] for n in names] for i in range(K)]}
    out = {}
    for name, fn in (("loop", loop), ("joint", joint), ("vmap", vectorized)):
        got = as_ref[name](fn())
        diff = max(float((a - b).abs().max()) for ga, gb in zip(got, ref, strict=True)
                   for a, b in zip(ga, gb, strict=True))
        out[name] = {"ms": timed_ms(fn, repeats, device), "ops": count_ops(fn), "difference": diff / scale}
    return out


def main() -> None:
    def sizes(parser: argparse.ArgumentParser) -> None:
        parser.add_argument("--k", type=int, default=K, help="memories per iteration")
        parser.add_argument("--batch", type=int, default=BATCH, help="observations per memory batch")

    device, args = parse_device_args(__doc__, repeats=10, extra=sizes)
    print(f"device: {device_name(device)}; torch {torch.__version__}; k = {args.k} memories, batch {args.batch}; "  # noqa: T201
          f"median of {args.repeats}\n")
    print("| policy | method | ms | vs loop | ATen ops | max difference / max entry |\n"  # noqa: T201
          "|---|---|---|---|---|---|")
    for vision in (False, True):
        rows = per_memory_gradients(device, vision, args.repeats, args.k, args.batch)
        for name, r in rows.items():
            print(f"| ACT-SR {'vision' if vision else 'state-only'} | {METHODS[name]} | {r['ms']:.2f} | "  # noqa: T201
                  f"{rows['loop']['ms'] / r['ms']:.2f}x | {r['ops']:.0f} | {r['difference']:.1e} |")


if __name__ == "__main__":
    main()
