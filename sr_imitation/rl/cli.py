"""``sr-rl-train``: run (or resume) the Meta-World stream with SAC wake, critic memories and Nash sleep.

LeRobot-style flags through draccus, e.g.::

    sr-rl-train --config_path=configs/sac_mt5_cpu.json --seed=1 --output_dir=outputs/sac_cpu_s1
    sr-rl-train --config_path=configs/sac_mt5_cpu.json --output_dir=outputs/sac_cpu_s1 --resume=true
    sr-rl-train --config_path=configs/sac_mt5_cpu.json --sleep_enabled=false   # SR wake-only ablation
"""


import json
import logging

import draccus

from sr_imitation.rl.config import RLTrainConfig

logger = logging.getLogger(__name__)


def train(cfg: RLTrainConfig) -> dict:
    from sr_imitation.rl.trainer import StreamTrainer

    results = StreamTrainer(cfg).run()
    logger.info("final metrics: %s", json.dumps({k: v for k, v in results["metrics"].items()
                                                  if not k.endswith("_curve")}))
    logger.info("results written to %s", cfg.output_dir / "results.json")
    return results


@draccus.wrap()
def main(cfg: RLTrainConfig) -> None:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    train(cfg)


if __name__ == "__main__":
    main()
