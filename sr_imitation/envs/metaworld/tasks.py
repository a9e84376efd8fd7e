"""Meta-World skill streams for the SAC substrate (Appendix A.1, "Environment" and "Skill stream").

One :class:`SkillEnv` per skill wraps a single Meta-World v3 environment with the 50 randomized task
configurations of ``metaworld.MT1`` (goal positions visible in the 39-d observation, ``partially_observable=False``)
and samples one configuration uniformly at the start of every episode from its own seeded generator. The policy
never sees a task id. Episodes end by time limit only (``max_episode_steps``, 500 in Meta-World); Meta-World never
reports ``terminated``, so a truncation is never a terminal transition for SAC.

Streams (skill names are Meta-World v3 ids; the metrics strip the ``-v3`` suffix):

* ``mt5``: reach -> door-open -> drawer-open -> window-close -> button-press-topdown (the paper's order),
* ``mt5-reverse``: the same five skills reversed (Appendix, order sensitivity),
* ``mt8``: MT5 followed by window-open, drawer-close, handle-press (Appendix, length sensitivity).
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

logger = logging.getLogger(__name__)

MT5_STREAM: tuple[str, ...] = (
    "reach-v3",
    "door-open-v3",
    "drawer-open-v3",
    "window-close-v3",
    "button-press-topdown-v3",
)
STREAMS: dict[str, tuple[str, ...]] = {
    "mt5": MT5_STREAM,
    "mt5-reverse": tuple(reversed(MT5_STREAM)),
    "mt8": (*MT5_STREAM, "window-open-v3", "drawer-close-v3", "handle-press-v3"),
}
MT5_PAIRS: tuple[tuple[str, str], ...] = (
    ("reach", "door-open"),
    ("door-open", "drawer-open"),
    ("reach", "drawer-open"),
    ("door-open", "window-close"),
    ("drawer-open", "button-press-topdown"),
    ("window-close", "button-press-topdown"),
)
"""The six pre-registered MT5 PRS pairs (Appendix A.1, "Evaluation protocol"), by skill identity (no version)."""


def canonical_skill(name: str) -> str:
    """Strip a Meta-World version suffix ("door-open-v3" -> "door-open") so pairs match by skill identity."""
    for suffix in ("-v1", "-v2", "-v3"):
        if name.endswith(suffix):
            return name[: -len(suffix)]
    return name


OBS_DIM = 39
"""Meta-World observation size (Appendix A.1: 39-d)."""
ACT_DIM = 4
"""Meta-World action size (Appendix A.1: 4-d end-effector motion + gripper)."""
NUM_CONFIGURATIONS = 50
"""Randomized task configurations per skill (Appendix A.1: 50, sampled uniformly per episode)."""


def check_task(task: str) -> None:
    """``ValueError`` unless ``task`` is a Meta-World v3 environment with a scripted policy (``metaworld.MT1``'s
    names; a close name is suggested)."""
    import difflib

    import metaworld

    names = list(metaworld.MT1.ENV_NAMES)
    if task not in names:
        close = difflib.get_close_matches(task, names, n=1)
        hint = f"; did you mean {close[0]!r}?" if close else " (use '-v3' names, e.g. 'reach-v3')"
        raise ValueError(f"{task!r} is not a Meta-World v3 task{hint}")


def scripted_policy(skill: str) -> Callable[[np.ndarray], np.ndarray]:
    """Meta-World's own scripted expert for ``skill`` (``metaworld.policies.ENV_POLICY_MAP``): observation -> action
    in [-1, 1]^4."""
    import warnings

    from metaworld.policies import ENV_POLICY_MAP

    if skill not in ENV_POLICY_MAP:
        raise ValueError(f"Meta-World has no scripted policy for {skill!r}")
    policy = ENV_POLICY_MAP[skill]()

    def act(obs: np.ndarray) -> np.ndarray:
        with warnings.catch_warnings():  # "Constant(s) may be too high": Meta-World's own policies warn
            warnings.simplefilter("ignore", UserWarning)
            return np.clip(policy.get_action(np.asarray(obs, dtype=np.float64)), -1.0, 1.0)

    return act


def stream_skills(stream: str) -> tuple[str, ...]:
    """The ordered skill ids of a named stream."""
    if stream not in STREAMS:
        raise ValueError(f"unknown stream {stream!r}; choose from {sorted(STREAMS)}")
    return STREAMS[stream]


@dataclass
class StepResult:
    obs: np.ndarray
    reward: float
    terminated: bool
    truncated: bool
    success: bool


@functools.cache
def _benchmark(skill: str, task_seed: int) -> Any:
    """``metaworld.MT1(skill, seed=task_seed)``, built once a process (our choice, for speed): building it resets a
    fresh environment 50 times to draw the configurations (about 2 s on a 2-core CPU); with a seed it restores
    numpy's global generator after, so a second build gives the same configurations and leaves the same state
    (``tests/substrates/sac/test_envs_evaluate.py`` checks both). Only its immutable task list and its environment
    class are read."""
    import metaworld

    return metaworld.MT1(skill, seed=task_seed)


def configurations(skill: str, task_seed: int = 0) -> tuple[Any, ...]:
    """The 50 task configurations of ``metaworld.MT1(skill, seed=task_seed)`` (``metaworld.Task``: immutable)."""
    return tuple(_benchmark(skill, int(task_seed)).train_tasks)


class SkillEnv:
    """One Meta-World v3 skill with its 50 task configurations, sampled uniformly at every reset.

    Args:
        skill: Meta-World v3 environment id, e.g. ``"door-open-v3"``.
        seed: seeds the configuration generator (``metaworld.MT1(skill, seed=task_seed)`` draws the 50
            configurations; ``seed`` then picks among them per episode) and the environment's own RNG.
        task_seed: seed of the 50 configurations themselves; fixed so that every run, method and evaluation
            sees the same 50 configurations per skill (only the per-episode choice depends on ``seed``).
        max_episode_steps: time limit (Meta-World default 500).
    """

    def __init__(self, skill: str, seed: int = 0, task_seed: int = 0, max_episode_steps: int = 500) -> None:
        import metaworld  # local import: only the RL substrate needs Meta-World

        if skill not in metaworld.MT1.ENV_NAMES:
            raise ValueError(f"{skill!r} is not a Meta-World v3 environment (use '-v3' names, e.g. 'reach-v3')")
        if max_episode_steps < 1:
            raise ValueError(f"max_episode_steps must be >= 1, got {max_episode_steps}")
        self.skill = skill
        self.max_episode_steps = int(max_episode_steps)
        self.tasks = list(configurations(skill, task_seed))
        if len(self.tasks) != NUM_CONFIGURATIONS:
            raise RuntimeError(f"{skill}: expected {NUM_CONFIGURATIONS} configurations, got {len(self.tasks)}")
        self._env = _benchmark(skill, int(task_seed)).train_classes[skill]()
        self._env.max_path_length = max(self._env.max_path_length, self.max_episode_steps)
        self.seed(seed)
        self._t = 0
        self.configuration: int | None = None

    def seed(self, seed: int) -> None:
        """Reseed the configuration choice and the environment (reproducible episodes for a given seed)."""
        self._rng = np.random.default_rng(seed)
        self._env.seed(int(seed))

    def rng_state(self) -> dict[str, Any]:
        """The state of this environment's generators (the configuration choice and the simulator's own), as plain
        data: what a wake snapshot keeps (:mod:`sr_imitation.substrates.sac.wake_snapshot`)."""
        return {"choice": self._rng.bit_generator.state, "env": self._env.np_random.bit_generator.state}

    def set_rng_state(self, state: dict[str, Any]) -> None:
        self._rng.bit_generator.state = state["choice"]
        self._env.np_random.bit_generator.state = state["env"]

    def reset(self, configuration: int | None = None) -> np.ndarray:
        """Start an episode with a uniformly sampled configuration (or the given index); returns the 39-d
        observation."""
        if configuration is None:
            configuration = int(self._rng.integers(len(self.tasks)))
        elif not 0 <= configuration < len(self.tasks):
            raise ValueError(f"configuration must be in [0, {len(self.tasks)}), got {configuration}")
        self.configuration = int(configuration)
        self._env.set_task(self.tasks[self.configuration])
        obs, _ = self._env.reset()
        self._t = 0
        return np.asarray(obs, dtype=np.float32)

    def step(self, action: np.ndarray) -> StepResult:
        """One environment step; ``truncated`` at the time limit, ``terminated`` never (Meta-World has no
        terminal states)."""
        action = np.clip(np.asarray(action, dtype=np.float32), -1.0, 1.0)
        obs, reward, terminated, _, info = self._env.step(action)
        self._t += 1
        return StepResult(
            obs=np.asarray(obs, dtype=np.float32),
            reward=float(reward),
            terminated=bool(terminated),
            truncated=self._t >= self.max_episode_steps,
            success=bool(info.get("success", 0.0)),
        )

    @property
    def mj_model(self) -> Any:
        """The underlying ``mujoco.MjModel`` (for offscreen rendering, :mod:`sr_imitation.envs.metaworld.video`)."""
        return self._env.model

    @property
    def mj_data(self) -> Any:
        """The underlying ``mujoco.MjData`` (read-only use: writing to it changes the rollout)."""
        return self._env.data

    @property
    def fps(self) -> float:
        """Control steps per simulated second (Meta-World's ``render_fps``: 80), the real-time video rate."""
        return float(self._env.metadata.get("render_fps", 80))

    def close(self) -> None:
        self._env.close()

    def __enter__(self) -> SkillEnv:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
