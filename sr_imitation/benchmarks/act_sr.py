"""Benchmark of ACT-SR training costs against plain ACT, measured in one run on the same inputs.

    python -m sr_imitation.benchmarks.act_sr [--image_size 64] [--dim_model 256] [--repeats 10]

``--image_size 0``: the state-only policy (the state also as the environment state, as the state presets feed it).

Rows (median ms per call; ratios against the plain ACT step on the same batch):

* plain ACT training step: forward + backward + AdamW on a batch of 8 (no memories);
* ACT-SR wake step at k = 5 (4 earlier memories, distillation batch 8 each) with the snapshots' chunks cached in
  the memories (what ACT-SR does) and with the 4 snapshots re-run on every step (the naive alternative); and with
  the memories in groups of one, one student forward each, as the stream had them before 2026-11-27 (each memory
  names its own checkpoint, which split the grouping: :mod:`sr_imitation.benchmarks.sleep_joint_forward`);
  the floor is the BC step plus one forward+backward of the student on the 32 distillation observations;
* one sleep iteration over k = 5 memories (batch 8 each) against 5 forward+backward passes of the student.
"""

from __future__ import annotations

import argparse
import copy
import platform
import time

import torch
from lerobot.configs.types import FeatureType, PolicyFeature

from lerobot_policy_act_sr import ACTSRConfig, ACTSRPolicy
from lerobot_policy_act_sr.actor_memory import ActorMemory
from sr_imitation.benchmarks.sleep_joint_forward import GroupsOfOne
from sr_imitation.benchmarks.timing import median_ms
from sr_imitation.core.sleep import sleep_consolidate
from sr_imitation.substrates.act.config import SurgicAISleepConfig

STATE_DIM, ACTION_DIM, BATCH, K = 35, 7, 8, 5


def _policy(image_size: int, dim_model: int) -> ACTSRPolicy:
    cfg = ACTSRConfig(device="cpu", dim_model=dim_model, n_heads=8, dim_feedforward=4 * dim_model,
                      n_encoder_layers=2, n_vae_encoder_layers=2, chunk_size=16, n_action_steps=16,
                      use_images=image_size > 0)
    cfg.input_features = {"observation.state": PolicyFeature(FeatureType.STATE, (STATE_DIM,))}
    if image_size:
        cfg.input_features["observation.images.wrist"] = PolicyFeature(FeatureType.VISUAL, (3, image_size, image_size))
    else:
        cfg.input_features["observation.environment_state"] = PolicyFeature(FeatureType.ENV, (STATE_DIM,))
    cfg.output_features = {"action": PolicyFeature(FeatureType.ACTION, (ACTION_DIM,))}
    policy = ACTSRPolicy(cfg)
    policy.set_observation_normalizer(
        lambda raw: {k: (v.float() / 255.0 if v.dtype == torch.uint8 else v) for k, v in raw.items()})
    return policy


