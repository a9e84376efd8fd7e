"""Rigid transforms, SurgicAI's RPY convention and the suturing scene's fixed geometry.

All numbers come from ``shared/notes/surgicai-needle-spec.md`` (§1, §3), converted from AMBF millimetres to
metres. Poses are 4x4 homogeneous matrices in metres; RPY follows KDL ``Rotation.RPY`` (fixed-axis X-Y-Z,
``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``), spec §0.
"""

from __future__ import annotations

import math

import numpy as np

MM = 1e-3
DEG = math.pi / 180.0


def rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rpy_to_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """KDL ``Rotation.RPY``: Rz(yaw) @ Ry(pitch) @ Rx(roll), written out for speed."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def matrix_to_rpy(R: np.ndarray, near: np.ndarray | None = None) -> np.ndarray:
    """Inverse of :func:`rpy_to_matrix` (principal branch, |pitch| <= 90 deg).

    With ``near`` (a reference RPY), each angle is moved by multiples of 2*pi onto the branch nearest to it,
    so that ``goal - current`` has no 2*pi jumps (spec §6.2).
    """
    pitch = math.asin(max(-1.0, min(1.0, -R[2, 0])))
    roll = math.atan2(R[2, 1], R[2, 2])
    yaw = math.atan2(R[1, 0], R[0, 0])
    out = np.array([roll, pitch, yaw])
    if near is not None:
        out = near + (out - near + math.pi) % (2 * math.pi) - math.pi
    return out


def make_pose(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = p
    return T


def translation(x: float, y: float, z: float) -> np.ndarray:
    return make_pose(np.eye(3), np.array([x, y, z]))


def rotation(R: np.ndarray) -> np.ndarray:
    return make_pose(R, np.zeros(3))


def invert(T: np.ndarray) -> np.ndarray:
    Ti = np.eye(4)
    Rt = T[:3, :3].T
    Ti[:3, :3] = Rt
    Ti[:3, 3] = -Rt @ T[:3, 3]
    return Ti


def rotation_angle(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Geodesic angle (rad) between two rotation matrices."""
    c = (float(np.sum(Ra * Rb)) - 1.0) * 0.5
    return math.acos(max(-1.0, min(1.0, c)))


def axis_angle_matrix(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues' formula for a unit ``axis``."""
    x, y, z = axis
    K = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + math.sin(angle) * K + (1.0 - math.cos(angle)) * (K @ K)


def matrix_log(R: np.ndarray) -> np.ndarray:
    """Rotation vector (axis * angle) of ``R``; robust near 0 and pi."""
    angle = math.acos(max(-1.0, min(1.0, (np.trace(R) - 1.0) * 0.5)))
    if angle < 1e-9:
        return np.zeros(3)
    if math.pi - angle < 1e-6:
        # Near pi: take the axis from the largest diagonal entry of (R + I) / 2.
        M = (R + np.eye(3)) * 0.5
        i = int(np.argmax(np.diag(M)))
        axis = M[:, i] / math.sqrt(max(M[i, i], 1e-12))
        return axis / np.linalg.norm(axis) * angle
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return w * (angle / (2.0 * math.sin(angle)))


def interpolate_pose(Ta: np.ndarray, Tb: np.ndarray, s: float) -> np.ndarray:
    """Pose at fraction ``s`` from ``Ta`` to ``Tb`` (linear position, geodesic rotation)."""
    w = matrix_log(Ta[:3, :3].T @ Tb[:3, :3])
    angle = float(np.linalg.norm(w))
    R = Ta[:3, :3] if angle < 1e-12 else Ta[:3, :3] @ axis_angle_matrix(w / angle, s * angle)
    return make_pose(R, (1.0 - s) * Ta[:3, 3] + s * Tb[:3, 3])


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z), MuJoCo's convention."""
    t = np.trace(R)
    if t > 0.0:
        s = math.sqrt(t + 1.0) * 2.0
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2]) * 2.0
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] > R[2, 2]:
        s = math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2]) * 2.0
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1]) * 2.0
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.array(q)
    return q / np.linalg.norm(q)


# --- Needle (spec §1.1) ---------------------------------------------------------------------------------
NEEDLE_RADIUS = 10.18 * MM
NEEDLE_ARC = 120.0 * DEG  # tail at 0 deg, tip at 120 deg
NEEDLE_NOMINAL_CENTER = np.array([-20.79, 56.20, 71.17]) * MM  # centre, lying flat, yaw 0


def needle_point_frame(theta: float) -> np.ndarray:
    """Frame at arc angle ``theta`` (needle frame): origin p(theta), x to the centre, y forward tangent."""
    return make_pose(
        rot_z(-theta), np.array([-NEEDLE_RADIUS * math.cos(theta), NEEDLE_RADIUS * math.sin(theta), 0.0])
    )


# --- Phantom entry / exit (spec §1.2) -------------------------------------------------------------------
ENTRY_POSE = make_pose(rot_y(-0.805), np.array([-3.74, 44.19, 75.00]) * MM)
EXIT_POSE = make_pose(rot_y(0.805), np.array([4.08, 44.19, 74.86]) * MM)

# --- Arms (spec §1.3); fixed-axis RPY, verified to put both parked TCPs ~36 mm above the needle ----------
PSM1, PSM2 = 0, 1
ARM_NAMES = ("psm1", "psm2")
BASE_POSES = (
    make_pose(rpy_to_matrix(0.6981, -0.5236, -math.pi), np.array([100.0, 134.6, 135.0]) * MM),
    make_pose(rpy_to_matrix(0.6981, 0.5236, -math.pi), np.array([-100.0, 134.6, 135.0]) * MM),
)
# Parked setpoints [x, y, z (m), roll, pitch, yaw (rad), jaw] in each arm's base frame.
INIT_SETPOINTS = (
    np.array([0.04629, 0.00752, -0.08174, -3.5980, -0.0576, 1.2739, 0.8]),
    np.array([-0.03721, 0.01213, -0.08036, -2.7039, 0.0769, 2.0361, 0.8]),
)
# Grasp rotations R_g (tool z against the needle-plane normal), spec §3.
GRASP_ROTATIONS = (
    np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]),
    np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]),
)
# INSERT's setpoint limits, used for every skill (spec §2.2, §6.1): x, y, z (m), roll, pitch, yaw (rad), jaw.
SETPOINT_LOW = np.array([-0.1, -0.1, -0.25, -270 * DEG, -80 * DEG, -260 * DEG, 0.0])
SETPOINT_HIGH = np.array([0.1, 0.1, 0.05, -90 * DEG, 80 * DEG, 260 * DEG, 1.0])
JAW_OPEN = 0.8
# SurgicAI's default benchmark step sizes (spec §2.2, §6.1): 1 mm, 3 deg, 0.05 jaw.
ACTION_STEP = np.array([1.0 * MM] * 3 + [3.0 * DEG] * 3 + [0.05])


def setpoint_to_pose(setpoint: np.ndarray, arm: int) -> np.ndarray:
    """World pose of an arm's tool (TCP at the wrist-yaw axis) from its base-frame setpoint."""
    local = make_pose(rpy_to_matrix(*setpoint[3:6]), setpoint[:3])
    return BASE_POSES[arm] @ local


def pose_to_setpoint(T_world: np.ndarray, arm: int, jaw: float, near: np.ndarray | None) -> np.ndarray:
    """Base-frame setpoint vector of a world tool pose; RPY on the branch nearest ``near`` (RPY)."""
    local = invert(BASE_POSES[arm]) @ T_world
    return np.concatenate([local[:3, 3], matrix_to_rpy(local[:3, :3], near), [jaw]])
