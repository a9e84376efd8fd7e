"""Per-memory gradients of a sleep iteration: k backward passes (what the sleep does) against one vectorized pass.

    python -m sr_imitation.benchmarks.per_memory_grads [--device auto|cpu|cuda] [--repeats 10] [--threads N]

A sleep iteration needs the k per-memory gradients g_i = grad L_i(theta) (the rows of the Gram matrix, Eq. 5). The
sleep computes them with k forward/backward passes of batch 8 (:func:`sr_imitation.core.sleep.sleep_consolidate`);
``torch.func.vmap(torch.func.grad(L))`` over the k memories' batches computes the same k gradients in one batched
pass. This benchmark times both on the CPU needle presets' ACT-SR (state-only and vision, k = 5, batch 8, random
targets) and reports the largest difference between them relative to the largest gradient entry (float summation
order only). It decides whether a
vectorized sleep is worth adding: on the VM's CPU it is for the state-only policy and is not for the vision one; on a
GPU, where the k passes are launch-bound, it is to be measured (``docs/BENCHMARKS.md``).
"""

from __future__ import annotations

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


def per_memory_gradients(device: torch.device, vision: bool, repeats: int) -> dict[str, float]:
    """Milliseconds and ATen operations of the k per-memory gradients of the ACT-SR chunk loss, by k backward passes
    (``loop_*``) and by one vmap pass (``vmap_*``), and their largest difference relative to the largest gradient
    entry (``difference``)."""
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

    def loss(params: dict[str, torch.Tensor], o: dict[str, torch.Tensor], t: torch.Tensor) -> torch.Tensor:
        batch = dict(o)
        if vision:
            batch["observation.images"] = [o["observation.images.wrist"]]
        chunk = functional_call(model, (params, buffers), (batch,))[0]
        return (chunk - t).pow(2).mean()

    live = dict(model.named_parameters())
    frozen = {n: live[n].detach() for n in names}

    def loop() -> list[tuple[torch.Tensor, ...]]:
        return [torch.autograd.grad(loss(live, {k: v[i] for k, v in obs.items()}, target[i]),
                                    [live[n] for n in names]) for i in range(K)]

    def vectorized() -> dict[str, torch.Tensor]:
        return vmap(grad(loss), in_dims=(None, 0, 0))(frozen, obs, target)

    ref, vec = loop(), vectorized()
    scale = max(float(r.abs().max()) for grads in ref for r in grads)
    diff = max(float((vec[n][i] - ref[i][j]).abs().max()) for i in range(K) for j, n in enumerate(names)) / scale
    return {"loop_ms": timed_ms(loop, repeats, device), "vmap_ms": timed_ms(vectorized, repeats, device),
            "loop_ops": count_ops(loop), "vmap_ops": count_ops(vectorized), "difference": diff}


def main() -> None:
    device, args = parse_device_args(__doc__, repeats=10)
    print(f"device: {device_name(device)}; torch {torch.__version__}; k = {K} memories, batch {BATCH}; "  # noqa: T201
          f"median of {args.repeats}\n")
    print("| policy | k backward passes (ms) | one vmap pass (ms) | ratio | ATen ops: k passes / vmap | "  # noqa: T201
          "max difference / max entry |\n|---|---|---|---|---|---|")
    for vision in (False, True):
        r = per_memory_gradients(device, vision, args.repeats)
        print(f"| ACT-SR {'vision' if vision else 'state-only'} | {r['loop_ms']:.2f} | {r['vmap_ms']:.2f} | "  # noqa: T201
              f"{r['loop_ms'] / r['vmap_ms']:.2f}x | {r['loop_ops']:.0f} / {r['vmap_ops']:.0f} | "
              f"{r['difference']:.1e} |")


if __name__ == "__main__":
    main()
