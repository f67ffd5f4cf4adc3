"""MuJoCo simulation: bundled robots, the scene, physical checking, rendering and
the virtual robot. Importing ``sim`` does not import mujoco or torch; submodules do."""

from sim.errors import SimError

__all__ = ["SimError"]
