"""MJCF for the suturing scene: phantom with a wound ridge, a kinematic needle and two kinematic tools.

Every moving thing is a mocap body (spec §6.2: no arm kinematics, no needle or tissue physics), so the
commanded pose is the measured pose. Shadows and multisampling are off, curved geoms use few slices and the
table is a box (MuJoCo subdivides planes), which makes llvmpipe rendering ~5x faster on CPU.
"""

from __future__ import annotations

import math

import numpy as np

from sr_imitation.envs.needle.geometry import (
    ENTRY_POSE,
    EXIT_POSE,
    MM,
    NEEDLE_ARC,
    NEEDLE_NOMINAL_CENTER,
    NEEDLE_RADIUS,
    matrix_to_quat,
)

NEEDLE_SEGMENTS = 12
NEEDLE_WIRE_RADIUS = 0.4 * MM
JAW_LENGTH = 9.0 * MM
JAW_HALF_OPENING_PER_UNIT = 0.5  # hinge angle (rad) of each jaw per unit of commanded jaw (0.8 = open)
WRIST_CAMERA = "wrist"
SCENE_CAMERA = "scene"
# Wrist camera on PSM2's tool (tool frame): beside the wrist, looking past the jaws (spec §1.4, §7).
WRIST_CAMERA_POS = np.array([6.0, 0.0, -12.0]) * MM
WRIST_CAMERA_TARGET = np.array([0.0, 0.0, 14.0]) * MM
# Scene camera: above and in front of the wound, looking at the suture site (cf. SAI's endoscope, spec §1.4).
SCENE_CAMERA_POS = np.array([5.0, -35.0, 150.0]) * MM
SCENE_CAMERA_TARGET = np.array([5.0, 50.0, 86.0]) * MM


def _fmt(v) -> str:
    return " ".join(f"{float(x):.6g}" for x in np.ravel(v))


