"""Partner world positions (22, 3) m → robot joint angles (n,) rad, one frame at a time.

:class:`RetargetStage` runs :class:`retarget.streaming.StreamingRetargeter` (CasADi/IPOPT)
and returns the angles in the transport's joint order.
"""

from __future__ import annotations

import numpy as np

from ros_free_bridge.errors import BridgeError


class RetargetStage:
    """Reactor world positions → robot joint angles (n,) rad in ``joint_names`` order."""

    def __init__(self, robot, fps: float, joint_names=None):
        from retarget.streaming import StreamingConfig, StreamingRetargeter

        self.robot = robot
        # its default keypoint scaler uses REST_POSE proportions: a live stream has no clip to measure;
        # a free-standing robot keeps its feet planted and its CoM over them (fixed bases ignore it)
        self.streamer = StreamingRetargeter(robot, fps, StreamingConfig(balance=True))
        names = tuple(joint_names) if joint_names is not None else tuple(robot.joint_names)
        missing = [n for n in names if n not in robot.joint_names]
        if missing:
            raise BridgeError(
                f"retarget stage: the robot model has no joints {missing}; the hardware config and the MJCF disagree"
            )
        self.joint_names = names
        self._index = np.array([robot.joint_names.index(n) for n in names])
        self.fps = float(fps)
        self.settle_steps = 0  #: the robot's steps in the last settle (after the stream's end)

    def step(self, positions: np.ndarray, contacts: np.ndarray | None = None) -> np.ndarray:
        """One partner pose (22, 3) m (and its foot contacts (4,) bool, None: no foot down) →
        joint angles (n,) rad."""
        from retarget.targets import side_contacts

        side = (False, False)
        if contacts is not None:
            side = tuple(bool(c) for c in side_contacts(np.asarray(contacts)[None])[0])
        q, _, _ = self.streamer.split(self.streamer.step_human(positions, side))
        return q[self._index]

    def settle(self):
        """After the last frame: joint angles (n,) rad per frame, yielded as they are made,
        that step the robot back to its own stance and bring it to rest (retarget.settle; none
        for a robot without balance); ``settle_steps`` then holds the robot's steps in them.
        The bridge's stop ramp then starts from the stand pose."""
        frames = self.streamer.settle()
        for x in frames:
            self.settle_steps = frames.steps
            yield self.streamer.split(x)[0][self._index]
        self.settle_steps = frames.steps
