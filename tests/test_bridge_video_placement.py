"""Where the run video draws the actor next to the robot (ros_free_bridge.commands.run)."""

import numpy as np
import pytest

from dualflow.motion import Motion
from dualflow.motion.skeleton import REST_POSE
from retarget.trajectory import RobotTrajectory
from ros_free_bridge.run_video import actor_placement_for_robot
from sim.human_figure import place

FPS = 30.0


def _person(pelvis_xy, yaw):
    """A rest-pose person (faces +X) turned by ``yaw`` and moved so its pelvis follows ``pelvis_xy`` (T, 2)."""
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    body = (REST_POSE - REST_POSE[0] * [1, 1, 0]) @ rot.T
    pos = np.repeat(body[None], len(pelvis_xy), axis=0)
    pos[:, :, :2] += pelvis_xy[:, None, :]
    return Motion(pos, FPS)


def _robot(n):
    return RobotTrajectory(
        joint_names=("j",),
        joint_pos=np.zeros((n, 1)),
        root_pos=np.tile([0.0, 0.0, 0.27], (n, 1)),
        root_quat=np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)),
        fps=FPS,
        robot="op3",
    )


def test_the_actor_is_drawn_where_it_stood_relative_to_the_partner():
    n = 40
    partner = _person(np.zeros((n, 2)), 0.0)  # faces +X at the origin
    actor = _person(np.tile([2.0, 0.0], (n, 1)), np.pi)  # 2 m in front, facing it, standing still
    pl = actor_placement_for_robot(partner, _robot(n), actor)
    pelvis = place(actor.positions, pl.scale, pl)[:, 0]
    # in front of the robot (+X), at the partner's distance scaled to the robot (beyond the
    # minimum gap, so not moved), facing it
    assert 2.0 * pl.scale > 0.35
    np.testing.assert_allclose(pelvis[:, :2], np.tile([2.0 * pl.scale, 0.0], (n, 1)), atol=1e-9)
    assert pl.yaw_deg == 0.0


def test_an_actor_walking_into_the_robot_is_kept_at_the_minimum_gap():
    n = 60
    partner = _person(np.zeros((n, 2)), 0.0)
    walk = np.stack([np.linspace(1.2, 0.0, n), np.zeros(n)], axis=1)  # the actor walks onto the partner's spot
    actor = _person(walk, np.pi)
    robot = _robot(n)
    plain = actor_placement_for_robot(partner, robot)
    kept = actor_placement_for_robot(partner, robot, actor, min_gap=0.35)

    def gap(pl):
        return np.linalg.norm(place(actor.positions, pl.scale, pl)[:, 0, :2] - robot.root_pos[:, :2], axis=1)

    assert gap(plain).min() < 0.05  # without the actor, the drawn actor ends inside the robot
    assert gap(kept).min() >= 0.35 - 1e-6
    assert gap(kept).min() <= 0.35 + 1e-3  # moved just enough, straight away from the robot
    assert kept.yaw_deg == plain.yaw_deg and kept.scale == plain.scale


def test_the_video_camera_looks_across_the_robot_actor_line_not_along_it():
    from ros_free_bridge.run_video import side_view
    from sim.render import CameraConfig

    n = 30
    partner = _person(np.zeros((n, 2)), 0.0)
    for ax, ay in ((2.0, 0.0), (0.0, 2.0), (-1.5, -1.5)):
        actor = _person(np.tile([ax, ay], (n, 1)), np.arctan2(-ay, -ax))
        robot = _robot(n)
        pl = actor_placement_for_robot(partner, robot, actor)
        cam = side_view(robot, actor, pl, CameraConfig())
        d = place(actor.positions, pl.scale, pl)[:, 0, :2].mean(axis=0) - robot.root_pos[:, :2].mean(axis=0)
        view = np.array([np.cos(np.radians(cam.azimuth)), np.sin(np.radians(cam.azimuth))])  # MuJoCo: viewing direction
        # 120° from robot -> actor: mostly across the line, never along it toward the robot
        assert np.dot(view, d / np.linalg.norm(d)) == pytest.approx(np.cos(np.radians(120.0)), abs=1e-9)
        np.testing.assert_allclose(cam.lookat[:2], 0.4 * d, atol=1e-9)  # aimed between the two
