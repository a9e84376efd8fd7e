"""Gymnasium environment for one SurgicAI-style suturing skill (or a chain of them) in MuJoCo.

Interface contract from ``shared/notes/surgicai-needle-spec.md`` §2 and §6.1:

- action ``Box(-1, 1, (7,))`` for the active arm, ``setpoint += action * (1 mm, 3 deg, 0.05)`` in that arm's
  base frame, order ``[x, y, z, roll, pitch, yaw, jaw]``; out-of-range actions are clipped,
  non-finite ones raise;
- observation ``{"pixels": wrist RGB uint8 (H, W, 3), "agent_pos": float32 (35,)}``, where ``agent_pos`` is
  SurgicAI's ``[observation(21) = cur, goal, goal - cur; achieved_goal(7); desired_goal(7)]`` with xyz in cm;
- ``info["is_success"]`` every step, termination on success, truncation after ``step_limit`` steps (300).

Simulation is purely kinematic (spec §6.2): physics never steps; MuJoCo is only used to render.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from sr_imitation.envs.needle import geometry as G
from sr_imitation.envs.needle import skills as S
from sr_imitation.envs.needle.skills import Skill

OBS_TYPES = ("pixels_agent_pos", "agent_pos")
REWARD_TYPES = ("dense", "sparse")
STATE_DIM = 35
STATE_NAMES = tuple(
    [f"{g}_{a}" for g in ("cur", "goal", "delta") for a in ("x", "y", "z", "roll", "pitch", "yaw", "jaw")]
    + [f"achieved_{a}" for a in ("x", "y", "z", "roll", "pitch", "yaw", "jaw")]
    + [f"desired_{a}" for a in ("x", "y", "z", "roll", "pitch", "yaw", "jaw")]
)
ACTION_NAMES = ("dx", "dy", "dz", "droll", "dpitch", "dyaw", "djaw")

# Reset randomisation (spec §3.1, §6.2).
NEEDLE_XY_RANGE = np.array([3.0, 20.0]) * G.MM
NEEDLE_YAW_RANGE = 30.0 * G.DEG
PARKED_JITTER = (5.0 * G.MM, 10.0 * G.DEG)  # initial setpoint jitter of a parked arm
PREPOSITION_JITTER = (1.0 * G.MM, 3.0 * G.DEG)  # noise on analytically prepositioned poses

# Valid-grasp window used by the weld logic (spec §6.2: "within 2 mm and 15 deg of a valid grasp site").
GRASP_RADIAL_TOL = 2.0 * G.MM
GRASP_STANDOFF_RANGE = (2.0 * G.MM, 12.0 * G.MM)
GRASP_ROTATION_TOL = 15.0 * G.DEG


@dataclass
class NeedleEnvSettings:
    """Options of :class:`NeedleEnv`.

    Args:
        skill: one of ``approach, place, insert, regrasp, pullout``.
        thresholds: success threshold preset, ``learnable`` (default) or ``surgicai`` (spec §6.2).
        reward_type: ``dense`` ``-(d_cm/100 + d_rad/10)`` or ``sparse`` ``0/-1`` (spec §2.3).
        obs_type: ``pixels_agent_pos`` (wrist image + state) or ``agent_pos`` (state only, no rendering).
        image_height, image_width: wrist image size (640x480 as in the paper, 64-96 px for CPU work).
        render_mode: ``rgb_array`` for :meth:`NeedleEnv.render` (scene camera), or None.
        render_height, render_width: size of :meth:`NeedleEnv.render` frames.
        step_limit: truncation horizon (300, spec §2.4); ``gym.make`` adds the same ``TimeLimit``.
        randomize: SurgicAI's needle/grasp randomisation plus arm jitter; off gives the nominal scene.
        camera_dict: return ``pixels`` as ``{"wrist": image}`` instead of the bare image; LeRobot maps that to
            ``observation.images.wrist`` (a bare array would become ``observation.image``).
        threshold_scale: multiplies both success thresholds (position and rotation). 1 everywhere except when
            recording demos: ``sr-record --demo_threshold_scale`` ends a demo only once the expert is well inside
            the success region, so its last frames do not sit on the boundary (our choice, see
            ``RecordConfig``). The jaw rule is unchanged.
    """

    skill: str = "approach"
    thresholds: str = "learnable"
    reward_type: str = "dense"
    obs_type: str = "pixels_agent_pos"
    image_height: int = 96
    image_width: int = 96
    render_mode: str | None = None
    render_height: int = 240
    render_width: int = 320
    step_limit: int = 300
    randomize: bool = True
    camera_dict: bool = False
    threshold_scale: float = 1.0

    def __post_init__(self) -> None:
        self.skill = S.skill_from_name(self.skill).value
        if not 0.0 < self.threshold_scale <= 1.0:
            raise ValueError(f"threshold_scale must be in (0, 1], got {self.threshold_scale}")
        S.threshold_for(self.thresholds, Skill(self.skill))
        if self.reward_type not in REWARD_TYPES:
            raise ValueError(f"reward_type must be one of {REWARD_TYPES}, got {self.reward_type!r}")
        if self.obs_type not in OBS_TYPES:
            raise ValueError(f"obs_type must be one of {OBS_TYPES}, got {self.obs_type!r}")
        if self.render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {self.render_mode!r}")
        for name in ("image_height", "image_width", "render_height", "render_width"):
            value = getattr(self, name)
            if not 8 <= int(value) <= 2048:
                raise ValueError(f"{name} must be in [8, 2048], got {value}")
        if self.step_limit < 1:
            raise ValueError(f"step_limit must be >= 1, got {self.step_limit}")


class NeedleEnv(gym.Env):
    """One suturing skill; see the module docstring for the MDP."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 30}

    def __init__(self, **kwargs: Any) -> None:
        self.settings = NeedleEnvSettings(**kwargs)
        s = self.settings
        self.render_mode = s.render_mode
        self.action_space = gym.spaces.Box(-1.0, 1.0, shape=(7,), dtype=np.float32)
        spaces = {"agent_pos": gym.spaces.Box(-np.inf, np.inf, shape=(STATE_DIM,), dtype=np.float32)}
        if s.obs_type == "pixels_agent_pos":
            image = gym.spaces.Box(0, 255, shape=(s.image_height, s.image_width, 3), dtype=np.uint8)
            pixels = gym.spaces.Dict({"wrist": image}) if s.camera_dict else image
            spaces = {"pixels": pixels, **spaces}
        self.observation_space = gym.spaces.Dict(spaces)
        self._renderer = None
        self._set_skill(Skill(s.skill))
        # State, filled by reset().
        self.setpoints = [G.INIT_SETPOINTS[0].copy(), G.INIT_SETPOINTS[1].copy()]
        self.tool_poses = [G.setpoint_to_pose(sp, arm) for arm, sp in enumerate(self.setpoints)]
        self.needle_pose = G.make_pose(np.eye(3), G.NEEDLE_NOMINAL_CENTER.copy())
        self.holder: int | None = None
        self.tool_in_needle_grasp = np.eye(4)  # needle pose in the holder's tool frame
        self.goal = self.setpoints[self.active_arm].copy()
        self._goal_rot = np.eye(3)
        self._alt_goal_pos = np.zeros((0, 3))
        self._alt_goal_rot = np.zeros((0, 3, 3))
        self.grasp_angle = 0.0
        self.elapsed_steps = 0
        self._needs_reset = True

    # ----------------------------------------------------------------------------------------------- API
    @property
    def task(self) -> str:
        """Skill name, read by LeRobot's ``add_envs_task`` as the task string."""
        return self.skill.value

    @property
    def task_description(self) -> str:
        return self.skill.value

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if options and "skill" in options:
            self._set_skill(S.skill_from_name(options["skill"]))
        self._preposition(self.skill)
        self._compute_goal()
        self.elapsed_steps = 0
        self._needs_reset = False
        return self._observation(), self._info(*self._errors())

    def step(self, action):
        if self._needs_reset:
            raise RuntimeError("NeedleEnv.step() called before reset() or after the episode ended")
        a = np.asarray(action, dtype=np.float64)
        if a.shape != (7,):
            raise ValueError(f"action must have shape (7,), got {a.shape}")
        if not np.isfinite(a).all():
            raise ValueError(f"action contains NaN or inf: {a.tolist()}")
        a = np.clip(a, -1.0, 1.0)
        if self.skill is Skill.INSERT:
            a[6] = 0.0  # SurgicAI's INSERT forces the jaw action to 0 (spec §2.2)
        arm = self.active_arm
        sp = np.clip(self.setpoints[arm] + a * G.ACTION_STEP, G.SETPOINT_LOW, G.SETPOINT_HIGH)
        self.setpoints[arm] = sp
        self.tool_poses[arm] = G.setpoint_to_pose(sp, arm)
        self._update_grasp(arm)
        self._carry_needle()
        self.elapsed_steps += 1

        d_cm, d_rad = self._errors()
        success = self._is_success(d_cm, d_rad)
        if success and self.skill.needs_closed_jaw and self.holder != arm:
            self._attach(arm)  # SurgicAI attaches on APPROACH success (spec §3.1)
        dense = -(d_cm / 100.0 + d_rad / 10.0)
        reward = dense if self.settings.reward_type == "dense" else (0.0 if success else -1.0)
        truncated = self.elapsed_steps >= self.settings.step_limit and not success
        self._needs_reset = success or truncated
        return (
            self._observation(),
            float(reward),
            bool(success),
            bool(truncated),
            self._info(d_cm, d_rad, success),
        )

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        return self.render_camera("scene", self.settings.render_height, self.settings.render_width)

    def render_camera(self, camera: str, height: int, width: int) -> np.ndarray:
        """RGB frame from ``scene`` or ``wrist`` at any size (up to the offscreen buffer)."""
        renderer = self._get_renderer()
        renderer.set_state(
            self.needle_pose, tuple(self.tool_poses), (self.setpoints[0][6], self.setpoints[1][6])
        )
        return renderer.render(camera, height, width)

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def continue_with(self, skill: str | Skill) -> tuple[dict, dict]:
        """Switch to ``skill`` keeping the current scene (chained mode, spec §3.6); returns (obs, info).

        Scripted switches as in SurgicAI's chained env: entering PULLOUT opens PSM2's jaw (hand-over).
        """
        self._set_skill(S.skill_from_name(skill))
        if self.skill is Skill.PULLOUT:
            self.setpoints[G.PSM2][6] = G.JAW_OPEN
            if self.holder == G.PSM2:
                self.holder = None
        self._compute_goal()
        self.elapsed_steps = 0
        self._needs_reset = False
        return self._observation(), self._info(*self._errors())

    # ------------------------------------------------------------------------------------------ helpers
    def _set_skill(self, skill: Skill) -> None:
        self.skill = skill
        self.active_arm = skill.active_arm
        base = S.threshold_for(self.settings.thresholds, skill)
        scale = self.settings.threshold_scale
        self.threshold = S.Threshold(base.position_mm * scale, base.rotation_deg * scale)

    def _get_renderer(self):
        if self._renderer is None:
            from sr_imitation.envs.needle.rendering import SceneRenderer

            s = self.settings
            self._renderer = SceneRenderer(
                max(640, s.image_width, s.render_width), max(480, s.image_height, s.render_height)
            )
        return self._renderer

    def _uniform(self, half_range) -> np.ndarray | float:
        return self.np_random.uniform(-1.0, 1.0, size=np.shape(half_range)) * half_range

    def _jitter_pose(self, T: np.ndarray, jitter: tuple[float, float]) -> np.ndarray:
        if not self.settings.randomize:
            return T
        pos, ang = jitter
        rpy = self.np_random.uniform(-ang, ang, size=3)
        out = T @ G.rotation(G.rpy_to_matrix(*rpy))
        out[:3, 3] += self.np_random.uniform(-pos, pos, size=3)
        return out

    def _set_tool(self, arm: int, T: np.ndarray, jaw: float) -> None:
        sp = G.pose_to_setpoint(T, arm, jaw, G.INIT_SETPOINTS[arm][3:6])
        sp = np.clip(sp, G.SETPOINT_LOW, G.SETPOINT_HIGH)
        self.setpoints[arm] = sp
        self.tool_poses[arm] = G.setpoint_to_pose(sp, arm)

    def _park(self, arm: int) -> None:
        sp = G.INIT_SETPOINTS[arm].copy()
        if self.settings.randomize:
            pos, ang = PARKED_JITTER
            sp[:3] += self.np_random.uniform(-pos, pos, size=3)
            sp[3:6] += self.np_random.uniform(-ang, ang, size=3)
        self.setpoints[arm] = sp
        self.tool_poses[arm] = G.setpoint_to_pose(sp, arm)

    def _attach(self, arm: int) -> None:
        self.holder = arm
        self.tool_in_needle_grasp = G.invert(self.tool_poses[arm]) @ self.needle_pose

    def _carry_needle(self) -> None:
        if self.holder is not None:
            self.needle_pose = self.tool_poses[self.holder] @ self.tool_in_needle_grasp

    def _grasp_and_carry(self, arm: int, T_needle_goal: np.ndarray) -> None:
        """Move the holding ``arm`` so the needle lands near ``T_needle_goal`` (+ prepositioning noise)."""
        T_tool = self._jitter_pose(
            S.carried_tool_pose(T_needle_goal, self.tool_in_needle_grasp), PREPOSITION_JITTER
        )
        self._set_tool(arm, T_tool, 0.0)
        self._carry_needle()

    def _preposition(self, skill: Skill) -> None:
        """Analytic reset from the earlier skills' goals with SurgicAI's randomisation (spec §3, §6.2)."""
        rnd = self.settings.randomize
        centre = G.NEEDLE_NOMINAL_CENTER.copy()
        yaw = 0.0
        if rnd:
            centre[:2] += self._uniform(NEEDLE_XY_RANGE)
            yaw = float(self._uniform(NEEDLE_YAW_RANGE))
        self.needle_pose = G.make_pose(G.rot_z(yaw), centre)
        self.holder = None
        self.tool_in_needle_grasp = np.eye(4)
        self.setpoints[G.PSM1] = G.INIT_SETPOINTS[G.PSM1].copy()  # idle until REGRASP (spec §3.1)
        self.tool_poses[G.PSM1] = G.setpoint_to_pose(self.setpoints[G.PSM1], G.PSM1)
        if skill is Skill.APPROACH:
            self._park(G.PSM2)
            lo, hi = S.APPROACH_ANGLE_RANGE
            self.grasp_angle = float(self.np_random.uniform(lo, hi)) if rnd else 0.5 * (lo + hi)
            return
        lo, hi = S.CARRY_ANGLE_RANGE
        self.grasp_angle = float(self.np_random.uniform(lo, hi)) if rnd else 0.5 * (lo + hi)
        standoff = S.CARRY_STANDOFF_PLACE if skill is Skill.PLACE else S.CARRY_STANDOFF_INSERT
        T_grasp = S.grasp_pose(self.needle_pose, self.grasp_angle, standoff, G.PSM2)
        self._set_tool(G.PSM2, self._jitter_pose(T_grasp, PREPOSITION_JITTER), 0.0)
        self._attach(G.PSM2)
        if skill is Skill.PLACE:
            return
        if skill is Skill.INSERT:
            self._grasp_and_carry(G.PSM2, S.place_needle_pose(S.INSERT_ENTRY_STANDOFF))
            return
        self._grasp_and_carry(G.PSM2, S.insert_needle_pose())
        if skill is Skill.REGRASP:
            self._park(G.PSM1)
            return
        T_regrasp = S.grasp_pose(self.needle_pose, S.REGRASP_ANGLE, S.REGRASP_STANDOFF, G.PSM1)
        self._set_tool(G.PSM1, self._jitter_pose(T_regrasp, PREPOSITION_JITTER), 0.0)
        self._attach(G.PSM1)
        self.setpoints[G.PSM2][6] = G.JAW_OPEN  # PSM2 releases (spec §3.5)

    def goal_tool_pose(self) -> np.ndarray:
        """World pose the active tool must reach (the desired goal), recomputed from the current scene."""
        sk, N = self.skill, self.needle_pose
        if sk is Skill.APPROACH:
            return S.grasp_pose(N, self.grasp_angle, S.APPROACH_STANDOFF, G.PSM2)
        if sk is Skill.REGRASP:
            return S.grasp_pose(N, S.REGRASP_ANGLE, S.REGRASP_STANDOFF, G.PSM1)
        target = {
            Skill.PLACE: S.place_needle_pose,
            Skill.INSERT: S.insert_needle_pose,
            Skill.PULLOUT: S.pullout_needle_pose,
        }[sk]()
        return S.carried_tool_pose(target, self.tool_in_needle_grasp)

    def _compute_goal(self) -> None:
        """Desired goal, computed once per skill from the analytic recipe (spec §2.6 item 2, §6.5)."""
        arm = self.active_arm
        base_inv = G.invert(G.BASE_POSES[arm])
        local = base_inv @ self.goal_tool_pose()
        self._goal_rot = local[:3, :3].copy()
        self.goal = np.concatenate(
            [local[:3, 3], G.matrix_to_rpy(local[:3, :3], self.setpoints[arm][3:6]), [0.0]]
        )
        if self.skill is Skill.APPROACH:
            alts = [
                base_inv @ S.grasp_pose(self.needle_pose, th, S.APPROACH_STANDOFF, G.PSM2)
                for th in S.APPROACH_ALTERNATIVE_ANGLES
            ]
            self._alt_goal_pos = np.array([T[:3, 3] for T in alts])
            self._alt_goal_rot = np.array([T[:3, :3] for T in alts])

    def _errors(self) -> tuple[float, float]:
        """Position error (cm) and geodesic rotation error (rad) of the active setpoint to the goal."""
        sp = self.setpoints[self.active_arm]
        d_cm = 100.0 * math.sqrt(float(np.dot(sp[:3] - self.goal[:3], sp[:3] - self.goal[:3])))
        R = G.rpy_to_matrix(sp[3], sp[4], sp[5])
        return d_cm, G.rotation_angle(R, self._goal_rot)

    def _is_success(self, d_cm: float, d_rad: float) -> bool:
        sp = self.setpoints[self.active_arm]
        th = self.threshold
        if self.skill.needs_closed_jaw and sp[6] > S.JAW_CLOSED_MAX:
            return False
        if self.skill is Skill.APPROACH:
            # Any of SurgicAI's 25 alternative grasp goals (spec §3.1).
            R = G.rpy_to_matrix(sp[3], sp[4], sp[5])
            d = 100.0 * np.linalg.norm(self._alt_goal_pos - sp[:3], axis=1)
            cos = (np.einsum("kij,ij->k", self._alt_goal_rot, R) - 1.0) * 0.5
            ang = np.arccos(np.clip(cos, -1.0, 1.0))
            return bool(np.any((d <= th.position_cm) & (ang <= th.rotation_rad)))
        return d_cm <= th.position_cm and d_rad <= th.rotation_rad

    def _valid_grasp(self, arm: int) -> bool:
        """Is ``arm``'s TCP near a grasp pose on the needle arc (spec §6.2 weld rule)?"""
        q = G.invert(self.needle_pose) @ self.tool_poses[arm]
        px, py, pz = q[:3, 3]
        theta = min(max(math.atan2(py, -px), 0.0), G.NEEDLE_ARC)
        F = G.needle_point_frame(theta)
        radial = math.hypot(px - F[0, 3], py - F[1, 3])
        if radial > GRASP_RADIAL_TOL or not GRASP_STANDOFF_RANGE[0] <= pz <= GRASP_STANDOFF_RANGE[1]:
            return False
        R_rel = F[:3, :3].T @ q[:3, :3]
        return min(G.rotation_angle(R_rel, Rg) for Rg in G.GRASP_ROTATIONS) <= GRASP_ROTATION_TOL

    def _update_grasp(self, arm: int) -> None:
        jaw = self.setpoints[arm][6]
        if self.holder == arm and jaw > S.JAW_RELEASE_MIN:
            self.holder = None
        elif self.holder != arm and jaw <= S.JAW_CLOSED_MAX and self._valid_grasp(arm):
            self._attach(arm)

    def _state(self) -> np.ndarray:
        cur = self.setpoints[self.active_arm].copy()
        goal = self.goal.copy()
        cur[:3] *= 100.0
        goal[:3] *= 100.0
        return np.concatenate([cur, goal, goal - cur, cur, goal]).astype(np.float32)

    def _observation(self) -> dict[str, np.ndarray]:
        obs = {"agent_pos": self._state()}
        if self.settings.obs_type == "pixels_agent_pos":
            image = self.render_camera("wrist", self.settings.image_height, self.settings.image_width)
            obs["pixels"] = {"wrist": image} if self.settings.camera_dict else image
        return obs

    def _info(self, d_cm: float, d_rad: float, success: bool = False) -> dict[str, Any]:
        return {
            "is_success": bool(success),
            "position_error_mm": 10.0 * d_cm,
            "rotation_error_deg": math.degrees(d_rad),
            "holder": -1 if self.holder is None else self.holder,
        }
