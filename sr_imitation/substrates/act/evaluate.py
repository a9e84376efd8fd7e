"""Closed-loop evaluation of the shared policy on learned skills (Section 4, "Evaluation protocol").

Each skill is evaluated with N episodes per evaluation seed (paper: N = 20, three evaluation seeds); an episode
succeeds when ``info["is_success"]`` becomes true (the environment terminates on success). The observation
trajectories (``agent_pos``, all 35 entries) are kept; SPI uses their ``SPI_FEATURES`` only (the report slices
them, ``sr_imitation.core.metrics.policy_motion``), and the first episodes of each skill can be saved as mp4 from
the scene camera (offscreen EGL). Episode e of evaluation seed s on the skill at stream position i always resets
with the same seed (``EVAL_SEED_OFFSET + 10000 s + 100 i + e``), whatever the stage: S[k, i] and S[i, i], and the
evaluation right after skill i's wake, are paired (common random numbers). Observations go through LeRobot's
``preprocess_observation`` and the policy's pre/post-processors, as in ``lerobot-eval``.

Where each skill is evaluated (``--eval.env``, :data:`EVAL_ENVS`): the MuJoCo needle environment (``needle``, the
default: one task per needle skill name), one gymnasium id per skill (``gym``, ``--eval.gym_ids``), one LeRobot env
config per skill (``lerobot``, ``--eval.env_type`` and ``--eval.env_tasks``, what ``lerobot-eval`` builds from
``--env.type``/``--env.task``), or nowhere (``none``: the stream reports memory losses and validation l1 instead,
``substrates.act.substrate``). :func:`make_env_factory` builds the factory of each; :func:`resolve_eval_env` and
:func:`check_env_features` check an environment before the first gradient. Environments other than the needle one
follow LeRobot's gym convention: a dict observation with ``agent_pos`` (the robot state, ``observation.state``)
and optionally ``pixels`` (an image, or a dict of camera images), ``info["is_success"]`` for success; a plain
``Box`` observation is taken as ``agent_pos`` (our choice).
"""

from __future__ import annotations

import importlib
import importlib.util
import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from lerobot.envs.utils import preprocess_observation
from lerobot.utils.constants import ACTION, OBS_ENV_STATE

from sr_imitation.envs.metaworld.env import SPI_FEATURES as METAWORLD_SPI_FEATURES
from sr_imitation.envs.metaworld.tasks import OBS_DIM as METAWORLD_OBS_DIM
from sr_imitation.progress import Progress
from sr_imitation.video import write_mp4

logger = logging.getLogger(__name__)

EVAL_SEED_OFFSET = 1_000_000
"""Evaluation episodes use reset seeds far from the demonstration seeds."""


def episode_positions(skills: Sequence[str], stream: Sequence[str] | None = None) -> list[int]:
    """Each skill's position in its stream, which seeds its evaluation episodes (:func:`evaluate_skills`), so that an
    evaluation outside the run (sr-eval, sr-sleep) draws the run's own episodes in any stream order.

    Args:
        skills: the skills to evaluate.
        stream: the run's skill order, when known (the checkpoint's ``train_config.json``, the memories' skills).

    Returns:
        Per skill: its position in ``stream`` where it is there; else a needle skill's place in the needle's own order
        (approach ... pullout: the default stream); else its position in ``skills``.
    """
    from sr_imitation.envs.needle.skills import SKILL_NAMES as NEEDLE_SKILLS

    stream = list(stream or [])
    return [stream.index(s) if s in stream else NEEDLE_SKILLS.index(s) if s in NEEDLE_SKILLS else i
            for i, s in enumerate(skills)]

SPI_FEATURES: tuple[int, ...] = tuple(range(7))
"""Policy-dependent entries of the needle env's 35-d ``agent_pos`` used by SPI: the active arm's tool setpoint
``cur_x, cur_y, cur_z`` (cm), ``cur_roll, cur_pitch, cur_yaw`` (rad) and ``cur_jaw`` (``envs.needle.env.STATE_NAMES``
0-6). The rest is not the tool's own state or repeats it: ``goal_*`` (7-13) is set at reset, ``delta_*`` (14-20)
= goal - cur, ``achieved_*`` (21-27) repeats cur, ``desired_*`` (28-34) repeats goal (docs/NEEDLE_ENV.md)."""

