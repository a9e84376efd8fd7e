"""The hot paths of both substrates on whatever device is present: one wake step, one sleep iteration, one SAC update.

    python -m sr_imitation.benchmarks.device [--device auto|cpu|cuda|mps] [--repeats 20] [--threads N]

Rows, each the median wall time of one call in milliseconds (CUDA synchronized before and after each call):

- ACT wake step, the CPU needle preset's state-only policy (dim 128, 2 encoder layers, chunk 16, batch 32):
  forward (L1), backward, AdamW step;
- ACT wake step, the vision preset's policy (a 64x64 wrist camera through a GroupNorm ResNet-18, batch 8);
- ACT-SR sleep iteration, k = 5 actor memories of 1024 observations (state-only policy, batch 8 per memory, the
  SurgicAI table's settings): k per-memory gradients, the Gram matrix, the exact Nash solve, the Adam step; the same
  with ``joint_forward`` (one forward over the k batches, one backward batched over the k losses); the same on the
  vision preset;
- SAC update (the paper's MT5 networks, batch 256): critic, actor and temperature steps;
- SAC sleep iteration, k = 5 critic memories (batch 64 per memory, the MT5 table's settings).

Everything is created on the device (policy, optimizer state, memories' frozen models); the memories' buffers stay
on the host and each iteration's sampled batch is copied to the device, as a data loader's would be. The Nash solve
runs on the host on the k x k Gram matrix (a 5 x 5 copy per iteration). Run it on a GPU machine and record the table
in docs/BENCHMARKS.md next to a CPU run of the same command.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time
from collections.abc import Callable

import numpy as np
import torch
from lerobot.configs.types import FeatureType, PolicyFeature

from lerobot_policy_act_sr import ACTSRConfig, ACTSRPolicy
from lerobot_policy_act_sr.actor_memory import ActorMemory
from sr_imitation.benchmarks.sac import critic_memories, replay_buffer
from sr_imitation.core.excitability import ExcitabilityConfig
from sr_imitation.core.sleep import sleep_consolidate
from sr_imitation.envs.metaworld.tasks import OBS_DIM
from sr_imitation.stream.config import StreamSleepConfig
from sr_imitation.substrates.act.config import SurgicAISleepConfig
from sr_imitation.substrates.sac.config import SACConfig
from sr_imitation.substrates.sac.sac import SACAgent

STATE_DIM, ACTION_DIM, CHUNK, K = 35, 7, 16, 5


def resolve_device(name: str) -> torch.device:
    """``auto``: CUDA if present, then MPS, else the CPU; a named device must be available (one-line error)."""
    if name == "auto":
        if torch.cuda.is_available():
            return torch.device("cuda")
        return torch.device("mps" if torch.backends.mps.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device=cuda: no CUDA device here (torch.cuda.is_available() is false)")
    if device.type == "mps" and not torch.backends.mps.is_available():
        raise SystemExit("--device=mps: no MPS device here")
    return device


def synchronized_clock(device: torch.device) -> float:
    """``time.perf_counter()`` once the device has finished its queued work."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    elif device.type == "mps":
        torch.mps.synchronize()
    return time.perf_counter()


def timed_ms(fn: Callable[[], object], repeats: int, device: torch.device, warmup: int = 3) -> float:
    """Median milliseconds of ``fn()`` with the device synchronized around each call."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = synchronized_clock(device)
        fn()
        times.append(synchronized_clock(device) - t0)
    return 1e3 * statistics.median(times)


def act_policy(device: torch.device, vision: bool) -> ACTSRPolicy:
    """The CPU needle presets' ACT-SR (``configs/needle_cpu.json``, ``needle_cpu_vision.json``) on ``device``."""
    cfg = ACTSRConfig(device=device.type, dim_model=128, n_heads=4, dim_feedforward=512, n_encoder_layers=2,
                      n_decoder_layers=1, chunk_size=CHUNK, n_action_steps=8, use_vae=False, dropout=0.0,
                      backbone_norm="group", pretrained_backbone_weights=None)
    cfg.input_features = {"observation.state": PolicyFeature(FeatureType.STATE, (STATE_DIM,))}
    if vision:
        cfg.input_features["observation.images.wrist"] = PolicyFeature(FeatureType.VISUAL, (3, 64, 64))
    else:
        cfg.input_features["observation.environment_state"] = PolicyFeature(FeatureType.ENV, (STATE_DIM,))
    cfg.output_features = {"action": PolicyFeature(FeatureType.ACTION, (ACTION_DIM,))}
    return ACTSRPolicy(cfg).to(device)


