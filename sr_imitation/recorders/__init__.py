"""Recorders of scripted demonstrations into LeRobot v3 datasets: the needle skills by the needle's scripted
expert (:mod:`.needle`) and Meta-World v3 tasks by Meta-World's own scripted policies (:mod:`.metaworld`);
``sr-record``'s entry point (:mod:`.cli`) picks the recorder from ``--env``."""
