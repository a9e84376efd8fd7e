"""Meta-World v3 skills: the task streams and ``SkillEnv`` (:mod:`.tasks`), the offscreen renderer and video writer
(:mod:`.video`), the gymnasium environment of the imitation substrate (:mod:`.env`) and ``sr-record``'s scripted
demonstrations (:mod:`.record`). Meta-World is imported only when an environment is built."""
