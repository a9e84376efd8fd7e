"""The SAC substrate (``--substrate=sac``; Meta-World streams, Appendix A.1) and the methods that exist only for it.

Importing this package registers the substrate's command (``sr-train`` imports :mod:`sr_imitation.substrates.sac.cli`
only when it runs this substrate) and the methods of its ``methods/`` folder: CompoNet
(:mod:`sr_imitation.substrates.sac.methods.componet`), which replaces the SAC actor by its own architecture and so
lives here rather than with the substrate-free methods in :mod:`sr_imitation.stream.methods`. Neither imports
Meta-World or LeRobot.
"""

from sr_imitation.substrates.registry import SubstrateCommand, register_substrate
from sr_imitation.substrates.sac import methods as _methods  # noqa: F401  (registers the folder's methods)


@register_substrate
class SACCommand(SubstrateCommand):
    """SAC with critic memories on Meta-World (MT5, MT5 reversed, MT8)."""

    name = "sac"
    module = "sr_imitation.substrates.sac.cli"
