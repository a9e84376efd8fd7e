"""Moved (issue 61): the SAC substrate is :mod:`sr_imitation.substrates.sac`, with the same module names below it
(``python -m sr_imitation.substrates.sac.mt_joint``) except CompoNet, now ``sr_imitation.substrates.sac.methods
.componet``. Importing the old name, or running a module under it, is answered with the new name in one line (the
error's ``name`` is this package, so ``python -m`` prints the message alone, without a traceback)."""

raise ImportError("sr_imitation.rl moved to sr_imitation.substrates.sac (same module names below it; componet is "
                  "methods.componet): sr_imitation.rl.<module> is sr_imitation.substrates.sac.<module>", name=__name__)