NEEDLE_STATE_DIM = 35
"""Size of the needle env's ``agent_pos`` (``envs.needle.env.STATE_DIM``), the layout ``SPI_FEATURES`` refers to."""

STATE_LAYOUTS: dict[int, tuple[int, ...]] = {NEEDLE_STATE_DIM: SPI_FEATURES, METAWORLD_OBS_DIM: METAWORLD_SPI_FEATURES}
"""The robot's own entries of each known ``agent_pos`` layout: the needle env's 35 numbers, Meta-World's 39 (hand
xyz and gripper, :data:`sr_imitation.envs.metaworld.env.SPI_FEATURES`)."""


def spi_features(state_dim: int) -> tuple[int, ...]:
    """The ``agent_pos`` entries SPI uses (:data:`STATE_LAYOUTS`). Another environment (a custom ``EnvFactory``) has
    no declared layout here; all its entries are used, with a warning (our choice)."""
    if state_dim in STATE_LAYOUTS:
        return STATE_LAYOUTS[state_dim]
    logger.warning("SPI: %d-d agent_pos is none of the known layouts %s; using all %d entries", state_dim,
                   sorted(STATE_LAYOUTS), state_dim)
    return tuple(range(state_dim))

EnvFactory = Callable[[str, bool], gym.Env]
"""(skill, with_scene_render) -> a gymnasium env with ``pixels``/``agent_pos`` observations."""


EVAL_ENVS = ("needle", "metaworld", "gym", "lerobot", "none")
"""Values of ``--eval.env`` (module docstring)."""


