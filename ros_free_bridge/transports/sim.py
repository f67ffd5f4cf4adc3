"""The MuJoCo virtual robot as a bridge transport.

Wraps :class:`sim.virtual_robot.VirtualRobot` (which mirrors the transport methods but
returns its own reading type, since ``sim`` does not import the bridge; its IMU sample becomes
``JointState.imu``) and records what
the simulated robot actually did at every write: its root pose and measured joint angles.
:meth:`SimTransport.recorded_trajectory` returns that as a
:class:`retarget.RobotTrajectory`, for rendering a video of the run or checking it.
"""

from __future__ import annotations

import numpy as np

from retarget import RobotTrajectory
from ros_free_bridge.transports.base import ImuReading, JointState


class SimTransport:
    """``robot``: a bundled robot name. ``clock``: "realtime" (the loop's clock drives physics)
    or "lockstep" (each write advances physics by one control period)."""

    def __init__(self, robot: str = "op3", control_hz: float = 100.0, clock: str = "realtime", record: bool = True, **config):
        from sim.virtual_robot import VirtualRobot, VirtualRobotConfig

        self.robot = VirtualRobot(VirtualRobotConfig(robot=robot, control_hz=control_hz, clock=clock, **config))
        self.joint_names = self.robot.joint_names
        self.control_hz = float(control_hz)
        self.record = record
        self._root_pos: list[np.ndarray] = []
        self._root_quat: list[np.ndarray] = []
        self._q: list[np.ndarray] = []

    def open(self) -> None:
        self.robot.open()

    def read_state(self) -> JointState:
        r = self.robot.read_state()
        imu = None if r.imu is None else ImuReading(r.imu.gyro, r.imu.accel, r.imu.quat, r.imu.stamp)
        return JointState(r.position, r.velocity, r.effort, r.temperature, r.voltage, r.torque_enabled, r.stamp,
                          r.errors, imu)

    def write_goal(self, positions) -> None:
        self.robot.write_goal(positions)
        if self.record:
            scene = self.robot.scene
            d, idx = scene.data, scene.robot
            self._root_pos.append(d.xpos[idx.root_body].copy())
            self._root_quat.append(d.xquat[idx.root_body].copy())
            self._q.append(d.qpos[idx.qpos_adr].copy())

    def set_torque(self, enabled: bool) -> None:
        self.robot.set_torque(enabled)

    def safe_stop(self, policy: str = "hold") -> None:
        self.robot.safe_stop(policy)

    def close(self) -> None:
        self.robot.close()

    def recorded_trajectory(self) -> RobotTrajectory | None:
        """The simulated robot's measured motion, one frame per command written (None if none)."""
        if not self._q:
            return None
        return RobotTrajectory(self.joint_names, np.asarray(self._q), np.asarray(self._root_pos),
                               np.asarray(self._root_quat), self.control_hz, self.robot.config.robot,
                               {"source": "virtual robot, measured"})
