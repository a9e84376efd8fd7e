"""``sr-record``: the needle recorder (:mod:`sr_imitation.recorders.needle`, the default) or, with ``--env=metaworld``,
Meta-World's scripted policies (:mod:`sr_imitation.recorders.metaworld`); ``sr-record --env=metaworld --help``
lists the latter's options."""

from __future__ import annotations

import sys

from sr_imitation.infra.cli_errors import run_cli
from sr_imitation.recorders.needle import main as record_needle
from sr_imitation.recorders.needle import report_recorded
from sr_imitation.video import quiet_encoder_logs


def main(args: list[str] | None = None) -> None:
    argv = list(sys.argv[1:] if args is None else args)
    quiet_encoder_logs()
    if "--env=metaworld" not in argv:
        record_needle(argv)
        return
    from sr_imitation.recorders.metaworld import main as record_metaworld

    report_recorded(lambda: record_metaworld(argv))


def entry() -> None:
    """Console script ``sr-record``: :func:`main` with one-line user errors."""
    run_cli("sr-record", main)


if __name__ == "__main__":
    entry()
