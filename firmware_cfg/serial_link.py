"""Codec for the DualFlow serial link (DFSL v1): the small binary protocol between the
host and a microcontroller servo board. The normative description, with test vectors,
is ``firmware_cfg/serial_link.md``; this module implements exactly that (stdlib only).

Frame (all multi-byte integers little-endian)::

    A5 5A | SEQ u8 | TYPE u8 | LEN u8 | PAYLOAD (LEN bytes) | CRC16 u16

CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, not reflected, xorout 0; check value
of ASCII "123456789" is 0x29B1) over SEQ, TYPE, LEN and PAYLOAD, i.e. everything
after the two sync bytes. ``binascii.crc_hqx(data, 0xFFFF)`` computes it.

Wire units: angles are int16 centi-degrees (0.01°, ±327.67°), supply voltage u16
millivolts, times u16/u32 milliseconds, temperatures int8 °C. Radians exist only in
:func:`rad_to_cdeg` / :func:`cdeg_to_rad`.
"""

from __future__ import annotations

import binascii
import math
import struct
from dataclasses import dataclass, field
from enum import IntEnum

from firmware_cfg.errors import ConfigError

SYNC = b"\xa5\x5a"
PROTOCOL_VERSION = 1
MAX_PAYLOAD = 255
MAX_CHANNELS = 32
HEADER_LEN = 5  # sync(2) seq type len
FRAME_OVERHEAD = HEADER_LEN + 2  # + crc
#: int16 value meaning "not measured" in telemetry position / int8 for temperature.
UNKNOWN_CDEG = -32768
UNKNOWN_TEMP = -128
REPLY_BIT = 0x80


class MsgType(IntEnum):
    """Message types. Host → MCU below 0x80; the MCU's replies set bit 7."""

    HELLO = 0x01
    TARGETS = 0x02
    ENABLE = 0x03
    HEARTBEAT = 0x04
    TELEMETRY_REQ = 0x05
    SET_LIMITS = 0x06
    HELLO_ACK = 0x81
    ACK = 0x83
    HEARTBEAT_ACK = 0x84
    TELEMETRY = 0x85
    ERROR = 0xFF


class ErrorCode(IntEnum):
    """Codes in an ERROR frame (``detail`` is the channel, or 0xFF when none)."""

    BAD_CRC = 1
    UNKNOWN_TYPE = 2
    BAD_LENGTH = 3
    BAD_CHANNEL = 4
    TARGET_OUT_OF_LIMITS = 5
    WATCHDOG_EXPIRED = 6
    BAD_VERSION = 7
    NOT_READY = 8


ERROR_TEXT = {
    ErrorCode.BAD_CRC: "a frame arrived with a bad CRC",
    ErrorCode.UNKNOWN_TYPE: "unknown message type",
    ErrorCode.BAD_LENGTH: "payload length does not fit the message type",
    ErrorCode.BAD_CHANNEL: "channel number beyond the board's channel count",
    ErrorCode.TARGET_OUT_OF_LIMITS: "target outside the channel's limits (rejected, previous target kept)",
    ErrorCode.WATCHDOG_EXPIRED: "heartbeat watchdog expired; all outputs disabled",
    ErrorCode.BAD_VERSION: "protocol version not supported by the board",
    ErrorCode.NOT_READY: "HELLO has not been received yet",
}


def crc16(data: bytes, crc: int = 0xFFFF) -> int:
    """CRC-16/CCITT-FALSE of ``data`` (check: crc16(b"123456789") == 0x29B1)."""
    return binascii.crc_hqx(data, crc)


def rad_to_cdeg(angle: float) -> int:
    """Radians → int16 centi-degrees, rounded to nearest: cdeg = round(angle · 18000/π).

    Raises ConfigError outside the int16 range (±327.67°)."""
    value = int(round(angle * 18000.0 / math.pi))
    if not -32767 <= value <= 32767:
        raise ConfigError(f"serial link: angle {angle:.4f} rad is outside the wire range ±327.67°")
    return value


def cdeg_to_rad(value: int) -> float:
    """int16 centi-degrees → radians (NaN for UNKNOWN_CDEG): angle = value · π/18000."""
    if value == UNKNOWN_CDEG:
        return math.nan
    return value * math.pi / 18000.0


@dataclass(frozen=True)
class Frame:
    seq: int
    type: int
    payload: bytes = b""


