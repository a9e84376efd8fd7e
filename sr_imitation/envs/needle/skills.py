"""The five suturing skills: order, active arm, success thresholds and SurgicAI's goal recipes.

Goal recipes follow ``shared/notes/surgicai-needle-spec.md`` §3; thresholds §3.7 (``surgicai``) and §6.2
(``learnable``, the default).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from sr_imitation.envs.needle.geometry import (
    DEG,
    ENTRY_POSE,
    EXIT_POSE,
    GRASP_ROTATIONS,
    MM,
    PSM1,
    PSM2,
    invert,
    needle_point_frame,
    rot_x,
    rot_y,
    rotation,
    translation,
)


class Skill(StrEnum):
    """Skills in stream order (spec §6.1)."""

    APPROACH = "approach"
    PLACE = "place"
    INSERT = "insert"
    REGRASP = "regrasp"
    PULLOUT = "pullout"

    @property
    def active_arm(self) -> int:
        """PSM2 drives approach/place/insert, PSM1 regrasp/pullout (spec §3.7)."""
        return PSM2 if self in (Skill.APPROACH, Skill.PLACE, Skill.INSERT) else PSM1

    @property
    def needs_closed_jaw(self) -> bool:
        """APPROACH and REGRASP also require commanded jaw <= 0.1 (spec §2.4)."""
        return self in (Skill.APPROACH, Skill.REGRASP)


SKILLS: tuple[Skill, ...] = tuple(Skill)
SKILL_NAMES: tuple[str, ...] = tuple(s.value for s in Skill)
"""Stream order (Appendix A.2, "Skill stream")."""

PRS_PAIRS: tuple[tuple[str, str], ...] = (
    ("approach", "place"),
    ("place", "insert"),
    ("insert", "regrasp"),
    ("regrasp", "pullout"),
    ("approach", "insert"),
    ("place", "regrasp"),
    ("insert", "pullout"),
)
"""The seven pre-registered workflow-ordered SurgicAI PRS pairs (Appendix A.2, "Evaluation protocol")."""


@dataclass(frozen=True)
class Threshold:
    """Success threshold: position in mm and geodesic rotation in degrees."""

    position_mm: float
    rotation_deg: float

    @property
    def position_cm(self) -> float:
        return self.position_mm / 10.0

    @property
    def rotation_rad(self) -> float:
        return self.rotation_deg * DEG


# Spec §3.7 (SurgicAI's Env_info values) and §6.2 (learnable: >= 2x the 1 mm step and >= 3x the 3 deg step).
THRESHOLD_PRESETS: dict[str, dict[Skill, Threshold]] = {
    "surgicai": {
        Skill.APPROACH: Threshold(3.0, 10.0),
        Skill.PLACE: Threshold(5.0, 10.0),
        Skill.INSERT: Threshold(1.0, 5.0),
        Skill.REGRASP: Threshold(1.0, 10.0),
        Skill.PULLOUT: Threshold(5.0, 5.0),
    },
    "learnable": {
        Skill.APPROACH: Threshold(3.0, 15.0),
        Skill.PLACE: Threshold(3.0, 10.0),
        Skill.INSERT: Threshold(2.0, 10.0),
        Skill.REGRASP: Threshold(2.0, 15.0),
        Skill.PULLOUT: Threshold(5.0, 15.0),
    },
}
JAW_CLOSED_MAX = 0.1  # jaw rule for success and grasping (spec §2.4, §6.2)
JAW_RELEASE_MIN = 0.2  # the needle is released when the holder's jaw opens past this (spec §6.2)

# Grasp stand-offs and angles (spec §3, §6.1).
APPROACH_STANDOFF = 7.0 * MM
APPROACH_ANGLE_RANGE = (5.0 * DEG, 20.0 * DEG)
APPROACH_ALTERNATIVE_ANGLES = np.linspace(5.0 * DEG, 20.0 * DEG, 25)
CARRY_STANDOFF_PLACE = 10.0 * MM
CARRY_STANDOFF_INSERT = 7.0 * MM
CARRY_ANGLE_RANGE = (10.0 * DEG, 50.0 * DEG)
REGRASP_ANGLE = 105.0 * DEG
REGRASP_STANDOFF = 5.0 * MM
INSERT_ENTRY_STANDOFF = 1.0 * MM
# R_align for INSERT and PULLOUT: needle point tangent along the exit's outward normal (spec §3.3, §3.5).
R_ALIGN = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])


def grasp_pose(T_needle: np.ndarray, theta: float, standoff: float, arm: int) -> np.ndarray:
    """World tool pose grasping the needle at arc angle ``theta`` (spec §3 ``grasp(θ, h, arm)``)."""
    return (
        T_needle
        @ needle_point_frame(theta)
        @ translation(0.0, 0.0, standoff)
        @ rotation(GRASP_ROTATIONS[arm])
    )


def needle_pose_for_target(
    T_target: np.ndarray, theta: float, R_align: np.ndarray | None = None
) -> np.ndarray:
    """Needle pose putting its ``theta`` frame (times ``R_align``) on ``T_target`` (spec §3, carrying)."""
    T_align = np.eye(4) if R_align is None else rotation(R_align)
    return T_target @ invert(T_align) @ invert(needle_point_frame(theta))


def place_target(standoff: float = 0.0) -> np.ndarray:
    """Tip frame goal for PLACE: Entry1 · Rx(-90°), moved ``standoff`` along the entry's outward normal."""
    T = ENTRY_POSE @ rotation(rot_x(-90.0 * DEG))
    T = T.copy()
    T[:3, 3] += ENTRY_POSE[:3, 2] * standoff
    return T


def place_needle_pose(standoff: float = 0.0) -> np.ndarray:
    """Needle pose with the tip (120°) at Entry1 pointing into tissue (spec §3.2)."""
    return needle_pose_for_target(place_target(standoff), 120.0 * DEG)


def insert_needle_pose() -> np.ndarray:
    """Needle pose with the 100° point 2 mm beyond Exit1, tangent along its normal (spec §3.3)."""
    return needle_pose_for_target(EXIT_POSE @ translation(2.0 * MM, 0.0, 0.0), 100.0 * DEG, R_ALIGN)


def pullout_needle_pose() -> np.ndarray:
    """Hand-over needle pose: 110° frame on Exit1 · Ry(-50°), shifted +30 mm x and +30 mm z (spec §3.5)."""
    target = translation(30.0 * MM, 0.0, 30.0 * MM) @ EXIT_POSE @ rotation(rot_y(-50.0 * DEG))
    return needle_pose_for_target(target, 110.0 * DEG, R_ALIGN)


def carried_tool_pose(T_needle_goal: np.ndarray, T_tool_needle: np.ndarray) -> np.ndarray:
    """Tool pose that carries the needle (held with needle-in-tool ``T_tool_needle``) to ``T_needle_goal``."""
    return T_needle_goal @ invert(T_tool_needle)


def skill_from_name(name: str | Skill) -> Skill:
    if isinstance(name, Skill):
        return name
    try:
        return Skill(str(name).lower())
    except ValueError:
        raise ValueError(f"Unknown skill {name!r}; expected one of {list(SKILL_NAMES)}") from None


def threshold_for(preset: str, skill: Skill) -> Threshold:
    if preset not in THRESHOLD_PRESETS:
        raise ValueError(f"Unknown threshold preset {preset!r}; expected one of {sorted(THRESHOLD_PRESETS)}")
    return THRESHOLD_PRESETS[preset][skill]
