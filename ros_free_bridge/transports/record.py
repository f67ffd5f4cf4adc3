"""Record-only transport (dry run): every command is kept, nothing moves.

It reports the last commanded position as the measured one (an ideal servo), so the
control loop runs exactly as it would on hardware. The commands can be saved as npz.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from ros_free_bridge.errors import BridgeError
from ros_free_bridge.transports.base import JointState


class RecordTransport:
    def __init__(self, joint_names, initial=None):
        self.joint_names = tuple(joint_names)
        n = len(self.joint_names)
        self._q = np.zeros(n) if initial is None else np.asarray(initial, dtype=np.float64).copy()
        self._torque = np.zeros(n, dtype=bool)
        self.times: list[float] = []
        self.commands: list[np.ndarray] = []
        self.torque_events: list[tuple[float, bool]] = []
        self.stopped_with: str | None = None
        self.is_open = False

    def open(self) -> None:
        self.is_open = True

    def read_state(self) -> JointState:
        s = JointState.unknown(len(self.joint_names), time.monotonic())
        s.position = self._q.copy()
        s.torque_enabled = self._torque.copy()
        return s

    def write_goal(self, positions) -> None:
        if not self.is_open:
            raise BridgeError("record transport: write_goal before open()")
        q = np.asarray(positions, dtype=np.float64)
        self.times.append(time.monotonic())
        self.commands.append(q.copy())
        if self._torque.all():
            self._q = q.copy()

    def set_torque(self, enabled: bool) -> None:
        self._torque[:] = enabled
        self.torque_events.append((time.monotonic(), bool(enabled)))

    def safe_stop(self, policy: str = "hold") -> None:
        self.stopped_with = policy
        if policy == "limp":
            self.set_torque(False)

    def close(self) -> None:
        self.is_open = False

    def position_limits(self) -> None:
        """None: no limits beyond the caller's (see transports.base)."""
        return None

    def pipeline(self, enabled: bool = True) -> bool:
        """False: no split-phase bus cycle here (see transports.base)."""
        return False

    def save(self, path) -> Path:
        path = Path(path)
        tmp = path.with_name(path.name + ".partial.npz")
        np.savez(
            tmp,
            t=np.asarray(self.times),
            command=np.asarray(self.commands).reshape(-1, len(self.joint_names)),
            joint_names=np.asarray(self.joint_names),
        )
        tmp.replace(path)
        return path
