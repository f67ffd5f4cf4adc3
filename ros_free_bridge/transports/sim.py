"""The MuJoCo virtual robot as a bridge transport.

Wraps :class:`sim.virtual_robot.VirtualRobot` (which mirrors the transport methods and
returns the same :class:`firmware_cfg.readings.JointState`, IMU sample included) and records
what the simulated robot actually did at every write: its root pose and measured joint angles.
:meth:`SimTransport.recorded_trajectory` returns that as a
:class:`retarget.RobotTrajectory`, for rendering a video of the run or checking it.
"""

from __future__ import annotations

import numpy as np

from retarget import RobotTrajectory
from ros_free_bridge.transports.base import JointState


class SimTransport:
    """``robot``: a bundled robot name. ``clock``: "realtime" (the loop's clock drives physics)
    or "lockstep" (each write advances physics by one control period)."""

    def __init__(
        self, robot: str = "op3", control_hz: float = 100.0, clock: str = "realtime", record: bool = True, **config
    ):
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
        return self.robot.read_state()

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

    def position_limits(self) -> None:
        """None: no limits beyond the caller's (see transports.base)."""
        return None

    def pipeline(self, enabled: bool = True) -> bool:
        """False: no split-phase bus cycle here (see transports.base)."""
        return False

    def recorded_trajectory(self) -> RobotTrajectory | None:
        """The simulated robot's measured motion, one frame per command written (None if none)."""
        if not self._q:
            return None
        return RobotTrajectory(
            self.joint_names,
            np.asarray(self._q),
            np.asarray(self._root_pos),
            np.asarray(self._root_quat),
            self.control_hz,
            self.robot.config.robot,
            {"source": "virtual robot, measured"},
        )