def encode(frame: Frame) -> bytes:
    """Frame → bytes on the wire."""
    if not 0 <= frame.seq <= 255:
        raise ConfigError(f"serial link: seq {frame.seq} is not a u8")
    if len(frame.payload) > MAX_PAYLOAD:
        raise ConfigError(f"serial link: payload of {len(frame.payload)} bytes exceeds {MAX_PAYLOAD}")
    body = bytes((frame.seq, int(frame.type), len(frame.payload))) + bytes(frame.payload)
    return SYNC + body + struct.pack("<H", crc16(body))


def decode(data: bytes) -> Frame:
    """Exactly one frame's bytes → Frame; ConfigError on any defect."""
    frames = FrameDecoder()
    out = frames.feed(data)
    if len(out) != 1 or frames.pending or frames.crc_errors:
        raise ConfigError(f"serial link: {data.hex(' ')} is not exactly one valid frame")
    return out[0]


@dataclass
class FrameDecoder:
    """Incremental decoder: feed bytes as they arrive, get complete frames back.

    On a CRC mismatch it counts the error, drops the first sync byte and resynchronises
    on the next A5 5A, so one damaged frame never swallows the next.
    """

    buffer: bytearray = field(default_factory=bytearray)
    crc_errors: int = 0

    @property
    def pending(self) -> int:
        return len(self.buffer)

    def feed(self, data: bytes) -> list[Frame]:
        self.buffer.extend(data)
        frames: list[Frame] = []
        buf = self.buffer
        while True:
            start = buf.find(SYNC)
            if start < 0:
                # keep a trailing A5 that may be the first half of a sync pair
                del buf[: max(0, len(buf) - 1) if buf[-1:] == b"\xa5" else len(buf)]
                return frames
            if start:
                del buf[:start]
            if len(buf) < HEADER_LEN:
                return frames
            total = FRAME_OVERHEAD + buf[4]
            if len(buf) < total:
                return frames
            body = bytes(buf[2 : total - 2])
            (crc,) = struct.unpack_from("<H", buf, total - 2)
            if crc16(body) != crc:
                self.crc_errors += 1
                del buf[:1]
                continue
            frames.append(Frame(body[0], body[1], body[3:]))
            del buf[:total]


# --- payloads -------------------------------------------------------------------------


@dataclass(frozen=True)
class Hello:
    """HELLO (host → MCU): the host's protocol version and the watchdog timeout in ms
    (0 disables the watchdog)."""

    version: int = PROTOCOL_VERSION
    watchdog_ms: int = 0

    def pack(self) -> bytes:
        return struct.pack("<BH", self.version, self.watchdog_ms)

    @classmethod
    def unpack(cls, p: bytes) -> Hello:
        _need(p, 3, "HELLO")
        return cls(*struct.unpack("<BH", p))


@dataclass(frozen=True)
class HelloAck:
    """HELLO_ACK (MCU → host): protocol version, firmware major/minor, channel count and
    a board name of up to 16 ASCII bytes."""

    version: int
    fw_major: int
    fw_minor: int
    n_channels: int
    name: str = ""

    def pack(self) -> bytes:
        name = self.name.encode("ascii")[:16]
        return struct.pack("<BBBB", self.version, self.fw_major, self.fw_minor, self.n_channels) + name

    @classmethod
    def unpack(cls, p: bytes) -> HelloAck:
        _need(p, 4, "HELLO_ACK", exact=False)
        v, ma, mi, n = struct.unpack_from("<BBBB", p)
        return cls(v, ma, mi, n, p[4:20].decode("ascii", "replace"))


@dataclass(frozen=True)
class Targets:
    """TARGETS (host → MCU, no reply): ``first`` channel and int16 centi-degree targets
    for channels first .. first+len-1."""

    first: int
    cdeg: tuple[int, ...]

    def pack(self) -> bytes:
        return struct.pack(f"<BB{len(self.cdeg)}h", self.first, len(self.cdeg), *self.cdeg)

    @classmethod
    def unpack(cls, p: bytes) -> Targets:
        _need(p, 2, "TARGETS", exact=False)
        first, count = p[0], p[1]
        _need(p, 2 + 2 * count, "TARGETS")
        return cls(first, struct.unpack_from(f"<{count}h", p, 2))


