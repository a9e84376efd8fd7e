"""The SAC substrate (Meta-World streams, Appendix A.1) and the methods that exist only for it.

Importing the package registers CompoNet (:mod:`sr_imitation.rl.componet`), which replaces the SAC actor by its own
architecture and so lives here rather than with the substrate-free methods in :mod:`sr_imitation.stream.methods`.
"""

from sr_imitation.rl import componet as _componet  # noqa: F401  (registers the method)