@dataclass
class EvalConfig:
    """Evaluation protocol.

    Each field is documented below (``--help`` shows it). ``--eval.env`` says where each skill is evaluated; the
    episode settings (episodes, seeds, max_steps, videos) apply to every environment, ``thresholds`` to the needle
    environment only.
    """

    env: str = "needle"
    """Where each skill is evaluated - needle (the MuJoCo needle environment, one task per needle skill name),
    metaworld (one Meta-World v3 task per skill: the skill's name, e.g. reach-v3, or --eval.env_tasks; Meta-World's
    39-number observation and success, sr_imitation.envs.metaworld.env), gym
    (one gymnasium id per skill: --eval.gym_ids), lerobot (one LeRobot env config per skill, as lerobot-eval's
    --env.type/--env.task: --eval.env_type, --eval.env_tasks) or none (no closed-loop evaluation: results say
    "evaluation: none" and report every memory's loss and each skill's validation l1 instead of success; AFSR, PRS,
    BWT and SPI are null, and the episode settings below are unused)."""
    gym_ids: list[str] | None = None
    """--eval.env=gym: one gymnasium id per skill, in stream order (e.g. [MyPick-v0,MyPlace-v0]); an id of an
    unregistered namespace ns/Name-v0 imports the module ns first, module:Name-v0 imports module (gymnasium's
    syntax). Checked before the first gradient: the id exists and its spaces fit the datasets."""
    env_type: str | None = None
    """--eval.env=lerobot: the LeRobot env type (lerobot-eval's --env.type, e.g. pusht, aloha, needle; the needle
    environment is registered by this package)."""
    env_tasks: list[str] | None = None
    """--eval.env=lerobot or metaworld: one task per skill (lerobot-eval's --env.task; a Meta-World v3 id), in
    stream order; null - each skill's name is its task (our choice)."""
    env_options: dict[str, Any] = field(default_factory=dict)
    """--eval.env=gym: keyword arguments of gym.make; --eval.env=metaworld: of MetaWorldEnv (camera, task_seed);
    --eval.env=lerobot: other fields of the LeRobot env config
    (e.g. --eval.env_options='{obs_type: agent_pos, observation_height: 64}'). The same for every skill."""
    episodes: int = 20
    """Episodes per skill per evaluation seed (paper 20; 3 seeds x 20 = the paper's 60 per skill); 0 only with
    --eval.env=none."""
    seeds: list[int] = field(default_factory=lambda: [0, 1, 2])
    """Evaluation seeds (paper three); episodes reset identically at every stage."""
    max_steps: int = 300
    """Episode step limit (SurgicAI 300)."""
    videos_per_skill: int = 1
    """Episodes per skill (first seed) also saved as mp4; 0 disables videos (gym and lerobot environments must
    render rgb_array frames otherwise)."""
    video_height: int = 240
    """Video frame height (needle and metaworld environments; gym and lerobot ones render at their own size)."""
    video_width: int = 320
    """Video frame width (needle and metaworld environments)."""
    thresholds: str = "learnable"
    """Success-threshold preset of the needle environment - learnable or surgicai (--eval.env=needle only; with
    --eval.env=lerobot --eval.env_type=needle give it in --eval.env_options)."""

    def __post_init__(self) -> None:
        if self.env not in EVAL_ENVS:
            raise ValueError(f"eval.env must be one of {list(EVAL_ENVS)}, got {self.env!r}")
        if self.env == "none":
            if self.episodes < 0:
                raise ValueError(f"eval.episodes must be >= 0, got {self.episodes}")
        elif self.episodes < 1:
            raise ValueError(f"eval.episodes must be >= 1, got {self.episodes} (--eval.env=none switches the "
                             "evaluation off)")
        if not self.seeds:
            raise ValueError("eval.seeds must name at least one evaluation seed")
        if self.max_steps < 1:
            raise ValueError(f"eval.max_steps must be >= 1, got {self.max_steps}")
        if self.videos_per_skill < 0:
            raise ValueError(f"eval.videos_per_skill must be >= 0, got {self.videos_per_skill}")
        given = {"eval.gym_ids": self.gym_ids is not None, "eval.env_type": self.env_type is not None,
                 "eval.env_tasks": self.env_tasks is not None, "eval.env_options": bool(self.env_options)}
        belongs = {"eval.gym_ids": ("gym",), "eval.env_type": ("lerobot",), "eval.env_tasks": ("lerobot", "metaworld"),
                   "eval.env_options": ("gym", "lerobot", "metaworld")}
        for key, is_given in given.items():
            if is_given and self.env not in belongs[key]:
                raise ValueError(f"{key} is a setting of --eval.env={'|'.join(belongs[key])}, not of "
                                 f"--eval.env={self.env}")
        if self.env == "gym" and not self.gym_ids:
            raise ValueError("eval.gym_ids: --eval.env=gym needs one gymnasium id per skill, e.g. "
                             "--eval.gym_ids=[MyPick-v0,MyPlace-v0]")
        if self.env == "lerobot" and not self.env_type:
            raise ValueError("eval.env_type: --eval.env=lerobot needs a LeRobot env type (lerobot-eval's --env.type)")
        for key, values in (("eval.gym_ids", self.gym_ids), ("eval.env_tasks", self.env_tasks)):
            for i, value in enumerate(values or []):
                if not isinstance(value, str) or not value.strip():
                    raise ValueError(f"{key}[{i}] must be a non-empty name, got {value!r}")
        if self.env != "needle" and self.thresholds != "learnable":
            raise ValueError(f"eval.thresholds is the needle environment's success preset; --eval.env={self.env} "
                             f"has its own success (got {self.thresholds!r})")

    def check_skills(self, skills: Sequence[str]) -> None:
        """The per-skill lists have one entry per skill (``ValueError`` naming the key)."""
        for key, values in (("eval.gym_ids", self.gym_ids), ("eval.env_tasks", self.env_tasks)):
            if values is not None and len(values) != len(skills):
                raise ValueError(f"{key}: {len(values)} entries for {len(skills)} skills {list(skills)}; give one "
                                 "per skill, in stream order")

    def tasks(self, skills: Sequence[str]) -> list[str]:
        """The LeRobot task of each skill (``env_tasks``, or the skill names)."""
        return list(self.env_tasks) if self.env_tasks is not None else list(skills)


@dataclass
class SkillEvaluation:
    skill: str
    success_per_seed: list[float]
    episode_lengths: list[int]
    trajectories: list[np.ndarray]
    videos: list[str]

    @property
    def success(self) -> float:
        return float(np.mean(self.success_per_seed))


