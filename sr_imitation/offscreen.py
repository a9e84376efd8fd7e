"""The one place that sets up offscreen rendering.

MuJoCo picks its OpenGL backend when ``mujoco`` is first imported, from ``MUJOCO_GL``; on these machines (no
display, no GPU) that must be ``egl`` (Mesa). :func:`setup_offscreen_rendering` sets ``MUJOCO_GL`` and
``PYOPENGL_PLATFORM`` to ``egl`` unless the user chose otherwise; every entry point and every module that renders
calls it before importing MuJoCo.
"""

from __future__ import annotations

import os


def setup_offscreen_rendering() -> None:
    """Default ``MUJOCO_GL`` / ``PYOPENGL_PLATFORM`` to ``egl`` (a value the user set is kept)."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"] if os.environ["MUJOCO_GL"] in ("egl", "osmesa")
                          else "egl")
