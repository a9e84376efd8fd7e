"""``sr-train --substrate=sac`` (alias ``sr-rl-train``): the Meta-World stream with SAC wake, critic memories and
Nash sleep.

LeRobot-style flags through draccus, the same names as the imitation substrate's for shared concepts, e.g.::

    sr-train --config_path=configs/sac_mt5_cpu.json --seed=1 --output_dir=outputs/sac_cpu_s1
    sr-train --config_path=configs/sac_mt5_cpu.json --output_dir=outputs/sac_cpu_s1 --resume=true
    sr-train --config_path=outputs/sac_cpu_s1/train_config.json --resume=true   # resumes that run, wherever it is
    sr-train --config_path=configs/sac_mt5_cpu.json --sleep.enabled=false   # SR wake-only ablation
    sr-train --config_path=configs/sac_mt5_cpu.json --stream.name=mt8 --stream.extend_from=outputs/sac_cpu_s1

SAC has no ``--policy`` section; the ACT-SR policy's names of shared settings are accepted as on the ACT substrate
(``--policy.sleep`` is ``--sleep.enabled``, ``--policy.sleep_memory_size`` is ``--memory.buffer_size``;
:data:`~sr_imitation.stream.config.POLICY_ALIASES`).
"""


import json
import logging
import sys

from sr_imitation.infra.cli_errors import run_cli, setup_logging
from sr_imitation.infra.cli_parsing import parse_command
from sr_imitation.infra.config_file import split_config
from sr_imitation.infra.fingerprint import output_dir_for
from sr_imitation.infra.folder_lock import hold_folder
from sr_imitation.stream.config import fold_alias_flags
from sr_imitation.substrates.sac.config import RLTrainConfig

logger = logging.getLogger(__name__)


def train(cfg: RLTrainConfig) -> dict:
    """Run or resume the SAC stream ``cfg`` describes, as the only writer of its output_dir (its lock held
    throughout); returns the results."""
    from sr_imitation.substrates.sac.trainer import SACTrainer

    with hold_folder(cfg.output_dir):
        results = SACTrainer(cfg).run()
    logger.info("final metrics: %s", json.dumps({k: v["final"] for k, v in results["metrics"].items()}))
    logger.info("results written to %s", cfg.output_dir / "results.json")
    return results


def parse(args: list[str]) -> RLTrainConfig:
    """The config ``args`` describe; a run's own ``train_config.json`` (older runs: ``config.json``) stores
    output_dir "." (the run directory itself), resolved to the file's directory unless ``--output_dir`` is given."""
    config, rest = split_config(args)
    rest = fold_alias_flags(rest)  # the flags only: a config file has no policy section here
    cfg = parse_command(RLTrainConfig, rest, prog="sr-train", config_path=config)
    cfg.output_dir = output_dir_for(None if config is None else config.path, rest, cfg.output_dir)
    return cfg


def main(args: list[str] | None = None) -> None:
    setup_logging()
    train(parse(list(sys.argv[1:] if args is None else args)))


def entry() -> None:
    """``python -m sr_imitation.substrates.sac.cli``: :func:`main` with one-line user errors (``--debug`` for
    tracebacks)."""
    run_cli("sr-rl-train", main)


if __name__ == "__main__":
    entry()