def needle_env_factory(image_size: tuple[int, int] | None, cfg: EvalConfig) -> EnvFactory:
    """Factory for the MuJoCo needle environment (imported lazily: it is a separate module)."""

    def make(skill: str, with_video: bool) -> gym.Env:
        from sr_imitation.envs.needle import gym_id

        kwargs: dict[str, Any] = {"thresholds": cfg.thresholds, "camera_dict": True}
        if image_size is None:
            kwargs["obs_type"] = "agent_pos"
        else:
            kwargs["image_height"], kwargs["image_width"] = image_size
        if with_video:
            kwargs.update(render_mode="rgb_array", render_height=cfg.video_height, render_width=cfg.video_width)
        return gym.make(gym_id(skill), max_episode_steps=cfg.max_steps, **kwargs)

    return make


class _AgentPos(gym.ObservationWrapper):
    """A plain ``Box`` observation as LeRobot's ``{"agent_pos": ...}`` (our choice for plain gymnasium envs)."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.observation_space = gym.spaces.Dict({"agent_pos": env.observation_space})

    def observation(self, observation: Any) -> dict[str, Any]:
        return {"agent_pos": observation}


def _lerobot_convention(env: gym.Env) -> gym.Env:
    return _AgentPos(env) if isinstance(env.observation_space, gym.spaces.Box) else env


def _unregistered(gym_id: str) -> str | None:
    """gymnasium's reason why ``gym_id`` cannot be made (``None`` when it is registered)."""
    try:
        gym.spec(gym_id)
    except gym.error.Error as exc:
        return str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    return None


def resolve_gym_id(gym_id: str) -> str:
    """Make ``gym_id`` known to gymnasium, importing what registers it: ``module:Name-v0`` imports ``module``
    (gymnasium's syntax), an unregistered ``ns/Name-v0`` imports the module ``ns`` (as LeRobot imports an env's
    package). Returns the id without a module prefix; ``ValueError`` if it stays unknown."""
    module, _, name = gym_id.rpartition(":")
    if not module and _unregistered(name) and "/" in name:
        module = name.split("/", 1)[0]  # a namespace that may be an importable package
        try:
            found = importlib.util.find_spec(module) is not None
        except (ImportError, ValueError):
            found = False
        module = module if found else ""
    if module:
        try:
            importlib.import_module(module)
        except Exception as exc:  # noqa: BLE001 - whatever the user's module raises on import
            first = str(exc).splitlines()[0] if str(exc) else ""
            raise ValueError(f"cannot import {module!r} ({type(exc).__name__}: {first})") from exc
    reason = _unregistered(name)
    if reason:
        raise ValueError(f"gymnasium has no environment {name!r} ({reason.rstrip('.')}); register it, or install "
                         "the package of its namespace, before sr-train runs")
    return name


def metaworld_env_factory(skills: Sequence[str], image_size: tuple[int, int] | None, cfg: EvalConfig) -> EnvFactory:
    """Factory for ``--eval.env=metaworld``: :class:`~sr_imitation.envs.metaworld.env.MetaWorldEnv` of the skill's
    task (``cfg.tasks``), state only or with the dataset's camera image (``image_size``), episodes of
    ``cfg.max_steps``, rollout videos at ``cfg.video_height`` x ``cfg.video_width``."""
    tasks = dict(zip(skills, cfg.tasks(skills), strict=True))

    def make(skill: str, with_video: bool) -> gym.Env:
        from sr_imitation.envs.metaworld.env import MetaWorldEnv

        kwargs: dict[str, Any] = {"max_episode_steps": cfg.max_steps, **cfg.env_options}
        if image_size is not None:
            kwargs.update(obs_type="pixels_agent_pos", image_height=image_size[0], image_width=image_size[1])
        if with_video:
            kwargs.update(render_mode="rgb_array", render_height=cfg.video_height, render_width=cfg.video_width)
        return MetaWorldEnv(tasks[skill], **kwargs)

    return make


