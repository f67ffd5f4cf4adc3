"""Drive several transports with the same commands (e.g. the virtual robot and a bus).

The first transport is the primary: its readings are what the control loop sees. Every
other one receives the same goals, torque switches and stops. Stopping and closing reach
every transport even if one of them fails; the first failure is raised afterwards.
"""

from __future__ import annotations

import numpy as np

from ros_free_bridge.errors import BridgeError
from ros_free_bridge.transports.base import JointState


class TeeTransport:
    """``read_every``: read the other transports on every Nth ``read_state`` only (default 10,
    i.e. 10 Hz at a 100 Hz loop): they receive every goal, but their readings only feed the
    health checks, and each read of a bus costs a round trip the loop waits for."""

    def __init__(self, primary, *others, read_every: int = 10):
        self.transports = (primary, *others)
        for t in others:
            if tuple(t.joint_names) != tuple(primary.joint_names):
                raise BridgeError(
                    f"tee transport: {type(t).__name__} has joints {t.joint_names}, the primary "
                    f"{primary.joint_names}; both must use the robot's joint order"
                )
        self.joint_names = tuple(primary.joint_names)
        self.read_every = max(1, int(read_every))
        self._reads = 0

    def open(self) -> None:
        for t in self.transports:
            t.open()

    def read_state(self) -> JointState:
        """The primary's reading, with every transport's servo errors and the hottest
        temperature per joint merged in, so health checks see all of them."""
        state = self.transports[0].read_state()
        self._reads += 1
        if (self._reads - 1) % self.read_every:
            return state
        for t in self.transports[1:]:
            other = t.read_state()
            state.errors.update({j: f"{e} ({type(t).__name__})" for j, e in other.errors.items()})
            state.temperature = np.fmax(state.temperature, other.temperature)
        return state

    def write_goal(self, positions) -> None:
        for t in self.transports:
            t.write_goal(positions)

    def set_torque(self, enabled: bool) -> None:
        for t in self.transports:
            t.set_torque(enabled)

    def position_limits(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The tightest limits any transport enforces (None if none reports any)."""
        found = [lim for lim in (t.position_limits() for t in self.transports) if lim is not None]
        if not found:
            return None
        return (np.max([lo for lo, _ in found], axis=0), np.min([hi for _, hi in found], axis=0))

    def pipeline(self, enabled: bool = True) -> bool:
        """False: each tick reads every transport in turn (a split phase would pair one
        transport's reply with another's tick)."""
        return False

    def safe_stop(self, policy: str = "hold") -> None:
        self._all("safe_stop", policy)

    def close(self) -> None:
        self._all("close")

    def _all(self, method: str, *args) -> None:
        first = None
        for t in self.transports:
            try:
                getattr(t, method)(*args)
            except Exception as exc:  # noqa: BLE001 - reach every transport, then report
                first = first or exc
        if first is not None:
            raise first