def _observations(n: int, image_size: int, seed: int) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    if not image_size:
        state = torch.randn(n, STATE_DIM, generator=g)
        return {"observation.state": state, "observation.environment_state": state.clone()}
    return {"observation.images.wrist": torch.randint(0, 255, (n, 3, image_size, image_size), generator=g,
                                                      dtype=torch.uint8),
            "observation.state": torch.randn(n, STATE_DIM, generator=g)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--image_size", type=int, default=64)
    parser.add_argument("--dim_model", type=int, default=256)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    policy = _policy(args.image_size, args.dim_model)
    snapshots = [copy.deepcopy(policy) for _ in range(K - 1)]
    for i, snap in enumerate(snapshots):  # distinct frozen snapshots
        with torch.no_grad():
            for p in snap.parameters():
                p.add_(0.01 * (i + 1) * torch.randn_like(p))
        snap.requires_grad_(False)
    memories = [ActorMemory.from_observations(f"s{i}", snap.memory_chunk, _observations(256, args.image_size, i),
                                              snapshot=f"skill_{i + 1}/wake")  # as the stream names them
                for i, snap in enumerate(snapshots)]
    g = torch.Generator().manual_seed(0)
    batch = {k: v.float() / 255.0 if v.dtype == torch.uint8 else v
             for k, v in _observations(BATCH, args.image_size, 99).items()}
    batch["action"] = torch.randn(BATCH, 16, ACTION_DIM, generator=g)
    batch["action_is_pad"] = torch.zeros(BATCH, 16, dtype=torch.bool)
    optimizer = torch.optim.AdamW(policy.parameters(), lr=1e-9)
    gen = torch.Generator().manual_seed(0)

    def train_step() -> None:
        policy.train()
        optimizer.zero_grad()
        loss, _ = policy.forward(batch)
        loss.backward()
        optimizer.step()

    def recomputing_step() -> None:  # the naive alternative: re-run every snapshot on its batch each step
        policy.train()
        optimizer.zero_grad()
        loss, _ = policy.forward(batch)
        obs_list, targets = [], []
        for memory, snap in zip(memories, snapshots, strict=True):
            obs = {k.removeprefix("input."): v for k, v in memory.sample(BATCH, gen).items() if k != "target"}
            with torch.no_grad():
                targets.append(snap.memory_chunk(obs))
            obs_list.append(obs)
        joint = {k: torch.cat([o[k] for o in obs_list]) for k in obs_list[0]}
        pred = policy.memory_chunk(joint)  # one student pass, as in the cached step
        loss = loss + 0.5 * len(memories) * (pred - torch.cat(targets)).pow(2).flatten(1).sum(1).mean()
        loss.backward()
        optimizer.step()

    def floor_step() -> None:  # BC step + one forward/backward on the 32 distillation observations
        policy.train()
        optimizer.zero_grad()
        loss, _ = policy.forward(batch)
        obs = _observations(BATCH * (K - 1), args.image_size, 5)
        loss = loss + policy.memory_chunk(obs).pow(2).mean()
        loss.backward()
        optimizer.step()

    plain = median_ms(train_step, args.repeats)
    floor = median_ms(floor_step, args.repeats)
    policy.set_wake_memories(memories, weight=0.5)
    cached = median_ms(train_step, args.repeats)
    policy.set_wake_memories([GroupsOfOne(m.skill, dict(m.tensors), dict(m.config)) for m in memories], weight=0.5)
    ungrouped = median_ms(train_step, args.repeats)
    policy.set_wake_memories([], 0.0)
    recomputed = median_ms(recomputing_step, args.repeats)

    params = [p for p in policy.parameters() if p.requires_grad]
    all_memories = [*memories, ActorMemory.from_observations("s4", policy.memory_chunk,
                                                             _observations(256, args.image_size, 4))]
    sleep_cfg = SurgicAISleepConfig(max_iterations=args.repeats, early_stop_tol=0.0)

    def k_passes() -> None:
        for m in all_memories:
            torch.autograd.grad(m.objective(policy.memory_chunk, BATCH, gen), params, allow_unused=True)

    passes = median_ms(k_passes, args.repeats)
    t0 = time.perf_counter()
    sleep_consolidate(params, policy.memory_chunk, all_memories, sleep_cfg, anchor_params=[p.detach().clone()
                      for p in params], progress=False)
    sleep_ms = 1e3 * (time.perf_counter() - t0) / args.repeats

    n_params = sum(p.numel() for p in params)
    inputs = f"{args.image_size}x{args.image_size} wrist images" if args.image_size else "state only"
    print(f"# ACT-SR benchmark: {inputs}, dim_model {args.dim_model}, "
          f"{n_params / 1e6:.1f}M parameters, batch {BATCH}, torch {torch.__version__}, {args.threads} threads, "
          f"{platform.machine()}\n")
    print("| step | ms | ratio to plain ACT step |")
    print("|---|---|---|")
    print(f"| plain ACT step (BC only) | {plain:.1f} | 1.00 |")
    print(f"| floor: BC + one fwd/bwd on {BATCH * (K - 1)} distillation observations | {floor:.1f} | "
          f"{floor / plain:.2f} |")
    print(f"| ACT-SR wake step, k = {K}, cached snapshot chunks | {cached:.1f} | {cached / plain:.2f} |")
    print(f"| ACT-SR wake step, k = {K}, snapshots recomputed each step | {recomputed:.1f} | "
          f"{recomputed / plain:.2f} |")
    print(f"| ACT-SR wake step, k = {K}, cached, memories in groups of one (before 2026-11-27) | {ungrouped:.1f} | "
          f"{ungrouped / plain:.2f} |")
    print(f"\n| sleep | ms | ratio |\n|---|---|---|\n| {K} x (fwd+bwd) of the student, batch {BATCH} | "
          f"{passes:.1f} | 1.00 |\n| one sleep iteration, k = {K} | {sleep_ms:.1f} | {sleep_ms / passes:.2f} |")


if __name__ == "__main__":
    main()
