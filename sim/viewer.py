"""``view``: the interactive MuJoCo viewer, playing a trajectory through the servos.

Needs a display (X11 or Wayland). Without one, :func:`view` raises SimError with
what to do instead (render an mp4). The trajectory plays in real time through the
same :class:`sim.check.Checker` that ``check`` uses; the window stays open after
the clip ends until it is closed.
"""

from __future__ import annotations

import os
import time

from sim.errors import SimError


def display_available() -> bool:
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def require_display() -> None:
    if not display_available():
        raise SimError(
            "view: no display (DISPLAY and WAYLAND_DISPLAY are unset), so the interactive viewer cannot "
            "open; run it on a desktop or over `ssh -X`, or make a video instead with "
            "`dualflow-bridge render TRAJ.npz -o out.mp4`"
        )
    if os.environ.get("MUJOCO_GL", "glfw") not in ("glfw", ""):
        raise SimError(
            f"view: MUJOCO_GL={os.environ['MUJOCO_GL']} selects a headless backend; unset it "
            "(the viewer needs GLFW) and run again"
        )


def view(traj=None, robot: str | None = None, check_config=None, people=None, loop: bool = False) -> None:
    """Open the viewer on ``traj`` (RobotTrajectory or npz path), or on the robot
    standing still in its standing pose when ``traj`` is None; ``people``
    (:class:`sim.human_figure.People`) beside it."""
    require_display()
    import mujoco
    import mujoco.viewer

    from retarget.trajectory import RobotTrajectory
    from sim.check import CheckConfig, Checker, _as_trajectory, scene_for
    from sim.scene import Scene

    check_config = check_config or CheckConfig()
    check_config.validate()
    if traj is None:  # the robot standing (its "stand" keyframe or the derived pose: sim.scene)
        from sim.scene import SceneConfig

        scene = Scene(SceneConfig(robot=robot or "op3"))
        traj = RobotTrajectory.standing(
            scene.robot.joint_names,
            scene.stand_ctrl,
            2,
            1.0,
            root_pos=scene.data.xpos[scene.robot.root_body],
            robot=scene.config.robot,
        )
    traj = _as_trajectory(traj)
    scene = scene_for(traj, check_config, robot, people)
    try:
        handle = mujoco.viewer.launch_passive(scene.model, scene.data)
    except Exception as exc:  # GLFW raises several types when the display is unusable
        raise SimError(
            f"view: cannot open a window on this display ({exc}); make a video with `render` instead"
        ) from None
    start = time.monotonic()

    def on_tick(t: float) -> None:
        if not handle.is_running():
            raise _Closed
        handle.sync()
        delay = start + t - time.monotonic()
        if delay > 0:
            time.sleep(delay)

    try:
        while True:
            try:
                Checker(scene, check_config).run(traj, on_tick=on_tick)
            except _Closed:
                return
            if not loop:
                break
            scene.reset()
            start = time.monotonic()
        while handle.is_running():
            handle.sync()
            time.sleep(0.02)
    finally:
        handle.close()


class _Closed(Exception):
    """The user closed the viewer window."""
