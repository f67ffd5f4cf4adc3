"""The physics check plays a trajectory as the bridge would send it: through the bridge's safety
filter (joint, speed and acceleration limits of the robot's hardware config), and judges the
joint and speed limits on what the trajectory asked."""

from __future__ import annotations

import json

import numpy as np
import pytest

from retarget.trajectory import RobotTrajectory
from ros_free_bridge.cli import main
from ros_free_bridge.robots import bridge_check_config, loop_limits, resolve_robot
from sim.check import CheckConfig, check_trajectory


@pytest.fixture(scope="module")
def op3_stand():
    from retarget.robot import load_robot

    files = resolve_robot("op3")
    robot = load_robot(files.mjcf, files.profile)
    n = robot.n_root
    return robot, np.asarray(robot.x_stand)[n:].copy(), np.asarray(robot.x_stand)[:3]


def _arm_jump(op3_stand, fps=100.0) -> RobotTrajectory:
    """Standing, then the left shoulder pitch sets off at once at 3 rad/s (below the servo's speed)
    for 0.15 s and turns back at once: 600 rad/s² at the turn at 100 fps, past the bridge's
    limit (what the servo can give the arm, about 380 rad/s²)."""
    robot, pose, root = op3_stand
    traj = RobotTrajectory.standing(robot.joint_names, pose, 100, fps, root, "op3")
    q = np.array(traj.joint_pos)
    t = (np.arange(100) - 50) / fps
    ramp = (np.clip(t, 0.0, 0.15) - np.clip(t - 0.15, 0.0, 0.15)) * 3.0
    q[:, list(robot.joint_names).index("l_sho_pitch")] += ramp
    return RobotTrajectory(traj.joint_names, q, traj.root_pos, traj.root_quat, fps, "op3")


@pytest.mark.parametrize("mode", ["fixed", "free"])  # open loop, and through the stabilizer
def test_the_check_sends_what_the_bridge_filter_lets_through(op3_stand, mode):
    traj = _arm_jump(op3_stand)
    j = list(traj.joint_names).index("l_sho_pitch")
    raw = check_trajectory(traj, CheckConfig(mode=mode), robot="op3")
    filtered = check_trajectory(traj, bridge_check_config("op3", mode=mode), robot="op3")
    limits = loop_limits(resolve_robot("op3"))
    k = list(limits.names).index("l_sho_pitch")
    dt = 0.01

    def peak_acc(result):
        q = result.series["q_cmd"][:, j]
        return np.abs(np.diff(q, 2)).max() / dt**2

    # unfiltered the arm is commanded across in one tick; the bridge's filter ramps it
    assert peak_acc(raw) > 1.5 * limits.max_acceleration[k]
    assert peak_acc(filtered) <= limits.max_acceleration[k] * 1.001
    speed = np.abs(np.diff(filtered.series["q_cmd"][:, j])).max() / dt
    assert speed <= limits.max_velocity[k] * 1.001
    # the filtered arm still gets there
    assert filtered.series["q_cmd"][-1, j] == pytest.approx(traj.joint_pos[-1, j], abs=1e-6)


def test_a_trajectory_asking_beyond_the_limits_fails_though_the_filter_clamps_it(op3_stand, tmp_path, capsys):
    robot, pose, root = op3_stand
    traj = RobotTrajectory.standing(robot.joint_names, pose, 60, 30.0, root, "op3")
    q = np.array(traj.joint_pos)
    j = list(robot.joint_names).index("l_el")
    q[30:, j] = robot.x_upper[robot.n_root + j] + 0.5
    bad = RobotTrajectory(traj.joint_names, q, traj.root_pos, traj.root_quat, 30.0, "op3")
    result = check_trajectory(bad, bridge_check_config("op3", mode="fixed"), robot="op3")
    assert not result.passed and "joint_limit" in {f.reason for f in result.failures}
    # the commands sent stayed inside the limits: the filter clamped them
    assert result.series["q_cmd"][:, j].max() <= robot.x_upper[robot.n_root + j] + 1e-9


def test_cli_check_filters_by_default_and_says_so(op3_stand, tmp_path, capsys):
    path = _arm_jump(op3_stand).save_npz(tmp_path / "jump.npz")
    for extra, filtered in (([], True), (["--no-safety-filter"], False)):
        code = main(["check", str(path), "--mode", "fixed", "--no-plots", "-o", str(tmp_path / "c"), *extra])
        assert code == 0, capsys.readouterr()
        report = json.loads((tmp_path / "c" / "jump.json").read_text())
        assert report["config"]["command_filter"] is filtered
    assert main(["check", str(path), "--robot", str(tmp_path / "nowhere"), "-o", str(tmp_path / "c")]) == 2
    assert "nowhere" in capsys.readouterr().err
