"""Moved (issue 61): the ACT-SR substrate is :mod:`sr_imitation.substrates.act`, with the same module names below it
(``python -m sr_imitation.substrates.act.mt_joint``, ``from sr_imitation.substrates.act.config import ...``).
Importing the old name, or running a module under it, is answered with the new name in one line (the error's
``name`` is this package, so ``python -m`` prints the message alone, without a traceback)."""

raise ImportError("sr_imitation.imitation moved to sr_imitation.substrates.act (same module names below it): "
                  "sr_imitation.imitation.<module> is sr_imitation.substrates.act.<module>", name=__name__)