def gym_env_factory(skills: Sequence[str], gym_ids: Sequence[str], cfg: EvalConfig) -> EnvFactory:
    """Factory for ``--eval.env=gym``: ``gym.make(<the skill's id>, max_episode_steps=cfg.max_steps,
    **cfg.env_options)`` (the id resolved by :func:`resolve_gym_id`), with ``render_mode="rgb_array"`` for the
    recording env."""
    ids = dict(zip(skills, gym_ids, strict=True))

    def make(skill: str, with_video: bool) -> gym.Env:
        kwargs: dict[str, Any] = dict(cfg.env_options)
        if with_video:
            kwargs.setdefault("render_mode", "rgb_array")
        return _lerobot_convention(gym.make(resolve_gym_id(ids[skill]), max_episode_steps=cfg.max_steps, **kwargs))

    return make


def lerobot_env_config(env_type: str, task: str, options: Mapping[str, Any]) -> Any:
    """LeRobot's ``EnvConfig`` of ``env_type`` for ``task`` with ``options`` (decoded and validated by draccus, as
    ``--env.*`` flags are). ``ValueError`` for an env type LeRobot does not know, or one built from Hub code."""
    import draccus
    from lerobot.envs.configs import EnvConfig, HubEnvConfig

    import sr_imitation.envs.metaworld.lerobot_config  # noqa: F401  (registers --env.type=sr_meta_world)
    import sr_imitation.envs.needle.lerobot_config  # noqa: F401  (registers --env.type=needle)

    try:
        cls = EnvConfig.get_choice_class(env_type)
    except KeyError:
        raise ValueError(f"LeRobot knows no env type {env_type!r}; known: {sorted(EnvConfig.get_known_choices())}"
                         ) from None
    if issubclass(cls, HubEnvConfig):
        raise ValueError(f"env type {env_type!r} loads its environment code from the Hugging Face Hub; sr-train "
                         "evaluates offline")
    try:
        return draccus.decode(cls, {**dict(options), "task": task})
    except Exception as exc:  # noqa: BLE001 - draccus wraps the config's own ValueError
        cause = exc
        while cause.__cause__ is not None:
            cause = cause.__cause__
        raise ValueError(f"{env_type} env config for task {task!r}: {str(cause).splitlines()[0]}") from exc


class _VectorMember(gym.Wrapper):
    """The one environment of the vector env LeRobot's ``make_env`` builds; closing it closes the vector env."""

    def __init__(self, vector_env: Any) -> None:
        super().__init__(vector_env.envs[0])
        self._vector_env = vector_env

    def close(self) -> None:
        self._vector_env.close()


def make_lerobot_env(env_cfg: Any) -> gym.Env:
    """One environment of ``env_cfg`` built by LeRobot's ``make_env`` (its package imported first when its gym id
    is not registered, as ``make_env`` would); ``ValueError`` if LeRobot builds other than one environment."""
    from lerobot.envs.factory import make_env

    if not any(name in env_cfg.type for name in ("libero", "metaworld")) and env_cfg.gym_id not in gym.registry:
        try:
            importlib.import_module(env_cfg.package_name)
        except ModuleNotFoundError as exc:
            raise ValueError(f"env type {env_cfg.type!r} needs the package {env_cfg.package_name!r} ({exc})"
                             ) from None
        if env_cfg.gym_id not in gym.registry:
            raise ValueError(f"{env_cfg.package_name!r} registers no environment {env_cfg.gym_id!r}")
    suites = make_env(env_cfg, n_envs=1, use_async_envs=False)
    vector_envs = [v for tasks in suites.values() for v in tasks.values()]
    if len(vector_envs) != 1:
        for v in vector_envs:
            v.close()
        raise ValueError(f"task {env_cfg.task!r} of env type {env_cfg.type!r} is {len(vector_envs)} environments; "
                         "name one task per skill")
    return _lerobot_convention(_VectorMember(vector_envs[0]))


def lerobot_env_factory(skills: Sequence[str], cfg: EvalConfig) -> EnvFactory:
    """Factory for ``--eval.env=lerobot``: the env config of ``cfg.env_type`` with the skill's task and
    ``cfg.env_options``, built by LeRobot (its own ``render_mode`` serves the recording env too)."""
    tasks = dict(zip(skills, cfg.tasks(skills), strict=True))

    def make(skill: str, with_video: bool) -> gym.Env:
        return make_lerobot_env(lerobot_env_config(str(cfg.env_type), tasks[skill], cfg.env_options))

    return make