@dataclass(frozen=True)
class Enable:
    """ENABLE (host → MCU, answered by ACK): u32 bit mask, bit c = 1 drives channel c,
    0 switches its output off (limp). The mask replaces the previous one."""

    mask: int

    def pack(self) -> bytes:
        return struct.pack("<I", self.mask)

    @classmethod
    def unpack(cls, p: bytes) -> Enable:
        _need(p, 4, "ENABLE")
        return cls(*struct.unpack("<I", p))


@dataclass(frozen=True)
class SetLimits:
    """SET_LIMITS (host → MCU, answered by ACK): per channel (min, max) int16 centi-degrees
    for channels first .. first+len-1. The MCU rejects targets outside them."""

    first: int
    limits: tuple[tuple[int, int], ...]

    def pack(self) -> bytes:
        flat = [v for pair in self.limits for v in pair]
        return struct.pack(f"<BB{len(flat)}h", self.first, len(self.limits), *flat)

    @classmethod
    def unpack(cls, p: bytes) -> SetLimits:
        _need(p, 2, "SET_LIMITS", exact=False)
        first, count = p[0], p[1]
        _need(p, 2 + 4 * count, "SET_LIMITS")
        flat = struct.unpack_from(f"<{2 * count}h", p, 2)
        return cls(first, tuple(zip(flat[::2], flat[1::2])))


@dataclass(frozen=True)
class Ack:
    """ACK (MCU → host): the type of the message acknowledged."""

    acked_type: int

    def pack(self) -> bytes:
        return bytes((self.acked_type,))

    @classmethod
    def unpack(cls, p: bytes) -> Ack:
        _need(p, 1, "ACK")
        return cls(p[0])


@dataclass(frozen=True)
class HeartbeatAck:
    """HEARTBEAT_ACK (MCU → host): board uptime in ms (u32, wraps)."""

    uptime_ms: int

    def pack(self) -> bytes:
        return struct.pack("<I", self.uptime_ms)

    @classmethod
    def unpack(cls, p: bytes) -> HeartbeatAck:
        _need(p, 4, "HEARTBEAT_ACK")
        return cls(*struct.unpack("<I", p))


@dataclass(frozen=True)
class Telemetry:
    """TELEMETRY (MCU → host), answer to TELEMETRY_REQ::

        uptime_ms u32 | supply_mv u16 | enabled_mask u32 | fault_mask u32 | n u8 |
        n × position int16 cdeg | n × temperature int8 °C

    ``fault_mask`` bit c set: channel c has a fault (stalled, over-temperature) and its
    output is off. Unmeasured positions are -32768, unmeasured temperatures -128.
    """

    uptime_ms: int
    supply_mv: int
    enabled_mask: int
    fault_mask: int
    position_cdeg: tuple[int, ...]
    temperature_c: tuple[int, ...]

    def pack(self) -> bytes:
        n = len(self.position_cdeg)
        return struct.pack(
            f"<IHIIB{n}h{n}b",
            self.uptime_ms,
            self.supply_mv,
            self.enabled_mask,
            self.fault_mask,
            n,
            *self.position_cdeg,
            *self.temperature_c,
        )

    @classmethod
    def unpack(cls, p: bytes) -> Telemetry:
        _need(p, 15, "TELEMETRY", exact=False)
        up, mv, en, fault, n = struct.unpack_from("<IHIIB", p)
        _need(p, 15 + 3 * n, "TELEMETRY")
        pos = struct.unpack_from(f"<{n}h", p, 15)
        temp = struct.unpack_from(f"<{n}b", p, 15 + 2 * n)
        return cls(up, mv, en, fault, pos, temp)


@dataclass(frozen=True)
class Error:
    """ERROR (MCU → host): code (ErrorCode) and detail (channel, or 0xFF)."""

    code: int
    detail: int = 0xFF

    def pack(self) -> bytes:
        return bytes((self.code, self.detail))

    @classmethod
    def unpack(cls, p: bytes) -> Error:
        _need(p, 2, "ERROR")
        return cls(p[0], p[1])

    def describe(self) -> str:
        try:
            text = ERROR_TEXT[ErrorCode(self.code)]
        except ValueError:
            text = f"unknown error code {self.code}"
        where = "" if self.detail == 0xFF else f" (channel {self.detail})"
        return text + where


def _need(p: bytes, n: int, what: str, exact: bool = True) -> None:
    if (len(p) != n) if exact else (len(p) < n):
        raise ConfigError(f"serial link: {what} payload has {len(p)} bytes, expected {'' if exact else 'at least '}{n}")
