"""``python -m sr_imitation.rl.report RUN_DIR [RUN_DIR ...]``: the shared multi-run summary
(:mod:`sr_imitation.stream.summary`, the same as ``python -m sr_imitation.stream.summary``) of SAC runs; kept so the
commands in docs/RESULTS.md still run. Reads runs of every results schema (SAC schema 3 included)."""

from __future__ import annotations

from sr_imitation.stream.summary import main

if __name__ == "__main__":
    main()