def make_env_factory(cfg: EvalConfig, skills: Sequence[str], image_size: tuple[int, int] | None
                     ) -> EnvFactory | None:
    """The environment factory ``--eval.env`` names (``None`` for ``none``: nothing is evaluated)."""
    if cfg.env == "needle":
        return needle_env_factory(image_size, cfg)
    if cfg.env == "metaworld":
        return metaworld_env_factory(skills, image_size, cfg)
    if cfg.env == "gym":
        return gym_env_factory(skills, list(cfg.gym_ids or []), cfg)
    if cfg.env == "lerobot":
        return lerobot_env_factory(skills, cfg)
    return None


def resolve_eval_env(cfg: EvalConfig, skills: Sequence[str], index: int) -> str:
    """Check that skill ``index``'s environment exists (a registered gym id; a LeRobot env type LeRobot knows, with a
    valid config for the skill's task) without building it. Returns the words naming it in messages (its dotted key
    and the skill); ``ValueError`` starting with the dotted key otherwise."""
    skill = skills[index]
    if cfg.env == "gym":
        key = f"eval.gym_ids[{index}]"
        gym_id = list(cfg.gym_ids or [])[index]
        try:
            resolve_gym_id(gym_id)
        except ValueError as exc:
            raise ValueError(f"{key} (skill {skill!r}): {exc}") from None
        return f"{key} ({gym_id!r}, skill {skill!r})"
    task = cfg.tasks(skills)[index]
    key = (f"eval.env_tasks[{index}]" if cfg.env_tasks is not None
           else "eval.env_tasks (null: each skill's name is its task)")
    if cfg.env == "metaworld":
        from sr_imitation.envs.metaworld.tasks import check_task

        try:
            check_task(task)
        except ValueError as exc:
            raise ValueError(f"{key} (skill {skill!r}): {exc}") from None
        return f"{key} (Meta-World task {task!r}, skill {skill!r})"
    try:
        lerobot_env_config(str(cfg.env_type), task, cfg.env_options)
    except ValueError as exc:
        name = "eval.env_type" if "knows no env type" in str(exc) or "from the Hugging Face Hub" in str(exc) else key
        raise ValueError(f"{name}: {exc}") from None
    return f"{key} ({cfg.env_type} task {task!r}, skill {skill!r})"


def check_env_features(env: gym.Env, input_features: Mapping[str, Any], output_features: Mapping[str, Any],
                       where: str, seed: int = EVAL_SEED_OFFSET) -> None:
    """The environment fits the policy: its action space has the datasets' action shape, and a reset observation
    gives every policy input (``observation.state`` from ``agent_pos``, cameras from ``pixels``) with the datasets'
    shapes. ``ValueError`` starting with ``where``."""
    action = tuple(output_features[ACTION].shape)
    space = tuple(getattr(env.action_space, "shape", None) or ())
    if space != action:
        raise ValueError(f"{where}: its action space has shape {space}, the datasets' '{ACTION}' has {action}")
    obs, _ = env.reset(seed=seed)
    if not isinstance(obs, Mapping) or "agent_pos" not in obs:
        keys = sorted(obs) if isinstance(obs, Mapping) else type(obs).__name__
        raise ValueError(f"{where}: its observation has no 'agent_pos' (the robot state; it has {keys})")
    batch = _to_policy_batch(obs)
    for key, feature in input_features.items():
        if key == OBS_ENV_STATE and key not in batch:
            continue  # state-only ACT feeds it from observation.state
        if key not in batch:
            raise ValueError(f"{where}: its observations give no '{key}' that the policy needs (they give "
                             f"{sorted(batch)})")
        if tuple(batch[key].shape[1:]) != tuple(feature.shape):
            raise ValueError(f"{where}: its '{key}' has shape {tuple(batch[key].shape[1:])}, the datasets' has "
                             f"{tuple(feature.shape)}")


