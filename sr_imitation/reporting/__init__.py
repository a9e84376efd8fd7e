"""Reporting over run directories, apart from the engine that writes them: a run's shared results schema and its
checks (:mod:`.results`), multi-run summaries (:mod:`.summary`), run-against-run comparison (:mod:`.compare`), paired
tests over training seeds (:mod:`.stats`) and where runs stand (:mod:`.status`). Reads what ``sr_imitation.stream``
writes; the engine never imports it."""
