"""Run infrastructure: what every run and command needs around the formulas, but that is no formula itself.

- :mod:`~sr_imitation.infra.fingerprint`: settings fingerprints (a run directory cannot change its settings
  silently), ``to_jsonable``/``check_finite`` for configs, and where a command's run directory is;
- :mod:`~sr_imitation.infra.runlog`: the per-step run log ``log.jsonl``, optionally mirrored to Weights & Biases;
- :mod:`~sr_imitation.infra.provenance`: the git commit of the code that produced a result;
- :mod:`~sr_imitation.infra.cli_errors`: :func:`~sr_imitation.infra.cli_errors.run_cli` (one-line user errors)
  and the one logging set-up;
- :mod:`~sr_imitation.infra.cli_parsing`: the draccus parser of every ``sr-*`` command.

Its place in the layers (``tests/test_architecture.py``): ``io`` < ``core`` < ``infra`` < ``stream`` < substrates
< drivers. It may import :mod:`sr_imitation.io` and :mod:`sr_imitation.core` (today it needs ``io`` alone; besides
them the standard library, draccus and, when enabled, wandb), never the engine, a substrate, an environment or a
driver; like the core it imports neither LeRobot nor a simulator (tested).
"""
