"""Render a robot trajectory (and the people) to an mp4 with MuJoCo's offscreen renderer.

Headless machines: set ``MUJOCO_GL=egl`` (or ``osmesa``) before mujoco is imported;
:func:`ensure_headless_gl` does it when no display is present. Frames are encoded
with imageio-ffmpeg (libx264, yuv420p); the video is written under a temporary
name and renamed, so it is complete or absent.

Playback: ``physics`` (default) plays the trajectory through the servos exactly as
``check`` does (:class:`sim.check.Checker`) and films what the robot really does;
``kinematic`` sets the joint angles and root pose straight from the trajectory.

Side by side: three panels left to right: the human actor, the generated reactor
as a stick figure, and the robot with the actor (its partner).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sim.errors import SimError


def ensure_headless_gl() -> None:
    """Choose EGL when no display is present and MUJOCO_GL is unset. MuJoCo reads
    MUJOCO_GL when it is first imported, so this only helps before that; importing
    :mod:`sim` already does it."""
    if "MUJOCO_GL" not in os.environ and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        os.environ["MUJOCO_GL"] = "egl"


@dataclass(frozen=True)
class CameraConfig:
    """A free camera. ``distance`` m (None: 2.4 x robot height), ``azimuth`` and
    ``elevation`` degrees (MuJoCo's convention: azimuth 180 looks along -X, i.e. at
    the front of a robot facing +X), ``lookat`` (3,) m (None: the robot's root,
    at half its height); ``track`` follows the robot's root in x and y."""

    distance: float | None = None
    azimuth: float = 160.0
    elevation: float = -15.0
    lookat: tuple[float, float, float] | None = None
    track: bool = True


@dataclass(frozen=True)
class RenderConfig:
    """Video size (pixels per panel), frame rate, camera, playback and quality.
    ``quality`` "fast" turns off shadows, reflections and multisampling (CPU rendering)."""

    width: int = 640
    height: int = 480
    fps: float = 30.0
    camera: CameraConfig = field(default_factory=CameraConfig)
    side_by_side: bool = False
    playback: str = "physics"  # "physics" | "kinematic"
    quality: str = "fast"  # "fast" | "full"

    def validate(self) -> None:
        if not (16 <= int(self.width) <= 1920 and 16 <= int(self.height) <= 1080):
            raise SimError(
                f"render: width x height must be within 16..1920 x 16..1080, got {self.width} x {self.height}"
            )
        if not (np.isfinite(self.fps) and 1 <= self.fps <= 120):
            raise SimError(f"render: fps must be in 1..120, got {self.fps!r}")
        if self.playback not in ("physics", "kinematic"):
            raise SimError(f"render: playback must be 'physics' or 'kinematic', got {self.playback!r}")
        if self.quality not in ("fast", "full"):
            raise SimError(f"render: quality must be 'fast' or 'full', got {self.quality!r}")


class Filmer:
    """Grabs frames of a scene into a list of (H, W', 3) uint8 images."""

    def __init__(self, scene, config: RenderConfig):
        import mujoco

        self.mujoco = mujoco
        self.scene, self.config = scene, config
        m = scene.model
        if config.quality == "fast":
            m.vis.quality.offsamples = 0
        try:
            self.renderer = mujoco.Renderer(m, int(config.height), int(config.width))
        except Exception as exc:  # GL context creation fails with several exception types
            raise SimError(
                f"render: cannot create an offscreen OpenGL context ({exc}); on a headless machine "
                "set MUJOCO_GL=egl (or osmesa) and check that libEGL/libOSMesa is installed"
            ) from None
        self.frames: list[np.ndarray] = []
        self._next_t = 0.0
        from sim.scene import ACTOR_GROUP, REACTOR_GROUP, ROBOT_GROUP

        def opt(groups):
            o = mujoco.MjvOption()
            o.geomgroup[:] = 0
            o.sitegroup[:] = 0
            for g in (0, *groups):
                o.geomgroup[g] = 1
            return o

        if config.side_by_side:
            self.panels = [
                (opt([ACTOR_GROUP]), "actor"),
                (opt([REACTOR_GROUP]), "reactor"),
                (opt([ROBOT_GROUP, ACTOR_GROUP]), "robot"),
            ]
        else:
            self.panels = [(opt([ROBOT_GROUP, ACTOR_GROUP]), "robot")]

    def _camera(self, target: str):
        sc, cc = self.scene, self.config.camera
        cam = self.mujoco.MjvCamera()
        cam.type = self.mujoco.mjtCamera.mjCAMERA_FREE
        cam.distance = cc.distance if cc.distance is not None else 2.4 * sc.robot_height
        cam.azimuth, cam.elevation = cc.azimuth, cc.elevation
        if cc.lookat is not None and not cc.track:
            cam.lookat[:] = cc.lookat
            return cam
        if (
            target == "robot"
            or (target == "actor" and sc.actor is None)
            or (target == "reactor" and sc.reactor is None)
        ):
            xy = sc.data.xpos[sc.robot.root_body, :2]
        else:
            fig = sc.actor if target == "actor" else sc.reactor
            xy = sc.data.mocap_pos[fig._mocap[0], :2]  # first bone: pelvis to left hip
        base = np.array(cc.lookat) if cc.lookat is not None else np.array([0.0, 0.0, 0.5 * sc.robot_height])
        cam.lookat[:] = (xy[0] + base[0], xy[1] + base[1], base[2]) if cc.track else base
        return cam

    def grab(self) -> None:
        mj, r = self.mujoco, self.renderer
        images = []
        for opt, target in self.panels:
            r.update_scene(self.scene.data, self._camera(target), opt)
            if self.config.quality == "fast":
                r.scene.flags[mj.mjtRndFlag.mjRND_SHADOW] = 0
                r.scene.flags[mj.mjtRndFlag.mjRND_REFLECTION] = 0
            images.append(r.render().copy())
        self.frames.append(np.concatenate(images, axis=1))

    def on_tick(self, t: float) -> None:
        """Grab a frame whenever the clip time passes the next video frame time."""
        while t + 1e-9 >= self._next_t:
            self.grab()
            self._next_t += 1.0 / self.config.fps

    def close(self) -> None:
        self.renderer.close()


