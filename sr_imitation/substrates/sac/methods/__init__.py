"""The methods that exist only on the SAC substrate, one file each, registered by name like the substrate-free ones
(:mod:`sr_imitation.stream.methods`): every module of this folder whose name does not start with ``_`` is imported
here. CompoNet is one: its composed actor replaces SAC's own (:mod:`sr_imitation.substrates.sac.composed_actor`)."""

from sr_imitation.stream.methods.registry import import_method_files

import_method_files(__name__, __path__)
