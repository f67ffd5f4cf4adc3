"""The film of a live run: the actor, the generated partner and the simulated robot side by
side, the actor drawn where it stood relative to the partner (``run --video``, ``demo``)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

#: Closest the drawn actor's pelvis may come to the robot's root in the video (m, scene units).
#: The robot keeps its feet planted while the generated partner may travel, so the actor,
#: placed relative to the partner's first frame, can otherwise walk into the robot.
VIDEO_MIN_GAP_M = 0.35


def actor_placement_for_robot(partner, robot_motion, actor=None, min_gap: float = VIDEO_MIN_GAP_M):
    """Where to draw the actor in the robot's scene: the rigid transform (and scale) that takes
    the generated partner's first-frame pelvis and heading onto the robot's root, so the actor
    stands relative to the robot as it stood relative to its partner. With ``actor`` (a Motion),
    the placement is then moved straight away from the robot until the actor's pelvis stays at
    least ``min_gap`` from the robot's root in every frame they share."""
    import numpy as np

    from sim.human_figure import Placement, place

    p0 = partner.positions[0]
    left = p0[1] - p0[2]  # right hip -> left hip
    partner_yaw = np.arctan2(-left[0], left[1])  # facing is the hips' left vector turned by -90°
    w, x, y, z = robot_motion.root_quat[0]
    robot_yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    scale = float(robot_motion.root_pos[0, 2] / max(p0[0, 2], 1e-3))
    yaw = robot_yaw - partner_yaw
    c, s = np.cos(yaw), np.sin(yaw)
    moved = scale * np.array([c * p0[0, 0] - s * p0[0, 1], s * p0[0, 0] + c * p0[0, 1]])
    offset = np.array([robot_motion.root_pos[0, 0] - moved[0], robot_motion.root_pos[0, 1] - moved[1], 0.0])
    placement = Placement(scale=scale, offset=tuple(offset), yaw_deg=float(np.degrees(yaw)))
    if actor is None:
        return placement
    n = min(actor.n_frames, len(robot_motion.root_pos))
    root = np.asarray(robot_motion.root_pos[:n, :2])
    pelvis = place(actor.positions[:n], scale, placement)[:, 0, :2]
    away = pelvis[0] - root[0]
    if np.linalg.norm(away) < 1e-6:  # the actor starts on the robot: step back along the robot's facing
        away = np.array([np.cos(robot_yaw), np.sin(robot_yaw)])
    away /= np.linalg.norm(away)
    for _ in range(8):  # each step closes the worst frame's shortfall (exact for motion along `away`)
        shortfall = min_gap - float(np.min(np.linalg.norm(pelvis - root, axis=1)))
        if shortfall <= 1e-4:
            break
        offset[:2] += shortfall * away
        pelvis = pelvis + shortfall * away
    return Placement(scale=scale, offset=tuple(float(v) for v in offset), yaw_deg=placement.yaw_deg)


def side_view(robot_motion, actor, placement, camera):
    """The render camera turned so that it looks across the robot-actor line (120° from the
    direction robot -> actor, so the robot's front stays in view) instead of along it, where
    the actor would stand between the camera and the robot, and aimed between the two."""
    import numpy as np

    from sim.human_figure import place

    pelvis = place(actor.positions, placement.scale, placement)[:, 0, :2].mean(axis=0)
    d = pelvis - np.asarray(robot_motion.root_pos[:, :2]).mean(axis=0)
    if np.linalg.norm(d) < 1e-6:
        return camera
    # aim between the two (the camera tracks each panel's figure; this offset is relative to it)
    aim = (0.4 * float(d[0]), 0.4 * float(d[1]), float(np.mean(robot_motion.root_pos[:, 2])))
    return replace(camera, azimuth=float(np.degrees(np.arctan2(d[1], d[0]))) + 120.0, lookat=aim)


def render_video(result, path: Path, on_tick=None) -> Path:
    """Actor, generated partner and robot side by side, from the run's recorded motions
    (``on_tick(t)``: as the film reaches run time t, s)."""
    from ros_free_bridge.errors import BridgeError
    from sim.human_figure import People
    from sim.render import RenderConfig, render_trajectory

    if result.robot_motion is None:
        raise BridgeError("--video needs a sim transport (sim or sim+dynamixel): only the virtual robot can be filmed")
    placement = (
        None if result.partner is None else actor_placement_for_robot(result.partner, result.robot_motion, result.actor)
    )
    config = RenderConfig(playback="kinematic", side_by_side=True)
    if placement is not None and result.actor is not None:
        config = replace(config, camera=side_view(result.robot_motion, result.actor, placement, config.camera))
    out, _ = render_trajectory(
        result.robot_motion,
        path,
        config,
        robot=result.files.ref,
        people=People(result.actor, placement, result.partner),
        on_tick=on_tick,
    )
    return out