def _look_at_xyaxes(pos: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> str:
    """MuJoCo camera ``xyaxes`` so that the camera at ``pos`` looks at ``target``."""
    fwd = target - pos
    fwd = fwd / np.linalg.norm(fwd)
    x = np.cross(fwd, np.asarray(up))
    x = x / np.linalg.norm(x)
    y = np.cross(x, fwd)
    return _fmt(np.concatenate([x, y]))


def _needle_geoms() -> str:
    geoms = []
    for i in range(NEEDLE_SEGMENTS):
        a0 = NEEDLE_ARC * i / NEEDLE_SEGMENTS
        a1 = NEEDLE_ARC * (i + 1) / NEEDLE_SEGMENTS
        p0 = (-NEEDLE_RADIUS * math.cos(a0), NEEDLE_RADIUS * math.sin(a0), 0.0)
        p1 = (-NEEDLE_RADIUS * math.cos(a1), NEEDLE_RADIUS * math.sin(a1), 0.0)
        mat = "tip" if i == NEEDLE_SEGMENTS - 1 else "needle"
        geoms.append(
            f'<geom type="capsule" fromto="{_fmt(p0)} {_fmt(p1)}" size="{NEEDLE_WIRE_RADIUS}" '
            f'material="{mat}"/>'
        )
    return "\n      ".join(geoms)


def _tool_body(name: str, rgba: str, camera: str) -> str:
    """A tool: mocap body at the TCP (wrist-yaw axis, spec §1.3), z toward the jaws, shaft along -z."""
    j = JAW_LENGTH
    return f"""
    <body name="{name}" mocap="true">
      <geom type="cylinder" fromto="0 0 -0.011 0 0 -0.2" size="0.004" rgba="{rgba}"/>
      <geom type="cylinder" fromto="0 0 -0.0015 0 0 -0.011" size="0.0022" rgba="0.55 0.55 0.6 1"/>
      <body name="{name}_jaw_a">
        <joint name="{name}_jaw_a" type="hinge" axis="1 0 0"/>
        <geom type="box" pos="0 0.0004 {j / 2}" size="0.0007 0.0004 {j / 2}" rgba="0.75 0.75 0.8 1"/>
      </body>
      <body name="{name}_jaw_b">
        <joint name="{name}_jaw_b" type="hinge" axis="1 0 0"/>
        <geom type="box" pos="0 -0.0004 {j / 2}" size="0.0007 0.0004 {j / 2}" rgba="0.75 0.75 0.8 1"/>
      </body>
      {camera}
    </body>"""


def _face_box(pose: np.ndarray, rgba: str) -> str:
    """A ridge face: box whose top face passes through the entry/exit frame with +z its normal."""
    half = np.array([6.0, 10.0, 6.0]) * MM  # a short ridge: tools over it stay outside the tissue
    centre = pose[:3, 3] - pose[:3, 2] * half[2]
    return (
        f'<geom type="box" pos="{_fmt(centre)}" quat="{_fmt(matrix_to_quat(pose[:3, :3]))}" '
        f'size="{_fmt(half)}" rgba="{rgba}"/>'
    )


def _marker(pose: np.ndarray, rgba: str) -> str:
    p = pose[:3, 3] + pose[:3, 2] * 0.05 * MM
    return (
        f'<geom type="cylinder" pos="{_fmt(p)}" quat="{_fmt(matrix_to_quat(pose[:3, :3]))}" '
        f'size="{0.9 * MM} {0.05 * MM}" rgba="{rgba}"/>'
    )


def build_scene_xml(offscreen_width: int = 640, offscreen_height: int = 480) -> str:
    """The whole scene as an MJCF string; ``offscreen_*`` bound the largest image that can be rendered."""
    surface_z = NEEDLE_NOMINAL_CENTER[2] - NEEDLE_WIRE_RADIUS
    pad_half = np.array([45.0, 45.0, 8.0]) * MM
    pad_centre = np.array([-10.0 * MM, 50.0 * MM, surface_z - pad_half[2]])
    tissue = "0.85 0.55 0.55 1"
    wrist_camera = (
        f'<camera name="{WRIST_CAMERA}" pos="{_fmt(WRIST_CAMERA_POS)}" '
        f'xyaxes="{_look_at_xyaxes(WRIST_CAMERA_POS, WRIST_CAMERA_TARGET, up=(1.0, 0.0, 0.0))}" fovy="70"/>'
    )
    return f"""<mujoco model="sr_needle">
  <compiler angle="radian"/>
  <option gravity="0 0 0" timestep="0.005"/>
  <statistic extent="0.2" center="{_fmt(pad_centre)}"/>
  <visual>
    <quality shadowsize="0" offsamples="0" numslices="12" numstacks="4" numquads="1"/>
    <global offwidth="{int(offscreen_width)}" offheight="{int(offscreen_height)}"/>
    <map znear="0.002" zfar="20"/>
    <headlight ambient="0.45 0.45 0.45" diffuse="0.5 0.5 0.5" specular="0.1 0.1 0.1"/>
  </visual>
  <asset>
    <material name="needle" rgba="0.82 0.82 0.88 1" specular="0.8" shininess="0.8"/>
    <material name="tip" rgba="0.2 0.35 0.9 1" specular="0.8" shininess="0.8"/>
  </asset>
  <worldbody>
    <light directional="true" pos="0 0 1" dir="0 0.3 -1" castshadow="false" diffuse="0.5 0.5 0.5"/>
    <geom name="table" type="box" pos="0 0.05 {surface_z - 2 * pad_half[2] - 0.005}" size="0.3 0.3 0.005"
          rgba="0.25 0.3 0.35 1"/>
    <geom name="pad" type="box" pos="{_fmt(pad_centre)}" size="{_fmt(pad_half)}" rgba="{tissue}"/>
    {_face_box(ENTRY_POSE, tissue)}
    {_face_box(EXIT_POSE, tissue)}
    {_marker(ENTRY_POSE, "0.1 0.8 0.2 1")}
    {_marker(EXIT_POSE, "0.9 0.8 0.1 1")}
    <camera name="{SCENE_CAMERA}" pos="{_fmt(SCENE_CAMERA_POS)}"
            xyaxes="{_look_at_xyaxes(SCENE_CAMERA_POS, SCENE_CAMERA_TARGET)}" fovy="50"/>
    <body name="needle" mocap="true">
      {_needle_geoms()}
    </body>
    {_tool_body("psm1", "0.2 0.2 0.22 1", "")}
    {_tool_body("psm2", "0.3 0.3 0.34 1", wrist_camera)}
  </worldbody>
</mujoco>
"""
