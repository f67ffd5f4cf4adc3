"""Serial-link transport: a microcontroller servo board over pyserial, speaking DFSL v1
(``firmware_cfg/serial_link.md``).

One bus of the robot's hardware config with ``protocol: serial-link``; each servo entry's
``id`` is the board channel. Joint ↔ wire: ``servo = direction · joint + zero_offset``
(rad), sent as int16 centi-degrees.

Per control tick: ``write_goal`` sends one TARGETS frame per run of consecutive channels
(no reply); ``read_state`` sends TELEMETRY_REQ and waits for TELEMETRY. Every request
that expects a reply is retried ``retries`` times on a timeout or a damaged reply, then
fails with :class:`BridgeError`. The board's own safety net is configured at ``open``:
the joint limits (SET_LIMITS; the board rejects targets outside them) and the heartbeat
watchdog (the board switches its outputs off when the host goes quiet).

The port is opened with ``exclusive=True`` (pyserial takes an ``flock`` on POSIX), so a
second process gets a clear "in use" error instead of interleaved frames.
"""

from __future__ import annotations

import math
import time

import numpy as np

from firmware_cfg import serial_link as sl
from firmware_cfg.config import BusConfig, ServoConfig
from ros_free_bridge.errors import BridgeError
from ros_free_bridge.transports.base import STOP_POLICIES, JointState


