"""Cost of one wake step of the CPU needle preset's ACT under its architecture options, measured in one run.

    python -m sr_imitation.benchmarks.act_wake_step [--repeats 30] [--threads 2]

The CPU preset's state-only ACT (dim 128, 2 encoder layers, 1 decoder layer, chunk 16) on a batch of 32: forward
(ACT's L1 + KL loss), backward and the optimizer step, median ms per step, with and without ACT's CVAE encoder
(``use_vae``) and dropout; ratios against ACT's defaults (CVAE on, dropout 0.1) in the same run.
"""

from __future__ import annotations

import argparse
import platform

import torch
from lerobot.configs.types import FeatureType, PolicyFeature

from lerobot_policy_act_sr import ACTSRConfig, ACTSRPolicy
from sr_imitation.benchmarks.timing import median_ms

STATE_DIM, ACTION_DIM, BATCH, CHUNK = 35, 7, 32, 16
VARIANTS = {"ACT defaults (CVAE, dropout 0.1)": (True, 0.1), "no CVAE": (False, 0.1), "dropout 0": (True, 0.0),
            "no CVAE, dropout 0 (the preset)": (False, 0.0)}


def _policy(use_vae: bool, dropout: float) -> ACTSRPolicy:
    cfg = ACTSRConfig(device="cpu", use_vae=use_vae, dropout=dropout, dim_model=128, n_heads=4,
                      dim_feedforward=512, n_encoder_layers=2, n_decoder_layers=1, n_vae_encoder_layers=2,
                      chunk_size=CHUNK, n_action_steps=8)
    cfg.input_features = {"observation.state": PolicyFeature(FeatureType.STATE, (STATE_DIM,)),
                          "observation.environment_state": PolicyFeature(FeatureType.ENV, (STATE_DIM,))}
    cfg.output_features = {"action": PolicyFeature(FeatureType.ACTION, (ACTION_DIM,))}
    return ACTSRPolicy(cfg)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    g = torch.Generator().manual_seed(0)
    batch = {"observation.state": torch.randn(BATCH, STATE_DIM, generator=g),
             "action": torch.randn(BATCH, CHUNK, ACTION_DIM, generator=g),
             "action_is_pad": torch.zeros(BATCH, CHUNK, dtype=torch.bool)}
    times = {}
    for name, (use_vae, dropout) in VARIANTS.items():
        torch.manual_seed(0)
        policy = _policy(use_vae, dropout)
        policy.train()
        optimizer = policy.config.get_optimizer_preset().build(policy.get_optim_params())

        def step(policy: ACTSRPolicy = policy, optimizer: torch.optim.Optimizer = optimizer) -> None:
            loss, _ = policy.forward(dict(batch))
            loss.backward()
            optimizer.step()
            optimizer.zero_grad()

        times[name] = median_ms(step, args.repeats, warmup=3)
    base = times[next(iter(VARIANTS))]
    print(f"machine: {platform.processor() or platform.machine()}, torch {torch.__version__}, "  # noqa: T201
          f"{args.threads} thread(s), {args.repeats} repeats, batch {BATCH}")
    print("| variant | ms per wake step (median) | speed-up |\n|---|---|---|")  # noqa: T201
    for name, ms in times.items():
        print(f"| {name} | {ms:.1f} | {base / ms:.2f}x |")  # noqa: T201


if __name__ == "__main__":
    main()
