"""What each joint's servo can give its links (retarget.actuation), and that the retargeter and
the bridge's safety filter use the same acceleration limits."""

import mujoco
import numpy as np
import pytest

from retarget.actuation import DEFAULT_ACCELERATION, acceleration_limits, stall_accelerations

# an upper arm (hinge about z at the shoulder) carrying a forearm point mass 0.1 m out, and a
# wrist hinge whose actuator the model leaves unlimited
ARM = """
<mujoco>
  <worldbody>
    <body name="upper">
      <joint name="shoulder" type="hinge" axis="0 0 1" armature="0.005"/>
      <inertial pos="0 0 0" mass="0.2" diaginertia="0.001 0.002 0.003"/>
      <body name="fore" pos="0.1 0 0">
        <joint name="wrist" type="hinge" axis="0 1 0"/>
        <inertial pos="0 0 0" mass="1.0" diaginertia="1e-4 1e-4 1e-4"/>
      </body>
    </body>
  </worldbody>
  <actuator>
    <position joint="shoulder" kp="10" forcelimited="true" forcerange="-3.4 3.4"/>
    <position joint="wrist" kp="10"/>
  </actuator>
</mujoco>
"""


def test_stall_acceleration_is_torque_over_the_links_inertia_about_the_axis():
    model = mujoco.MjModel.from_xml_string(ARM)
    stall = stall_accelerations(model)
    # about the shoulder's z: its own 0.003 + armature 0.005 + the forearm's 1e-4 + 1.0 x 0.1²
    inertia = 0.003 + 0.005 + 1e-4 + 1.0 * 0.1**2
    assert stall == {"shoulder": pytest.approx(3.4 / inertia, rel=1e-9)}
    # a joint whose torque the model does not limit gets the default
    limits = acceleration_limits(model, ["wrist", "shoulder"])
    assert limits[0] == DEFAULT_ACCELERATION and limits[1] == pytest.approx(3.4 / inertia)
    # a geared motor: MuJoCo multiplies the clamped force by the gear at the joint
    geared = mujoco.MjModel.from_xml_string(ARM.replace('forcerange="-3.4 3.4"', 'gear="10" forcerange="-0.34 0.34"'))
    assert stall_accelerations(geared)["shoulder"] == pytest.approx(3.4 / inertia, rel=1e-9)
    # a servo too weak for the default still gets it: it follows late, as it did under it
    weak = mujoco.MjModel.from_xml_string(ARM.replace("-3.4 3.4", "-0.5 0.5"))
    assert stall_accelerations(weak)["shoulder"] == pytest.approx(0.5 / inertia)
    assert 0.5 / inertia < DEFAULT_ACCELERATION
    assert acceleration_limits(weak, ["shoulder"])[0] == DEFAULT_ACCELERATION


def test_the_bridge_filters_with_the_limits_the_retargeter_plans_with():
    """The op3 (hardware config, no profile acceleration set) and a model-only robot: the
    loop's acceleration limits are the retargeter's, joint by joint, and the bridge plans no
    faster than its loop sends (the profile's 4.0 rad/s, the loop's 0.8 x the XM430's no-load
    speed). Where they differ, the filter sends a lagging copy of a plan the servos could
    follow (the feet of a streamed fast-stepping duet follower collided in physics at the old
    flat 80 rad/s²)."""
    from retarget.robot import load_robot
    from ros_free_bridge.robots import loop_limits, model_limits, planning_robot, resolve_robot

    files = resolve_robot("op3")
    assert files.hardware is not None
    robot = load_robot(files.mjcf, files.profile)
    loop = loop_limits(files).in_order(robot.joint_names)
    assert np.allclose(loop.max_acceleration, robot.acceleration_limits)
    assert np.allclose(model_limits(robot).max_acceleration, robot.acceleration_limits)
    assert np.any(robot.velocity_limits > loop.max_velocity)  # the profile's own speed is above the loop's
    planned = planning_robot("op3")
    assert np.allclose(planned.velocity_limits, np.minimum(robot.velocity_limits, loop.max_velocity))
    assert np.allclose(planned.acceleration_limits, loop.max_acceleration)
    # the op3's hips move the whole leg: their servos speed it up least
    hips = [robot.joint_names.index(n) for n in ("l_hip_pitch", "l_hip_roll")]
    assert np.all(robot.acceleration_limits[hips] < np.median(robot.acceleration_limits))


