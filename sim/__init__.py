"""MuJoCo simulation: bundled robots, the scene, physical checking, rendering and
the virtual robot. Importing ``sim`` does not import mujoco or torch; submodules do.

On a machine without a display, importing ``sim`` sets ``MUJOCO_GL=egl`` (unless
MUJOCO_GL is already set) so that offscreen rendering works once mujoco loads;
MuJoCo reads that variable when it is first imported.
"""

import os as _os

from sim.errors import SimError

if "MUJOCO_GL" not in _os.environ and not (_os.environ.get("DISPLAY") or _os.environ.get("WAYLAND_DISPLAY")):
    _os.environ["MUJOCO_GL"] = "egl"

__all__ = ["SimError"]
