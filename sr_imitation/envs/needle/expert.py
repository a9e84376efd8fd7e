"""Scripted expert: waypoints plus SurgicAI's noisy saturating proportional controller.

Controller (spec §4.2, fitted to SurgicAI's shipped demos), per pose axis i with ``e_i`` = waypoint - setpoint
in cm (xyz) or rad (rpy)::

    a_i = sign(e_i) * 0.7 * clip(|e_i| / c, 0.2, 1.0) + U(-0.2, 0.2),   c = 0.93 cm (xyz), 0.9 rad (rpy)

Jaw: 0, except on the final waypoint of APPROACH and REGRASP, where it closes (-1 per step) once
``||e_xyz|| < 0.15 cm``. Waypoints (spec §6.3) advance when within 0.5 mm and 3 degrees.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sr_imitation.envs.needle import geometry as G
from sr_imitation.envs.needle import skills as S
from sr_imitation.envs.needle.env import NeedleEnv
from sr_imitation.envs.needle.skills import Skill


@dataclass
class ExpertSettings:
    """Gains and tolerances of :class:`NeedleExpert` (defaults from spec §4.2 and §6.3)."""

    gain_cap: float = 0.7
    gain_floor: float = 0.2
    scale_cm: float = 0.93
    scale_rad: float = 0.9
    noise: float = 0.2
    jaw_close_cm: float = 0.15
    waypoint_tol_mm: float = 0.5
    waypoint_tol_deg: float = 3.0
    insert_waypoints: int = 4
    pullout_rotation_waypoints: int = 3

    def __post_init__(self) -> None:
        if not 0.0 < self.gain_cap <= 1.0:
            raise ValueError(f"gain_cap must be in (0, 1], got {self.gain_cap}")
        if not 0.0 <= self.gain_floor <= 1.0:
            raise ValueError(f"gain_floor must be in [0, 1], got {self.gain_floor}")
        if self.scale_cm <= 0 or self.scale_rad <= 0:
            raise ValueError("scale_cm and scale_rad must be positive")
        if not 0.0 <= self.noise < 1.0:
            raise ValueError(f"noise must be in [0, 1), got {self.noise}")
        if self.insert_waypoints < 1 or self.pullout_rotation_waypoints < 1:
            raise ValueError("waypoint counts must be >= 1")


class NeedleExpert:
    """Scripted expert for the skill the env is running; call :meth:`reset` after each env reset."""

    def __init__(
        self, env: NeedleEnv, seed: int | None = None, settings: ExpertSettings | None = None
    ) -> None:
        self.env = env.unwrapped if hasattr(env, "unwrapped") else env
        self.settings = settings or ExpertSettings()
        self.rng = np.random.default_rng(seed)
        self.waypoints: list[np.ndarray] = []  # world tool poses; the last one is the env's goal
        self.index = 0

    def reset(self, seed: int | None = None) -> None:
        """Plan waypoints from the env's current scene (after ``env.reset`` or ``env.continue_with``)."""
        if seed is not None:
            self.rng = np.random.default_rng(seed)
        self.waypoints = self._plan()
        self.index = 0

    def _plan(self) -> list[np.ndarray]:
        env = self.env
        skill = env.skill
        goal = env.goal_tool_pose()
        tool = env.tool_poses[env.active_arm]
        if skill in (Skill.APPROACH, Skill.REGRASP):
            # Hover 10 mm back along the tool axis, then descend onto the grasp pose (spec §6.3).
            return [goal @ G.translation(0.0, 0.0, -10.0 * G.MM), goal]
        if skill is Skill.PLACE:
            # SurgicAI's mid waypoint (entry.x - 35 mm, entry.y, grasp.z + 25 mm), same orientation (§3.2).
            mid = tool.copy()
            mid[:3, 3] = [G.ENTRY_POSE[0, 3] - 35.0 * G.MM, G.ENTRY_POSE[1, 3], tool[2, 3] + 25.0 * G.MM]
            return [mid, goal]
        grip = env.tool_in_needle_grasp
        N0 = env.needle_pose
        if skill is Skill.INSERT:
            # Arc-following: intermediate needle poses between the current and the goal needle pose (§6.3).
            N1 = S.insert_needle_pose()
            n = self.settings.insert_waypoints
            return [S.carried_tool_pose(G.interpolate_pose(N0, N1, k / n), grip) for k in range(1, n)] + [
                goal
            ]
        # PULLOUT: rotate about the needle centre first (extraction along the arc), then carry to hand-over.
        N1 = S.pullout_needle_pose()
        rotated = G.make_pose(N1[:3, :3], N0[:3, 3])
        n = self.settings.pullout_rotation_waypoints
        return [
            S.carried_tool_pose(G.interpolate_pose(N0, rotated, k / n), grip) for k in range(1, n + 1)
        ] + [goal]

    def act(self) -> np.ndarray:
        """Next action in [-1, 1]^7 for the env's active arm."""
        env, s = self.env, self.settings
        arm = env.active_arm
        sp = env.setpoints[arm]
        final = self.index >= len(self.waypoints) - 1
        if final:
            target = env.goal
        else:
            target = G.pose_to_setpoint(self.waypoints[self.index], arm, 0.0, sp[3:6])
            d_mm = 1000.0 * float(np.linalg.norm(target[:3] - sp[:3]))
            d_deg = np.degrees(G.rotation_angle(G.rpy_to_matrix(*sp[3:6]), G.rpy_to_matrix(*target[3:6])))
            if d_mm <= s.waypoint_tol_mm and d_deg <= s.waypoint_tol_deg:
                self.index += 1
                return self.act()
        err = np.empty(6)
        err[:3] = 100.0 * (target[:3] - sp[:3])
        err[3:] = target[3:6] - sp[3:6]
        scale = np.array([s.scale_cm] * 3 + [s.scale_rad] * 3)
        mag = s.gain_cap * np.clip(np.abs(err) / scale, s.gain_floor, 1.0)
        action = np.zeros(7)
        action[:6] = np.sign(err) * mag + self.rng.uniform(-s.noise, s.noise, size=6)
        if final and env.skill.needs_closed_jaw and np.linalg.norm(err[:3]) < s.jaw_close_cm:
            action[6] = -1.0
        return np.clip(action, -1.0, 1.0).astype(np.float32)


def run_expert_episode(env: NeedleEnv, seed: int, expert_seed: int | None = None) -> dict:
    """Reset ``env`` with ``seed`` and run the expert until success or truncation; returns a summary."""
    obs, info = env.reset(seed=seed)
    expert = NeedleExpert(env, seed=seed if expert_seed is None else expert_seed)
    expert.reset()
    steps = 0
    while True:
        obs, _, terminated, truncated, info = env.step(expert.act())
        steps += 1
        if terminated or truncated:
            break
    return {"success": bool(info["is_success"]), "steps": steps, **info}