def act_batch(n: int, vision: bool, device: torch.device, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    batch = {"observation.state": torch.randn(n, STATE_DIM, generator=g),
             "action": torch.randn(n, CHUNK, ACTION_DIM, generator=g),
             "action_is_pad": torch.zeros(n, CHUNK, dtype=torch.bool)}
    if vision:
        batch["observation.images.wrist"] = torch.rand(n, 3, 64, 64, generator=g)
    else:
        batch["observation.environment_state"] = batch["observation.state"].clone()
    return {k: v.to(device) for k, v in batch.items()}


def bench_act_wake(device: torch.device, vision: bool, repeats: int) -> float:
    torch.manual_seed(0)
    policy = act_policy(device, vision)
    policy.train()
    optimizer = policy.config.get_optimizer_preset().build(policy.get_optim_params())
    batch = act_batch(8 if vision else 32, vision, device)

    def step() -> None:
        loss, _ = policy.forward(dict(batch))
        loss.backward()
        optimizer.step()
        optimizer.zero_grad()

    return timed_ms(step, repeats, device)


def bench_act_sleep(device: torch.device, repeats: int, vision: bool = False, joint_forward: bool = False,
                    k: int = K, batch: int = 8, memory_class: type[ActorMemory] = ActorMemory) -> float:
    """One ACT-SR sleep iteration over ``k`` memories of 1024 observations, ``batch`` from each (mean over
    ``repeats`` + 3 iterations). Each memory names its own checkpoint (``skill_<i>/wake``), as the stream's do.

    ``vision``: the vision preset's policy and memories (64x64 uint8 wrist images, as the memories store them);
    ``joint_forward``: :class:`~sr_imitation.core.sleep.SleepConfig`'s one forward over the k batches and one backward
    batched over the k losses (same values up to float order); ``memory_class``: the memories' class (a subclass
    changes how they group, :mod:`sr_imitation.benchmarks.sleep_joint_forward`)."""
    torch.manual_seed(0)
    policy = act_policy(device, vision=vision)
    policy.eval()

    def to_device(raw: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:  # the substrate's preprocessor's move
        state = raw["observation.state"].to(device)
        if vision:
            return {"observation.state": state,
                    "observation.images.wrist": raw["observation.images.wrist"].to(device).float() / 255.0}
        return {"observation.state": state, "observation.environment_state": state}

    policy.set_observation_normalizer(to_device)
    g = torch.Generator().manual_seed(1)
    memories = []
    for i in range(k):
        obs = {"observation.state": torch.randn(1024, STATE_DIM, generator=g)}
        if vision:
            obs["observation.images.wrist"] = torch.randint(0, 256, (1024, 3, 64, 64), generator=g, dtype=torch.uint8)
        memories.append(memory_class.from_observations(f"skill{i}", policy.memory_chunk, obs,
                                                       snapshot=f"skill_{i + 1}/wake"))
        with torch.no_grad():
            for p in policy.parameters():
                p.add_(0.01 * torch.randn_like(p))
    params = [p for p in policy.parameters() if p.requires_grad]
    anchor = [p.detach().clone() for p in params]
    cfg = SurgicAISleepConfig(max_iterations=repeats + 3, early_stop_tol=0.0, joint_forward=joint_forward,
                              batch_size=batch)
    t0 = synchronized_clock(device)
    result = sleep_consolidate(params, policy.memory_chunk, memories, cfg, anchor_params=anchor, progress=False)
    return 1e3 * (synchronized_clock(device) - t0) / result.stop_iteration


def bench_sac_update(device: torch.device, repeats: int) -> float:
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    replay = replay_buffer(2_000)
    cfg = SACConfig()
    agent = SACAgent(cfg, ExcitabilityConfig(), device=device)
    agent.normalizer.update(replay.obs[:1000])
    return timed_ms(lambda: agent.update(replay.batch(replay.indices(cfg.batch_size, rng), device), 1e-3), repeats,
                    device)


def bench_sac_sleep(device: torch.device, repeats: int) -> float:
    torch.manual_seed(0)
    agent = SACAgent(SACConfig(), ExcitabilityConfig(), device=device)
    agent.normalizer.update(np.random.default_rng(0).normal(size=(100, OBS_DIM)))
    memories = critic_memories(agent, K)
    params = agent.actor_parameters()
    cfg = StreamSleepConfig.mt5(max_iterations=repeats + 3, early_stop_tol=0.0, anchor_tau=None)
    anchor = [p.detach().clone() for p in params]
    t0 = synchronized_clock(device)
    result = sleep_consolidate(params, agent.policy_fn, memories, cfg, anchor_params=anchor, progress=False)
    return 1e3 * (synchronized_clock(device) - t0) / result.stop_iteration


def device_name(device: torch.device) -> str:
    if device.type == "cuda":
        return f"{torch.cuda.get_device_name(device)} (CUDA {torch.version.cuda})"
    return f"{device.type} ({platform.processor() or platform.machine()}, {torch.get_num_threads()} threads)"


def parse_device_args(description: str, repeats: int,
                      extra: Callable[[argparse.ArgumentParser], None] | None = None,
                      ) -> tuple[torch.device, argparse.Namespace]:
    """The device benchmarks' flags (``--device``, ``--repeats``, ``--threads``, and what ``extra`` adds): the
    device, the arguments; sets torch's thread count."""
    parser = argparse.ArgumentParser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="auto")
    parser.add_argument("--repeats", type=int, default=repeats)
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    if extra is not None:
        extra(parser)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    return resolve_device(args.device), args


def main() -> None:
    device, args = parse_device_args(__doc__, repeats=20)
    rows = [
        ("ACT wake step, state-only preset (batch 32)", lambda: bench_act_wake(device, False, args.repeats)),
        ("ACT wake step, vision preset (64x64 wrist camera, batch 8)", lambda: bench_act_wake(device, True,
                                                                                             args.repeats)),
        (f"ACT-SR sleep iteration (k = {K} actor memories, batch 8 each)", lambda: bench_act_sleep(device,
                                                                                                   args.repeats)),
        (f"ACT-SR sleep iteration, joint forward (k = {K}, one forward, one batched backward)",
         lambda: bench_act_sleep(device, args.repeats, joint_forward=True)),
        (f"ACT-SR sleep iteration, vision preset (k = {K} memories of 64x64 images, batch 8 each)",
         lambda: bench_act_sleep(device, args.repeats, vision=True)),
        ("SAC update (the paper's MT5 networks, batch 256)", lambda: bench_sac_update(device, args.repeats)),
        (f"SAC sleep iteration (k = {K} critic memories, batch 64 each)", lambda: bench_sac_sleep(device,
                                                                                                  args.repeats)),
    ]
    print(f"device: {device_name(device)}; torch {torch.__version__}; median of {args.repeats}\n")
    print("| hot path | ms per call |\n|---|---|")
    for name, fn in rows:
        print(f"| {name} | {fn():.2f} |", flush=True)


if __name__ == "__main__":
    main()
