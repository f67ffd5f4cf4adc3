"""The virtual robot behaves like a servo bus: life cycle, holding, faults, heat."""

from __future__ import annotations

import numpy as np
import pytest

from firmware_cfg.readings import JointState
from sim import SimError
from sim.virtual_robot import VirtualRobot, VirtualRobotConfig


@pytest.fixture
def robot():
    vr = VirtualRobot(VirtualRobotConfig(clock="lockstep"))
    vr.open()
    yield vr
    vr.close()


def _start(vr: VirtualRobot) -> np.ndarray:
    present = vr.read_state().position
    vr.write_goal(present)
    vr.set_torque(True)
    return present


def test_life_cycle_and_reading_fields(robot):
    s = robot.read_state()
    assert isinstance(s, JointState)
    n = len(robot.joint_names)
    assert n == 20 and robot.joint_names[0] == "r_sho_pitch"
    for arr in (s.position, s.velocity, s.effort, s.temperature, s.voltage, s.torque_enabled):
        assert arr.shape == (n,)
    assert not s.torque_enabled.any()
    _start(robot)
    assert robot.read_state().torque_enabled.all()
    assert np.allclose(robot.read_state().voltage, 11.1)


def test_holds_standing_and_follows_goals(robot):
    present = _start(robot)
    for _ in range(200):  # 2 s at 100 Hz
        robot.write_goal(present)
    s = robot.read_state()
    assert robot.sim_time == pytest.approx(2.0)
    assert np.abs(s.position - present).max() < 0.08
    assert robot.scene.data.xpos[robot.scene.robot.root_body, 2] > 0.25  # still standing
    j = robot.joint_names.index("r_sho_pitch")
    goal = present.copy()
    goal[j] = -0.8
    for _ in range(100):
        robot.write_goal(goal)
    assert robot.read_state().position[j] == pytest.approx(-0.8, abs=0.05)


def test_stuck_joint_ignores_goals_and_clears(robot):
    present = _start(robot)
    j = robot.joint_names.index("l_sho_pitch")
    robot.inject_fault("l_sho_pitch", "stuck")
    goal = present.copy()
    goal[j] = -1.0
    for _ in range(100):
        robot.write_goal(goal)
    assert abs(robot.read_state().position[j] - present[j]) < 0.01
    robot.clear_faults()
    for _ in range(100):
        robot.write_goal(goal)
    assert robot.read_state().position[j] == pytest.approx(-1.0, abs=0.05)


def test_lowered_torque_limit_caps_effort(robot):
    present = _start(robot)
    j = robot.joint_names.index("r_sho_pitch")
    robot.inject_fault("r_sho_pitch", "torque_limit", 0.05)
    goal = present.copy()
    goal[j] = -1.2
    for _ in range(100):
        robot.write_goal(goal)
    s = robot.read_state()
    assert abs(s.effort[j]) <= 0.05 + 1e-9
    assert s.position[j] > -0.6  # too weak to lift the arm there
    with pytest.raises(SimError, match="torque_limit fault needs value"):
        robot.inject_fault("r_sho_pitch", "torque_limit", -1.0)
    with pytest.raises(SimError, match="unknown fault"):
        robot.inject_fault("r_sho_pitch", "melted")
    with pytest.raises(SimError, match="unknown joint"):
        robot.inject_fault("tail", "stuck")


def test_a_stalled_servo_heats_up(robot):
    present = _start(robot)
    j = robot.joint_names.index("l_el")
    robot.inject_fault("l_el", "stuck")
    goal = present.copy()
    goal[j] = present[j] + 1.0  # the servo pushes at stall torque against the seized joint
    for _ in range(500):
        robot.write_goal(goal)
    s = robot.read_state()
    assert abs(s.effort[j]) == pytest.approx(3.8, abs=0.01)
    assert s.temperature[j] > 25.0 + 2.0
    others = np.delete(s.temperature, j)
    assert others.max() < s.temperature[j] - 1.5


def test_overheating_switches_the_servo_off():
    cfg = VirtualRobotConfig(clock="lockstep", thermal_time_constant_s=2.0)
    with VirtualRobot(cfg) as vr:
        present = _start(vr)
        j = vr.joint_names.index("l_el")
        vr.inject_fault("l_el", "stuck")
        goal = present.copy()
        goal[j] += 1.0
        for _ in range(600):
            vr.write_goal(goal)
        s = vr.read_state()
        assert s.errors.get("l_el") == "overheating"
        assert not s.torque_enabled[j] and s.torque_enabled[j - 1]
        vr.set_torque(True)
        assert not vr.read_state().torque_enabled[j]  # stays off until reboot
        vr.reboot("l_el")
        vr.set_torque(True)
        assert vr.read_state().torque_enabled[j]


def test_safe_stop_policies_and_close_twice(robot):
    _start(robot)
    robot.safe_stop("limp")
    assert not robot.read_state().torque_enabled.any()
    robot.safe_stop("hold")
    s = robot.read_state()
    assert s.torque_enabled.all()
    with pytest.raises(SimError, match="stop policy"):
        robot.safe_stop("freeze")
    robot.close()
    robot.close()
    with pytest.raises(SimError, match="open"):
        robot.read_state()


def test_bad_goals_are_sim_errors(robot):
    _start(robot)
    with pytest.raises(SimError, match="needs 20 positions"):
        robot.write_goal(np.zeros(19))
    bad = np.zeros(20)
    bad[3] = np.nan
    with pytest.raises(SimError, match="NaN"):
        robot.write_goal(bad)


def test_realtime_clock_follows_the_wall_clock():
    now = [100.0]
    vr = VirtualRobot(VirtualRobotConfig(clock="realtime"), clock=lambda: now[0])
    vr.open()
    present = _start(vr)
    now[0] += 0.05
    vr.write_goal(present)
    assert vr.sim_time == pytest.approx(0.05, abs=0.0021)
    now[0] += 5.0  # the caller stalled: physics skips ahead by at most max_catchup_s
    vr.read_state()
    assert vr.sim_time == pytest.approx(5.05, abs=0.0021)
    vr.close()


def test_fixed_base_robot_runs_without_standing():
    with VirtualRobot(VirtualRobotConfig(robot="ub14", clock="lockstep")) as vr:
        assert len(vr.joint_names) == 14
        present = _start(vr)
        for _ in range(100):
            vr.write_goal(present)
        assert np.abs(vr.read_state().position - present).max() < 0.05