class SerialLinkTransport:
    """Transport over a DFSL microcontroller link. Use as a context manager or call
    :meth:`open` / :meth:`close` (close is safe to call twice and after errors)."""

    def __init__(
        self,
        bus: BusConfig,
        *,
        port: str | None = None,
        joint_names: tuple[str, ...] | None = None,
        stop_policy: str = "hold",
        reply_timeout: float = 0.05,
        retries: int = 2,
        watchdog_ms: int = 250,
    ) -> None:
        if bus.protocol != "serial-link":
            raise BridgeError(
                f"bus {bus.name!r} has protocol {bus.protocol}; the serial-link transport needs 'serial-link'"
            )
        if stop_policy not in STOP_POLICIES:
            raise BridgeError(f"stop_policy {stop_policy!r} is not one of {STOP_POLICIES}")
        self.bus = bus
        self.port_name = port or bus.port
        by_joint = {s.joint: s for s in bus.servos}
        names = tuple(joint_names) if joint_names is not None else tuple(s.joint for s in bus.servos)
        missing = [j for j in names if j not in by_joint]
        if missing:
            raise BridgeError(f"serial link {bus.name!r}: joints {missing} have no channel in the hardware config")
        self.joint_names = names
        self.servos: tuple[ServoConfig, ...] = tuple(by_joint[j] for j in names)
        self.stop_policy = stop_policy
        self.reply_timeout = reply_timeout
        self.retries = retries
        self.watchdog_ms = watchdog_ms
        self.board: sl.HelloAck | None = None
        self._ser = None
        self._seq = 0
        self._decoder = sl.FrameDecoder()
        self._goal_written = False
        self._last_goal: np.ndarray | None = None
        self._pending_errors: list[sl.Error] = []
        self._directions = np.array([s.direction for s in self.servos], float)
        self._offsets = np.array([s.zero_offset for s in self.servos], float)
        self._lower = np.array([s.lower for s in self.servos], float)
        self._upper = np.array([s.upper for s in self.servos], float)
        self._channels = np.array([s.id for s in self.servos], int)

    # ------------------------------------------------------------------ life cycle
    def open(self) -> None:
        import serial

        if self._ser is not None:
            return
        try:
            self._ser = serial.Serial(self.port_name, self.bus.baud, timeout=0, exclusive=True)
        except (serial.SerialException, OSError, ValueError) as exc:
            text = str(exc)
            hint = (
                "another process holds it; close that program"
                if "lock" in text.lower() or "busy" in text.lower()
                else "check the cable and the port name (ls /dev/ttyACM* /dev/ttyUSB*)"
            )
            raise BridgeError(f"serial link {self.port_name}: cannot open ({text}); {hint}") from None
        try:
            ack = sl.HelloAck.unpack(
                self._request(
                    sl.MsgType.HELLO,
                    sl.Hello(sl.PROTOCOL_VERSION, self.watchdog_ms).pack(),
                    sl.MsgType.HELLO_ACK,
                    "HELLO",
                )
            )
            if ack.version != sl.PROTOCOL_VERSION:
                raise BridgeError(
                    f"serial link {self.port_name}: board speaks DFSL v{ack.version}, "
                    f"host v{sl.PROTOCOL_VERSION}; update the firmware"
                )
            need = int(self._channels.max()) + 1
            if ack.n_channels < need:
                raise BridgeError(
                    f"serial link {self.port_name}: board {ack.name!r} has {ack.n_channels} channels "
                    f"but the config uses channel {need - 1}"
                )
            self.board = ack
            self._send_limits()
        except BaseException:
            self._release()
            raise

    def close(self) -> None:
        if self._ser is None:
            return
        try:
            self.safe_stop(self.stop_policy)
        except BridgeError:
            pass  # the port may be gone; the board's watchdog then switches outputs off
        finally:
            self._release()

    def position_limits(self) -> None:
        """None: no limits beyond the caller's (see transports.base)."""
        return None

    def pipeline(self, enabled: bool = True) -> bool:
        """False: no split-phase bus cycle here (see transports.base)."""
        return False

    def __enter__(self) -> SerialLinkTransport:
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ Transport
    def read_state(self) -> JointState:
        tel = sl.Telemetry.unpack(self._request(sl.MsgType.TELEMETRY_REQ, b"", sl.MsgType.TELEMETRY, "TELEMETRY_REQ"))
        n = len(self.servos)
        state = JointState.unknown(n)
        servo_rad = np.array(
            [sl.cdeg_to_rad(tel.position_cdeg[c]) if c < len(tel.position_cdeg) else math.nan for c in self._channels]
        )
        state.position = self._directions * (servo_rad - self._offsets)
        state.temperature = np.array(
            [
                float(tel.temperature_c[c])
                if c < len(tel.temperature_c) and tel.temperature_c[c] != sl.UNKNOWN_TEMP
                else math.nan
                for c in self._channels
            ]
        )
        state.voltage = np.full(n, tel.supply_mv / 1000.0)
        state.torque_enabled = np.array([bool(tel.enabled_mask >> c & 1) for c in self._channels])
        for j, c in zip(self.joint_names, self._channels):
            if tel.fault_mask >> c & 1:
                state.errors[j] = f"channel {c} fault (stall or over-temperature); output off"
        state.stamp = time.monotonic()
        return state

    def write_goal(self, positions: np.ndarray) -> None:
        q = np.asarray(positions, float)
        if q.shape != (len(self.servos),):
            raise BridgeError(f"serial link: write_goal needs shape ({len(self.servos)},), got {q.shape}")
        bad = ~np.isfinite(q) | (q < self._lower - 1e-9) | (q > self._upper + 1e-9)
        if bad.any():
            i = int(np.argmax(bad))
            raise BridgeError(
                f"serial link: goal {q[i]:.4f} rad for joint {self.joint_names[i]} (channel {self._channels[i]}) "
                f"is outside its limits [{self._lower[i]:.4f}, {self._upper[i]:.4f}]; refusing to send"
            )
        self._raise_pending()
        cdeg = {int(c): self._to_cdeg(i, q[i]) for i, c in enumerate(self._channels)}
        for first, values in _runs(cdeg):
            self._send(sl.MsgType.TARGETS, sl.Targets(first, tuple(values)).pack())
        self._goal_written = True
        self._last_goal = q.copy()

    def set_torque(self, enabled: bool) -> None:
        if enabled and not self._goal_written:
            present = self.read_state().position
            self.write_goal(np.clip(present, self._lower, self._upper))
        mask = sum(1 << int(c) for c in self._channels) if enabled else 0
        self._request(sl.MsgType.ENABLE, sl.Enable(mask).pack(), sl.MsgType.ACK, "ENABLE")

    def safe_stop(self, policy: str = "hold") -> None:
        if policy not in STOP_POLICIES:
            raise BridgeError(f"safe_stop: policy {policy!r} is not one of {STOP_POLICIES}")
        if policy == "limp":
            self._request(sl.MsgType.ENABLE, sl.Enable(0).pack(), sl.MsgType.ACK, "ENABLE")
            return
        self._pending_errors.clear()
        present = self.read_state().position
        if np.all(np.isfinite(present)):
            self.write_goal(np.clip(present, self._lower, self._upper))

    # ------------------------------------------------------------------ wire
    def _to_cdeg(self, i: int, q: float) -> int:
        return sl.rad_to_cdeg(self._directions[i] * q + self._offsets[i])

    def _send_limits(self) -> None:
        limits = {}
        for s in self.servos:
            lo, hi = s.servo_limits()
            # round inwards so the board's limits are never wider than the config's
            limits[s.id] = (math.ceil(lo * 18000.0 / math.pi - 1e-9), math.floor(hi * 18000.0 / math.pi + 1e-9))
        for first, values in _runs(limits):
            self._request(
                sl.MsgType.SET_LIMITS, sl.SetLimits(first, tuple(values)).pack(), sl.MsgType.ACK, "SET_LIMITS"
            )

    def _send(self, mtype: int, payload: bytes) -> int:
        if self._ser is None:
            raise BridgeError(f"serial link {self.port_name}: not open; call open() first")
        self._seq = (self._seq + 1) & 0xFF
        raw = sl.encode(sl.Frame(self._seq, mtype, payload))
        try:
            self._ser.write(raw)
        except Exception as exc:  # serial.SerialException, OSError, termios.error
            raise BridgeError(
                f"serial link {self.port_name}: write failed ({exc}); the port is gone, check the cable"
            ) from None
        return self._seq

    def _request(self, mtype: int, payload: bytes, reply_type: int, what: str) -> bytes:
        """Send and wait for the reply of ``reply_type`` with the same SEQ; retry on timeouts
        and damaged replies; raise on an ERROR reply to this request."""
        for _attempt in range(self.retries + 1):
            seq = self._send(mtype, payload)
            deadline = time.monotonic() + self.reply_timeout
            while time.monotonic() < deadline:
                for frame in self._read_frames():
                    if frame.type == sl.MsgType.ERROR:
                        err = sl.Error.unpack(frame.payload)
                        if err.code == sl.ErrorCode.BAD_CRC:
                            deadline = 0.0  # the board saw our frame damaged: resend now
                            break
                        if frame.seq == seq and err.code != sl.ErrorCode.TARGET_OUT_OF_LIMITS:
                            raise BridgeError(
                                f"serial link {self.port_name}: board answered {what} with error: {self._describe(err)}"
                            )
                        self._pending_errors.append(err)
                        continue
                    if frame.type == reply_type and frame.seq == seq:
                        self._raise_pending()
                        return frame.payload
        raise BridgeError(
            f"serial link {self.port_name}: no valid reply to {what} after {self.retries + 1} tries "
            f"({self.reply_timeout * 1000:.0f} ms each); check power, baud {self.bus.baud} and cable"
        )

    def _read_frames(self) -> list[sl.Frame]:
        try:
            data = self._ser.read(self._ser.in_waiting or 1)
        except Exception as exc:
            raise BridgeError(
                f"serial link {self.port_name}: read failed ({exc}); the port is gone, check the cable"
            ) from None
        if not data:
            time.sleep(0.0002)
            return []
        return self._decoder.feed(data)

    def _raise_pending(self) -> None:
        if self._pending_errors:
            err = self._pending_errors.pop(0)
            self._pending_errors.clear()
            raise BridgeError(f"serial link {self.port_name}: board reported: {self._describe(err)}")

    def _describe(self, err: sl.Error) -> str:
        text = err.describe()
        joint = next((s.joint for s in self.servos if s.id == err.detail), None)
        if err.detail != 0xFF and joint and text.endswith(")"):
            text = text[:-1] + f", joint {joint})"
        return text

    def _release(self) -> None:
        ser, self._ser = self._ser, None
        self._goal_written = False
        if ser is not None:
            try:
                ser.close()
            except Exception:
                pass


def _runs(values: dict[int, object]) -> list[tuple[int, list]]:
    """{channel: value} → [(first_channel, [values of consecutive channels])]."""
    out: list[tuple[int, list]] = []
    for c in sorted(values):
        if out and out[-1][0] + len(out[-1][1]) == c:
            out[-1][1].append(values[c])
        else:
            out.append((c, [values[c]]))
    return out
