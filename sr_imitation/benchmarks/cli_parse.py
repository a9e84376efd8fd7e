"""How long ``sr-train`` takes to parse its flags, with every LeRobot policy type registered (draccus builds flags
and extracts help text from the source of all of them) and with ``act_sr`` as the only choice (what sr-train does,
:func:`sr_imitation.substrates.act.cli.act_sr_choices_only`); the latter also with the per-process memo of draccus'
field-help lookup emptied before each parse (``cold``: every parse before the memo, and a process's first parse).

    python -m sr_imitation.benchmarks.cli_parse --repeats=5
"""

from __future__ import annotations

import argparse
import json

import draccus

from sr_imitation.benchmarks.timing import median_ms
from sr_imitation.infra import cli_parsing
from sr_imitation.substrates.act.cli import act_sr_choices_only, parse_config
from sr_imitation.substrates.act.trainer import TrainStreamConfig

ARGS = ["--policy.type=act_sr", "--sleep.lr=1e-4", "--seed=3"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeats", type=int, default=5)
    repeats = parser.parse_args().repeats
    every = median_ms(lambda: draccus.parse(TrainStreamConfig, args=ARGS), repeats, warmup=1)
    narrowed = median_ms(lambda: parse_config(TrainStreamConfig, None, ARGS), repeats, warmup=1)

    def cold() -> object:
        cli_parsing._attribute_docstring.cache_clear()
        return parse_config(TrainStreamConfig, None, ARGS)

    narrowed_cold = median_ms(cold, repeats, warmup=1)
    with act_sr_choices_only():
        tree = draccus.encode(parse_config(TrainStreamConfig, None, ARGS))
        decode = median_ms(lambda: draccus.decode(TrainStreamConfig, tree), repeats, warmup=1)
    print(json.dumps({"every_policy_type_ms": round(every, 1), "act_sr_only_ms": round(narrowed, 1),  # noqa: T201
                      "act_sr_only_cold_ms": round(narrowed_cold, 1), "decode_only_ms": round(decode, 2),
                      "ratio": round(every / narrowed, 1), "memo_ratio": round(narrowed_cold / narrowed, 1),
                      "repeats": repeats}))


if __name__ == "__main__":
    main()
