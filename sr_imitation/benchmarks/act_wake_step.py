"""Cost of one wake step of the CPU needle preset's ACT under its architecture options, measured in one run.

    python -m sr_imitation.benchmarks.act_wake_step [--repeats 30] [--threads 2] [--vision [--image_sizes 64 48]]

The CPU preset's state-only ACT (dim 128, 2 encoder layers, 1 decoder layer, chunk 16) on a batch of 32: forward
(ACT's L1 + KL loss), backward and the optimizer step, median ms per step, with and without ACT's CVAE encoder
(``use_vae``) and dropout; ratios against ACT's defaults (CVAE on, dropout 0.1) in the same run. ``--vision``: the
CPU vision preset's policy instead (the same transformer, no CVAE, dropout 0, a 64x64 wrist camera through a
ResNet-18 trained from scratch, batch 8) with the backbone's frozen batch norms (LeRobot's) and with GroupNorm (the
default without pretrained weights); ratio against frozen batch norm. ``--image_sizes 64 48``: the GroupNorm policy
at each wrist-image size instead, ratio against the first.
"""

from __future__ import annotations

import argparse
import platform

import torch
from lerobot.configs.types import FeatureType, PolicyFeature

from lerobot_policy_act_sr import ACTSRConfig, ACTSRPolicy
from sr_imitation.benchmarks.timing import median_ms

STATE_DIM, ACTION_DIM, BATCH, CHUNK = 35, 7, 32, 16
VISION_BATCH, IMAGE = 8, 64
VARIANTS = {"ACT defaults (CVAE, dropout 0.1)": {"use_vae": True, "dropout": 0.1},
            "no CVAE": {"use_vae": False, "dropout": 0.1}, "dropout 0": {"use_vae": True, "dropout": 0.0},
            "no CVAE, dropout 0 (the preset)": {"use_vae": False, "dropout": 0.0}}
VISION_VARIANTS = {"frozen batch norm (LeRobot's ACT)": {"backbone_norm": "frozen_batch"},
                   "GroupNorm (the vision preset)": {"backbone_norm": "group"}}


def _policy(vision: bool, image: int = IMAGE, **options: object) -> ACTSRPolicy:
    base = {"use_vae": False, "dropout": 0.0} if vision else {}
    cfg = ACTSRConfig(device="cpu", dim_model=128, n_heads=4, dim_feedforward=512, n_encoder_layers=2,
                      n_decoder_layers=1, n_vae_encoder_layers=2, chunk_size=CHUNK, n_action_steps=8,
                      **{**base, **options})
    cfg.input_features = {"observation.state": PolicyFeature(FeatureType.STATE, (STATE_DIM,))}
    if vision:
        cfg.input_features["observation.images.wrist"] = PolicyFeature(FeatureType.VISUAL, (3, image, image))
    else:
        cfg.input_features["observation.environment_state"] = PolicyFeature(FeatureType.ENV, (STATE_DIM,))
    cfg.output_features = {"action": PolicyFeature(FeatureType.ACTION, (ACTION_DIM,))}
    return ACTSRPolicy(cfg)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    parser.add_argument("--vision", action="store_true", help="the CPU vision preset's policy, two backbone norms")
    parser.add_argument("--image_sizes", type=int, nargs="+", default=None,
                        help="with --vision: the GroupNorm policy at these wrist-image sizes instead")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    g = torch.Generator().manual_seed(0)
    size = VISION_BATCH if args.vision else BATCH
    batch = {"observation.state": torch.randn(size, STATE_DIM, generator=g),
             "action": torch.randn(size, CHUNK, ACTION_DIM, generator=g),
             "action_is_pad": torch.zeros(size, CHUNK, dtype=torch.bool)}
    variants: dict[str, dict] = VISION_VARIANTS if args.vision else VARIANTS
    if args.vision and args.image_sizes:
        variants = {f"GroupNorm, {n}x{n} wrist image": {"backbone_norm": "group", "image": n}
                    for n in args.image_sizes}
    times = {}
    for name, options in variants.items():
        torch.manual_seed(0)
        image = int(options.get("image", IMAGE))
        policy = _policy(args.vision, **options)
        policy.train()
        optimizer = policy.config.get_optimizer_preset().build(policy.get_optim_params())
        inputs = dict(batch)
        if args.vision:
            inputs["observation.images.wrist"] = torch.rand(size, 3, image, image, generator=g)

        def step(policy: ACTSRPolicy = policy, optimizer: torch.optim.Optimizer = optimizer,
                 inputs: dict = inputs) -> None:
            loss, _ = policy.forward(dict(inputs))
            loss.backward()
            optimizer.step()
            optimizer.zero_grad()

        times[name] = median_ms(step, args.repeats, warmup=3)
    base = times[next(iter(variants))]
    print(f"machine: {platform.processor() or platform.machine()}, torch {torch.__version__}, "  # noqa: T201
          f"{args.threads} thread(s), {args.repeats} repeats, batch {size}")
    print("| variant | ms per wake step (median) | speed-up |\n|---|---|---|")  # noqa: T201
    for name, ms in times.items():
        print(f"| {name} | {ms:.1f} | {base / ms:.2f}x |")  # noqa: T201


if __name__ == "__main__":
    main()
