"""Meta-World v3 skills: the task streams and ``SkillEnv`` (:mod:`.tasks`), the offscreen renderer and video writer
(:mod:`.video`), the gymnasium environment of the imitation substrate (:mod:`.env`) and ``sr-record``'s scripted
demonstrations (:mod:`.record`). Meta-World is imported only when an environment is built.

Importing the package chooses MuJoCo's offscreen GL (EGL unless the user set ``MUJOCO_GL``) before anything can
import MuJoCo, as the needle package does, so stock ``lerobot-eval --env.type=sr_meta_world`` works headless."""

from sr_imitation.offscreen import setup_offscreen_rendering

setup_offscreen_rendering()  # before the first `import mujoco` (Meta-World's, or the renderer's)