def test_a_servos_profile_acceleration_bounds_the_plan(tmp_path):
    """A robot folder whose hardware config sets a profile acceleration of 30 rad/s²: the
    bridge's retargeter plans within it, frame to frame."""
    import shutil

    import yaml

    from dualflow.synthetic import make_leader
    from retarget.streaming import StreamingConfig, StreamingRetargeter
    from ros_free_bridge.robots import loop_limits, planning_robot, resolve_robot

    folder = tmp_path / "slow_op3"
    shutil.copytree(resolve_robot("op3").mjcf.parent, folder)
    hw = yaml.safe_load((folder / "hardware.yaml").read_text())
    hw["servo_defaults"]["profile_acceleration"] = 30.0
    (folder / "hardware.yaml").write_text(yaml.safe_dump(hw))
    assert np.all(loop_limits(resolve_robot(folder)).max_acceleration == 30.0)
    robot = planning_robot(folder)
    assert np.all(robot.acceleration_limits == 30.0)
    traj = StreamingRetargeter(robot, 30.0, StreamingConfig(balance=True, steps=True)).run(make_leader(3.0, 30.0, 0))
    q = traj.joint_pos
    acc = np.abs(np.diff(q, n=2, axis=0)) * 30.0**2
    # except the last step onto a range's end, which may stop short by up to a (as the filter's)
    n = robot.n_root
    at_end = (np.abs(q[2:] - robot.x_lower[n:]) < 1e-9) | (np.abs(q[2:] - robot.x_upper[n:]) < 1e-9)
    assert acc[~at_end].max() <= 30.0 * (1 + 1e-9) + 1e-6
    assert acc[at_end].max(initial=0.0) <= 2 * 30.0


def test_a_fast_stepping_follower_streamed_stands_and_keeps_its_feet_apart():
    """In real MuJoCo, through the bridge's safety filter: a generated duet follower stepping
    about 3.5 times a second (hand_hold, seed 1), streamed with steps. With the filter below
    what the plan asked of the hips (80 rad/s² against up to 240), the swing leg lagged its
    plan by 0.26 rad of hip roll and the feet met 2.1 mm deep at 1.85 s."""
    from dualflow.synthetic import make_duet
    from retarget.robot import load_robot
    from retarget.streaming import StreamingConfig, StreamingRetargeter
    from ros_free_bridge.robots import bridge_check_config
    from sim.check import check_trajectory

    robot = load_robot("op3")
    follower = make_duet("hand_hold", seconds=10.0, fps=30.0, seed=1).reactor
    traj = StreamingRetargeter(robot, 30.0, StreamingConfig(balance=True, steps=True)).run(follower)
    q = traj.joint_pos
    assert np.all(np.abs(np.diff(q, n=2, axis=0)) * 30.0**2 <= robot.acceleration_limits * (1 + 1e-9) + 1e-6)
    res = check_trajectory(traj, bridge_check_config("op3", mode="free"), robot="op3")
    assert res.passed, res.failures
    assert res.metrics["self_collision_ticks"] == 0 and res.metrics["max_tilt_deg"] < 30


def test_a_hardware_config_the_loop_cannot_drive_leaves_the_plan_to_the_model(tmp_path):
    """Retargeting needs no loop: a robot folder whose hardware config the loop cannot use yet
    (here, a servo on a Dynamixel bus with no servo model, so no speed limit either) plans
    within its model's limits, as before the bridge narrowed them; `run` names the problem."""
    import shutil

    import yaml

    from firmware_cfg.errors import ConfigError
    from retarget.robot import load_robot
    from ros_free_bridge.robots import planning_robot, resolve_robot

    folder = tmp_path / "unfinished_op3"
    shutil.copytree(resolve_robot("op3").mjcf.parent, folder)
    hw = yaml.safe_load((folder / "hardware.yaml").read_text())
    hw["buses"][0]["servos"][0]["model"] = None
    (folder / "hardware.yaml").write_text(yaml.safe_dump(hw))
    with pytest.raises(ConfigError, match="model: required on a Dynamixel bus"):
        resolve_robot(folder).hardware_config()
    robot, model = planning_robot(folder), load_robot(folder)
    assert np.array_equal(robot.velocity_limits, model.velocity_limits)
    assert np.array_equal(robot.acceleration_limits, model.acceleration_limits)