def write_mp4(frames: list[np.ndarray], path, fps: float) -> Path:
    """Encode frames (H, W, 3) uint8 to ``path`` (libx264) atomically."""
    import imageio.v2 as imageio

    if not frames:
        raise SimError(f"render: no frames to write to {path}")
    path = Path(path)
    if path.suffix.lower() != ".mp4":
        raise SimError(f"render: output {path} must end in .mp4")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.stem + ".partial.mp4")
    try:
        with imageio.get_writer(
            tmp, fps=fps, codec="libx264", quality=7, pixelformat="yuv420p", macro_block_size=16
        ) as writer:
            for f in frames:
                writer.append_data(f)
        tmp.replace(path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def render_trajectory(
    traj,
    out_path,
    config: RenderConfig | None = None,
    check_config=None,
    robot: str | None = None,
    people=None,
    on_tick=None,
):
    """Film ``traj`` (RobotTrajectory or npz path) to ``out_path`` (.mp4), with ``people``
    (:class:`sim.human_figure.People`, None: the robot alone) beside the robot.

    Returns (path, CheckResult): the physics check of ``traj`` in the same scene, with the
    same people placed the same way (:func:`sim.check.check_trajectory` gives the same verdict):
    with physics playback the film is of that very run (from the clip's first frame; the entry
    transition from the standing pose before it is judged, not filmed), with kinematic playback
    the check runs after filming. ``on_tick(t)`` (optional) is called as the film reaches
    trajectory time ``t`` (s), e.g. for a progress bar.
    """
    ensure_headless_gl()
    from sim.check import CheckConfig, Checker, _as_trajectory, _joint_columns, scene_for

    config = config or RenderConfig()
    config.validate()
    if Path(out_path).suffix.lower() != ".mp4":
        raise SimError(f"render: output {out_path} must end in .mp4")
    check_config = check_config or CheckConfig()
    check_config.validate()
    traj = _as_trajectory(traj)
    scene = scene_for(traj, check_config, robot, people)
    filmer = Filmer(scene, config)
    result = None
    try:
        if config.playback == "physics":

            def tick(t: float) -> None:
                filmer.on_tick(t)
                if on_tick is not None:
                    on_tick(t)

            result = Checker(scene, check_config).run(traj, on_tick=tick)
        else:
            q = _joint_columns(traj, scene.robot.joint_names, scene.config.robot)
            n_frames = int(np.floor(traj.duration * config.fps + 1e-9)) + 1
            for i in range(n_frames):
                t = i / config.fps
                f = min(t * traj.fps, traj.n_frames - 1)
                k = int(round(f))
                scene.set_robot_pose(q[k], traj.root_pos[k], traj.root_quat[k])
                scene.pose_humans(t)
                scene.mujoco_forward()
                filmer.grab()
                if on_tick is not None:
                    on_tick(t)
            result = Checker(scene, check_config).run(traj)
    finally:
        filmer.close()
    return write_mp4(filmer.frames, out_path, config.fps), result