def check_env_renders(env: gym.Env, where: str) -> None:
    """The recording environment renders ``rgb_array`` frames (the rollout videos); ``ValueError`` otherwise."""
    if getattr(env, "render_mode", None) != "rgb_array":
        raise ValueError(f"{where}: it does not render rgb_array frames for the rollout videos (render_mode "
                         f"{getattr(env, 'render_mode', None)!r}); pass --eval.videos_per_skill=0")


def _to_policy_batch(obs: dict[str, Any]) -> dict[str, torch.Tensor]:
    """Single-env observation -> LeRobot batch of size 1 (``pixels/<cam>`` -> ``observation.images.<cam>``)."""
    batched: dict[str, Any] = {}
    for key, value in obs.items():
        if isinstance(value, dict):
            batched[key] = {k: np.asarray(v)[None] for k, v in value.items()}
        else:
            batched[key] = np.asarray(value)[None]
    return preprocess_observation(batched)


def rollout(
    policy: Any, preprocessor: Any, postprocessor: Any, env: gym.Env, seed: int, max_steps: int, record: bool
) -> tuple[bool, int, np.ndarray, list[np.ndarray]]:
    """One episode; returns (success, steps, agent_pos trajectory (T x d), scene frames if ``record``)."""
    obs, info = env.reset(seed=seed)
    policy.reset()
    states, frames = [np.asarray(obs["agent_pos"], dtype=np.float64)], []
    if record:
        frames.append(env.render())
    success = bool(info.get("is_success", False))
    steps = 0
    while not success and steps < max_steps:
        with torch.no_grad():
            action = postprocessor(policy.select_action(preprocessor(_to_policy_batch(obs))))
        action = action.squeeze(0).cpu().numpy()
        obs, _, terminated, truncated, info = env.step(action)
        steps += 1
        states.append(np.asarray(obs["agent_pos"], dtype=np.float64))
        if record:
            frames.append(env.render())
        success = bool(info.get("is_success", False))
        if terminated or truncated:
            break
    return success, steps, np.stack(states), frames


def evaluate_skills(
    policy: Any,
    preprocessor: Any,
    postprocessor: Any,
    skills: Sequence[str],
    skill_indices: Sequence[int],
    make_env: EnvFactory,
    cfg: EvalConfig,
    video_dir: Path | None = None,
    progress: bool = True,
) -> dict[str, SkillEvaluation]:
    """Evaluate on every skill in ``skills`` (stream positions ``skill_indices``) over all evaluation seeds."""
    policy.eval()
    results: dict[str, SkillEvaluation] = {}
    total = len(skills) * len(cfg.seeds) * cfg.episodes
    bar = Progress(total, "eval", logger, enabled=progress, unit="ep")
    for skill, index in zip(skills, skill_indices, strict=True):
        per_seed, lengths, trajectories, videos = [], [], [], []
        env = make_env(skill, False)
        video_env = make_env(skill, True) if video_dir is not None and cfg.videos_per_skill > 0 else None
        try:
            for s_i, eval_seed in enumerate(cfg.seeds):
                wins = 0
                for episode in range(cfg.episodes):
                    record = video_env is not None and s_i == 0 and episode < cfg.videos_per_skill
                    run_env = video_env if record else env
                    seed = EVAL_SEED_OFFSET + 10_000 * eval_seed + 100 * index + episode
                    ok, steps, states, frames = rollout(policy, preprocessor, postprocessor, run_env, seed,
                                                        cfg.max_steps, record)
                    wins += int(ok)
                    lengths.append(steps)
                    trajectories.append(states)
                    if record and frames:
                        path = Path(video_dir) / f"{skill}_episode{episode}_{'success' if ok else 'failure'}.mp4"
                        write_mp4(path, frames, fps=run_env.metadata.get("render_fps", 30))
                        videos.append(str(path))
                    bar.update(1)
                per_seed.append(wins / cfg.episodes)
        finally:
            env.close()
            if video_env is not None:
                video_env.close()
        results[skill] = SkillEvaluation(skill, per_seed, lengths, trajectories, videos)
        logger.info("eval %s: success %.3f per seed %s", skill, results[skill].success, per_seed)
    bar.close()
    return results
