"""Offscreen MuJoCo rendering of the needle scene (EGL by default, shadows/reflections/MSAA off)."""

from __future__ import annotations

from sr_imitation.offscreen import setup_offscreen_rendering

setup_offscreen_rendering()  # must precede the first `import mujoco` (integration notes §5)

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from sr_imitation.envs.needle.geometry import matrix_to_quat  # noqa: E402
from sr_imitation.envs.needle.scene import JAW_HALF_OPENING_PER_UNIT, build_scene_xml  # noqa: E402


class SceneRenderer:
    """Owns the MuJoCo model/data and one ``mujoco.Renderer`` per image size; call :meth:`close` when done."""

    def __init__(self, max_width: int = 640, max_height: int = 480) -> None:
        self.model = mujoco.MjModel.from_xml_string(build_scene_xml(max_width, max_height))
        self.data = mujoco.MjData(self.model)
        self._renderers: dict[tuple[int, int], mujoco.Renderer] = {}
        m = self.model
        self._mocap = {
            name: int(m.body_mocapid[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, name)])
            for name in ("needle", "psm1", "psm2")
        }
        self._jaw_qpos = {
            arm: (
                int(m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, f"{arm}_jaw_a")]),
                int(m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, f"{arm}_jaw_b")]),
            )
            for arm in ("psm1", "psm2")
        }

    def set_state(
        self, needle_pose: np.ndarray, tool_poses: tuple[np.ndarray, ...], jaws: tuple[float, ...]
    ) -> None:
        """Place the needle and both tools (world 4x4 poses) and open the jaws, then run kinematics."""
        d = self.data
        for name, T in (("needle", needle_pose), ("psm1", tool_poses[0]), ("psm2", tool_poses[1])):
            i = self._mocap[name]
            d.mocap_pos[i] = T[:3, 3]
            d.mocap_quat[i] = matrix_to_quat(T[:3, :3])
        for arm, jaw in zip(("psm1", "psm2"), jaws, strict=True):
            a, b = self._jaw_qpos[arm]
            q = JAW_HALF_OPENING_PER_UNIT * float(jaw)
            d.qpos[a] = -q
            d.qpos[b] = q
        mujoco.mj_kinematics(self.model, d)
        mujoco.mj_camlight(self.model, d)

    def render(self, camera: str, height: int, width: int) -> np.ndarray:
        """RGB uint8 (height, width, 3) image from the named camera."""
        key = (height, width)
        renderer = self._renderers.get(key)
        if renderer is None:
            renderer = mujoco.Renderer(self.model, height=height, width=width)
            flags = renderer.scene.flags
            flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
            flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = False
            flags[mujoco.mjtRndFlag.mjRND_SKYBOX] = False
            self._renderers[key] = renderer
        renderer.update_scene(self.data, camera=camera)
        return renderer.render()

    def close(self) -> None:
        for renderer in self._renderers.values():
            renderer.close()
        self._renderers.clear()
