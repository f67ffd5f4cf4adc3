"""One open Dynamixel bus: the SDK's port and packet handler with bounded retries.

:class:`DynamixelBus` gives PING, READ, WRITE, REBOOT and SYNC_WRITE of one register, each
retried ``retries`` times and ending in a :class:`~ros_free_bridge.errors.BridgeError`
that names the servo (``names``: ID → joint) and what happened; every SDK call goes through
:meth:`DynamixelBus.call`, which clears the SDK's busy flag whatever happens and turns OS
errors into BridgeErrors. Used by the transport and by the ``servo`` commands.
"""

from __future__ import annotations

import dynamixel_sdk as sdk

from firmware_cfg.servo_models import Register
from ros_free_bridge.dynamixel.port import ExclusivePortHandler, set_latency_timer
from ros_free_bridge.dynamixel.protocol import ALERT_BIT, P1_HARDWARE_MASK, decode_hardware_error
from ros_free_bridge.errors import BridgeError


class DynamixelBus:
    """One open bus: the SDK port + packet handler with bounded retries and errors that
    name the servo. Used by the transport and by the ``servo`` commands.

    ``names``: servo ID → a label for messages (the joint name)."""

    def __init__(
        self,
        port: str,
        baud: int,
        protocol: float = 2.0,
        *,
        retries: int = 2,
        latency_ms: float = 16.0,
        names: dict[int, str] | None = None,
    ) -> None:
        self.port_name = port
        self.baud = baud
        self.protocol = float(protocol)
        self.retries = retries
        self.names = dict(names or {})
        self.latency_note = ""
        self._latency_ms = latency_ms
        self.port: ExclusivePortHandler | None = None
        self.ph = sdk.PacketHandler(self.protocol)
        #: Called (once, then cleared) before the next transfer: a transport that left a
        #: request's reply on the wire sets it, so nothing is sent over that reply (the bus
        #: is half duplex). See DynamixelTransport.pipeline.
        self.before_io = None

    # ------------------------------------------------------------------ life cycle
    def open(self) -> None:
        if self.port is not None:
            return
        timer, self.latency_note = set_latency_timer(self.port_name, 1)
        port = ExclusivePortHandler(self.port_name, latency_ms=timer if timer is not None else self._latency_ms)
        if port.getCFlagBaud(self.baud) <= 0:
            raise BridgeError(f"Dynamixel bus {self.port_name}: baud {self.baud} is not one the SDK can set")
        port.baudrate = self.baud
        try:
            port.setBaudRate(self.baud)
        except Exception as exc:  # serial.SerialException, OSError
            try:
                if port.ser is not None:
                    port.ser.close()
            except Exception:
                pass
            text = str(exc)
            hint = (
                "another program holds the port; close it (e.g. a second bridge, Dynamixel Wizard)"
                if "lock" in text.lower() or "busy" in text.lower() or "resource temporarily" in text.lower()
                else "check the cable and the port name (ls /dev/ttyUSB* /dev/ttyACM*)"
            )
            raise BridgeError(f"Dynamixel bus {self.port_name}: cannot open ({text}); {hint}") from None
        self.port = port

    def close(self) -> None:
        port, self.port = self.port, None
        self.before_io = None
        if port is not None:
            try:
                port.is_using = False
                if port.ser is not None:
                    port.closePort()
            except Exception:
                pass

    def __enter__(self) -> DynamixelBus:
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ primitives
    def label(self, sid: int) -> str:
        name = self.names.get(sid)
        return f"servo ID {sid}" + (f" ({name})" if name else "")

    def call(self, fn, *args, malformed=None):
        """Run one SDK call; the port's ``is_using`` flag is cleared whatever happens and
        OS-level failures (the port vanished) become BridgeError. With ``malformed`` given,
        an exception inside the SDK's reply parsing (e.g. an IndexError on a truncated
        fast-sync-read reply) returns ``malformed`` instead, so it counts as a failed try."""
        if self.port is None:
            raise BridgeError(f"Dynamixel bus {self.port_name}: not open; call open() first")
        if self.before_io is not None:
            settle, self.before_io = self.before_io, None
            settle()
        try:
            return fn(self.port, *args)
        except BridgeError:
            raise
        except (IndexError, KeyError) as exc:
            if malformed is not None:
                return malformed
            raise BridgeError(
                f"Dynamixel bus {self.port_name}: malformed reply during {getattr(fn, '__name__', 'a call')} "
                f"({type(exc).__name__}: {exc}); check for noise or a wrong baud rate"
            ) from None
        except Exception as exc:  # serial.SerialException, OSError, TypeError from a dead fd
            raise BridgeError(
                f"Dynamixel bus {self.port_name}: port failed during {getattr(fn, '__name__', 'a call')} "
                f"({type(exc).__name__}: {exc}); the adapter was unplugged or lost power"
            ) from None
        finally:
            if self.port is not None:
                self.port.is_using = False

    def comm_text(self, result: int) -> str:
        return self.ph.getTxRxResult(result).replace("[TxRxResult] ", "").rstrip("!")

    def error_text(self, error: int) -> str:
        if self.protocol == 2.0:
            return self.ph.getRxPacketError(error & ~ALERT_BIT).replace("[RxPacketError] ", "").rstrip("!")
        return ", ".join(decode_hardware_error(error, 1))

    def ping(self, sid: int, retries: int | None = None) -> int:
        """Model number of ``sid``; BridgeError after the retries."""
        last = 0
        for _ in range((self.retries if retries is None else retries) + 1):
            model, result, error = self.call(self.ph.ping, sid)
            if result == sdk.COMM_SUCCESS:
                return model
            last = result
        raise BridgeError(
            f"{self.label(sid)} on {self.port_name}: no answer to PING after "
            f"{(self.retries if retries is None else retries) + 1} tries ({self.comm_text(last)}); "
            f"check its power, ID and baud {self.baud}"
        )

    def read_raw(self, sid: int, address: int, length: int, what: str = "") -> tuple[bytes, int]:
        """Bytes [address, address+length) of ``sid`` and the status error byte."""
        last = 0
        for _ in range(self.retries + 1):
            data, result, error = self.call(self.ph.readTxRx, sid, address, length)
            if result == sdk.COMM_SUCCESS and len(data) == length:
                if self.protocol == 2.0 and error & 0x7F:
                    raise BridgeError(f"{self.label(sid)}: READ {what or address} refused: {self.error_text(error)}")
                return bytes(data), error
            last = result
        raise BridgeError(
            f"{self.label(sid)} on {self.port_name}: READ {what or f'address {address}'} failed after "
            f"{self.retries + 1} tries ({self.comm_text(last)})"
        )

    def read(self, sid: int, reg: Register) -> tuple[int, int]:
        """(value, status error byte) of one register."""
        data, error = self.read_raw(sid, reg.address, reg.size, reg.name)
        return reg.decode(data), error

    def write(self, sid: int, reg: Register, value: int) -> int:
        """Write one register, waiting for the status; returns the status error byte.
        A refused write (range, access, EEPROM locked by torque) is a BridgeError."""
        data = list(reg.encode(value))
        last = 0
        for _ in range(self.retries + 1):
            result, error = self.call(self.ph.writeTxRx, sid, reg.address, reg.size, data)
            if result == sdk.COMM_SUCCESS:
                refused = (error & 0x7F) if self.protocol == 2.0 else (error & ~P1_HARDWARE_MASK & 0x7F)
                if refused:
                    hint = " (EEPROM is locked while torque is on; switch torque off first)" if reg.eeprom else ""
                    raise BridgeError(
                        f"{self.label(sid)}: WRITE {reg.name}={value} refused: {self.error_text(error)}{hint}"
                    )
                return error
            last = result
        raise BridgeError(
            f"{self.label(sid)} on {self.port_name}: WRITE {reg.name}={value} failed after "
            f"{self.retries + 1} tries ({self.comm_text(last)})"
        )

    def reboot(self, sid: int) -> None:
        if self.protocol != 2.0:
            raise BridgeError(f"{self.label(sid)}: REBOOT exists on protocol 2.0 only; power-cycle the servo")
        last = 0
        for _ in range(self.retries + 1):
            result, error = self.call(self.ph.reboot, sid)
            if result == sdk.COMM_SUCCESS:
                return
            last = result
        raise BridgeError(f"{self.label(sid)}: REBOOT failed after {self.retries + 1} tries ({self.comm_text(last)})")

    def sync_write(self, reg: Register, values: dict[int, int]) -> None:
        """One GroupSyncWrite of ``reg`` (broadcast: no reply to wait for)."""
        group = sdk.GroupSyncWrite(self.port, self.ph, reg.address, reg.size)
        for sid, v in values.items():
            group.addParam(sid, list(reg.encode(v)))
        result = self.call(lambda port: group.txPacket())
        if result != sdk.COMM_SUCCESS:
            raise BridgeError(
                f"Dynamixel bus {self.port_name}: SYNC_WRITE {reg.name} failed ({self.comm_text(result)})"
            )
