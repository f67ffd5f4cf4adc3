"""Dynamixel protocol 2.0 and 1.0 packets: framing, CRC / checksum, byte stuffing, status
and error bits; pure functions over ``bytes``, no I/O.

Used by the bus (:mod:`.bus`), the hot-path group packets (:mod:`.group_codec`) and the
byte-level bus emulator (:mod:`ros_free_bridge.emulators`). Packet layouts, the CRC and the
stuffing rule are written out in docs/dynamixel.md; the tests check these bytes against
dynamixel-sdk's.
"""

from __future__ import annotations

from dataclasses import dataclass

from fastcrc.crc16 import umts as _crc16_umts

from ros_free_bridge.errors import BridgeError

HEADER2 = b"\xff\xff\xfd\x00"
BROADCAST_ID = 0xFE
STATUS = 0x55
SYNC_READ = 0x82
SYNC_WRITE = 0x83
FAST_SYNC_READ = 0x8A
FAST_BULK_READ = 0x9A
ALERT_BIT = 0x80


class PacketError(BridgeError):
    """A malformed packet: wrong header, length, CRC or checksum. Says which and why."""


def crc16(data, crc: int = 0) -> int:
    """CRC-16 of protocol 2.0: polynomial 0x8005 (x^16 + x^15 + x^2 + 1), init 0, MSB first,
    no final XOR (the catalogue's CRC-16/UMTS), by fastcrc's compiled code. ``data``: any
    bytes-like object (bytes, bytearray, memoryview); ``crc`` continues a running CRC, so
    ``crc16(b, crc16(a)) == crc16(a + b)``. A 20-servo reply's CRC costs well under a
    microsecond, where a table look-up per byte in Python cost ~25 µs with cold caches."""
    return _crc16_umts(data, crc)


#: struct format letter of a little-endian integer of 1, 2 or 4 bytes, by (size, signed)
INT_FORMAT = {(1, True): "b", (1, False): "B", (2, True): "h", (2, False): "H", (4, True): "i", (4, False): "I"}


def stuff(body: bytes) -> bytes:
    """Insert ``FD`` after every ``FF FF FD`` in the INST..PARAM bytes."""
    if b"\xff\xff\xfd" not in body:
        return bytes(body)
    return bytes(body).replace(b"\xff\xff\xfd", b"\xff\xff\xfd\xfd")


def unstuff(body: bytes) -> bytes:
    """Inverse of :func:`stuff`: ``FF FF FD FD`` becomes ``FF FF FD``."""
    if b"\xff\xff\xfd\xfd" not in body:
        return bytes(body)
    return bytes(body).replace(b"\xff\xff\xfd\xfd", b"\xff\xff\xfd")


def frame2(packet_id: int, body: bytes) -> bytes:
    """Header + ID + LEN + body (already stuffed) + CRC."""
    length = len(body) + 2
    head = HEADER2 + bytes((packet_id & 0xFF, length & 0xFF, length >> 8))
    crc = crc16(body, crc16(head))
    return head + body + bytes((crc & 0xFF, crc >> 8))


def encode_instruction(packet_id: int, instruction: int, params: bytes = b"") -> bytes:
    """A protocol 2.0 instruction packet, stuffed and with its CRC."""
    return frame2(packet_id, stuff(bytes((instruction,)) + bytes(params)))


HEADER1 = b"\xff\xff"

# Instructions (protocol 2.0; the 1.0 subset uses the same numbers).
PING = 0x01
READ = 0x02
WRITE = 0x03
REG_WRITE = 0x04
ACTION = 0x05
FACTORY_RESET = 0x06
REBOOT = 0x08
CLEAR = 0x10
BULK_READ = 0x92
BULK_WRITE = 0x93

INSTRUCTION_NAMES = {
    PING: "PING",
    READ: "READ",
    WRITE: "WRITE",
    REG_WRITE: "REG_WRITE",
    ACTION: "ACTION",
    FACTORY_RESET: "FACTORY_RESET",
    REBOOT: "REBOOT",
    CLEAR: "CLEAR",
    SYNC_READ: "SYNC_READ",
    SYNC_WRITE: "SYNC_WRITE",
    FAST_SYNC_READ: "FAST_SYNC_READ",
    BULK_READ: "BULK_READ",
    BULK_WRITE: "BULK_WRITE",
    FAST_BULK_READ: "FAST_BULK_READ",
    STATUS: "STATUS",
}

# Protocol 2.0 status error numbers (bits 0-6 of ERR); bit 7 is the hardware alert.
ERR_RESULT_FAIL = 0x01
ERR_INSTRUCTION = 0x02
ERR_CRC = 0x03
ERR_DATA_RANGE = 0x04
ERR_DATA_LENGTH = 0x05
ERR_DATA_LIMIT = 0x06
ERR_ACCESS = 0x07
ERR_ALERT = 0x80

# Protocol 1.0 status error bits.
ERR1_VOLTAGE = 0x01
ERR1_ANGLE = 0x02
ERR1_OVERHEAT = 0x04
ERR1_RANGE = 0x08
ERR1_CHECKSUM = 0x10
ERR1_OVERLOAD = 0x20
ERR1_INSTRUCTION = 0x40


#: Hardware Error Status (register 70, X series) bits → names.
HW_ERROR_BITS = {
    0x01: "input voltage",
    0x04: "overheating",
    0x08: "motor encoder",
    0x10: "electrical shock",
    0x20: "overload",
}
#: Protocol 1.0 status error byte bits → names.
P1_ERROR_BITS = {
    0x01: "input voltage",
    0x02: "angle limit",
    0x04: "overheating",
    0x08: "range",
    0x10: "checksum",
    0x20: "overload",
    0x40: "instruction",
}
P1_HARDWARE_MASK = 0x01 | 0x04 | 0x20


def decode_hardware_error(bits: int, protocol: int = 2) -> list[str]:
    """Hardware Error Status bits (protocol 2.0) or status error bits (1.0) → names."""
    table = HW_ERROR_BITS if protocol == 2 else P1_ERROR_BITS
    names = [name for bit, name in table.items() if bits & bit]
    unknown = bits & ~sum(table)
    if unknown:
        names.append(f"unknown bits 0x{unknown:02X}")
    return names


def encode_status(packet_id: int, error: int, params: bytes = b"", *, stuffing: bool = True) -> bytes:
    """A protocol 2.0 status packet (INST 0x55). ``stuffing=False`` for fast replies only."""
    body = bytes((STATUS, error & 0xFF)) + bytes(params)
    return frame2(packet_id, stuff(body) if stuffing else body)


def encode_fast_status(parts: list[tuple[int, int, bytes]], length: int | None = None) -> bytes:
    """The single status packet of a Fast Sync/Bulk Read: ``parts`` = [(error, id, data)].

    Each part is followed by the CRC of the packet up to and including that part,
    as every servo in the chain appends its own piece. Never stuffed. ``length``
    overrides the LEN field: the first servo announces the whole reply, so a chain
    that breaks part-way leaves a packet shorter than its LEN says.
    """
    if length is None:
        length = 1 + sum(4 + len(data) for _, _, data in parts)
    out = bytearray(HEADER2 + bytes((BROADCAST_ID, length & 0xFF, length >> 8, STATUS)))
    crc = crc16(out)
    for error, servo_id, data in parts:
        piece = bytes((error & 0xFF, servo_id & 0xFF)) + bytes(data)
        crc = crc16(piece, crc)  # running CRC of the packet so far
        out += piece + bytes((crc & 0xFF, crc >> 8))
        crc = crc16(out[-2:], crc)
    return bytes(out)


@dataclass(frozen=True)
class Packet:
    """A decoded packet of either protocol.

    ``instruction`` is 0x55 for a protocol 2.0 status packet; for protocol 1.0 status
    packets (which have no instruction byte) it is ``STATUS`` too. ``error`` is None
    for instruction packets. ``params`` are unstuffed.
    """

    protocol: int
    id: int
    instruction: int
    params: bytes
    error: int | None = None

    @property
    def is_status(self) -> bool:
        return self.error is not None


def decode_packet(raw: bytes) -> Packet:
    """Decode one complete protocol 2.0 packet (instruction or status), checking its CRC."""
    raw = bytes(raw)
    if len(raw) < 10 or raw[:4] != HEADER2:
        raise PacketError(
            f"not a protocol 2.0 packet: {raw[:8].hex(' ')}... (needs header FF FF FD 00 and >= 10 bytes)"
        )
    length = raw[5] | (raw[6] << 8)
    if len(raw) != 7 + length:
        raise PacketError(f"packet length field says {length} bytes after it but {len(raw) - 7} follow")
    crc = raw[-2] | (raw[-1] << 8)
    expected = crc16(raw[:-2])
    if crc != expected:
        raise PacketError(f"CRC mismatch: packet carries 0x{crc:04X}, bytes give 0x{expected:04X}")
    body = unstuff(raw[7:-2])
    instruction = body[0]
    if instruction == STATUS:
        if len(body) < 2:
            raise PacketError("status packet without an error byte")
        return Packet(2, raw[4], STATUS, body[2:], body[1])
    return Packet(2, raw[4], instruction, body[1:])


def decode_fast_status(raw: bytes, data_lengths: list[int]) -> list[tuple[int, int, bytes]]:
    """Split a Fast Sync/Bulk Read reply into [(error, id, data)], checking every CRC.

    ``data_lengths`` gives each servo's data length in reply order.
    """
    raw = bytes(raw)
    if raw[:4] != HEADER2 or len(raw) < 8 or raw[4] != BROADCAST_ID or raw[7] != STATUS:
        raise PacketError("not a fast-read status packet (needs FF FF FD 00 FE .. .. 55)")
    length = raw[5] | (raw[6] << 8)
    if len(raw) != 7 + length or length != 1 + sum(4 + n for n in data_lengths):
        raise PacketError(
            f"fast-read length {length} does not match {len(data_lengths)} servos of {data_lengths} bytes"
        )
    parts, pos = [], 8
    for n in data_lengths:
        end = pos + 2 + n
        crc = raw[end] | (raw[end + 1] << 8)
        if crc16(raw[:end]) != crc:
            raise PacketError(f"fast-read CRC mismatch in the part for servo ID {raw[pos + 1]}")
        parts.append((raw[pos], raw[pos + 1], raw[pos + 2 : end]))
        pos = end + 2
    return parts


# ----------------------------------------------------------------------------- protocol 1.0


def checksum1(body: bytes) -> int:
    """Protocol 1.0 checksum over ID..last parameter: ~sum & 0xFF."""
    return (~sum(body)) & 0xFF


def encode_instruction1(packet_id: int, instruction: int, params: bytes = b"") -> bytes:
    """A protocol 1.0 instruction packet."""
    body = bytes((packet_id & 0xFF, len(params) + 2, instruction)) + bytes(params)
    return HEADER1 + body + bytes((checksum1(body),))


def encode_status1(packet_id: int, error: int, params: bytes = b"") -> bytes:
    """A protocol 1.0 status packet."""
    body = bytes((packet_id & 0xFF, len(params) + 2, error & 0xFF)) + bytes(params)
    return HEADER1 + body + bytes((checksum1(body),))


def decode_packet1(raw: bytes, *, status: bool) -> Packet:
    """Decode one complete protocol 1.0 packet. Protocol 1.0 cannot tell an instruction
    from a status packet by its bytes, so the caller says which it expects."""
    raw = bytes(raw)
    if len(raw) < 6 or raw[:2] != HEADER1:
        raise PacketError(f"not a protocol 1.0 packet: {raw[:6].hex(' ')} (needs FF FF and >= 6 bytes)")
    length = raw[3]
    if len(raw) != 4 + length:
        raise PacketError(f"protocol 1.0 length field says {length} bytes after it but {len(raw) - 4} follow")
    if checksum1(raw[2:-1]) != raw[-1]:
        raise PacketError(f"checksum mismatch: packet carries 0x{raw[-1]:02X}, bytes give 0x{checksum1(raw[2:-1]):02X}")
    if status:
        return Packet(1, raw[2], STATUS, raw[5:-1], raw[4])
    return Packet(1, raw[2], raw[4], raw[5:-1])


# ----------------------------------------------------------------------------- stream framing


@dataclass(frozen=True)
class Frame:
    """One framed packet out of a byte stream: its raw bytes, its protocol (1 or 2) and
    whether its CRC/checksum held."""

    raw: bytes
    valid: bool
    protocol: int = 2


class StreamParser:
    """Cuts a byte stream (as read from a serial port) into packets.

    ``protocol`` is 1, 2, or None to accept both on one bus (a packet starting
    ``FF FF FD 00`` is protocol 2.0, any other ``FF FF ID`` is protocol 1.0; a 1.0 packet
    cannot start ``FF FF FD 00`` because its length byte is at least 2).
    ``feed(data)`` returns the frames completed by ``data``; partial packets wait for
    more bytes. Garbage before a header is skipped. A frame with a bad CRC/checksum is
    returned with ``valid=False`` (a servo answers it with a CRC error); an impossible
    length (protocol 2.0 above ``max_length``, protocol 1.0 below 2) drops one byte and
    resyncs.
    """

    def __init__(self, protocol: int | None = 2, max_length: int = 1024) -> None:
        if protocol not in (1, 2, None):
            raise PacketError(f"protocol must be 1, 2 or None (both), got {protocol!r}")
        self.protocol = protocol
        self.max_length = max_length
        self._buf = bytearray()

    def reset(self) -> None:
        self._buf.clear()

    @property
    def pending(self) -> int:
        """Bytes held back waiting for the rest of a packet."""
        return len(self._buf)

    def feed(self, data: bytes) -> list[Frame]:
        self._buf += data
        out: list[Frame] = []
        buf = self._buf
        while True:
            start = buf.find(b"\xff\xff")
            if start < 0:
                del buf[: len(buf) - (1 if buf.endswith(b"\xff") else 0)]
                return out
            # skip runs of FF so the header's last FF is the one before the ID/FD byte
            while len(buf) > start + 2 and buf[start + 2] == 0xFF:
                start += 1
            del buf[:start]
            if len(buf) < 4:
                return out
            is_v2 = buf[2] == 0xFD and buf[3] == 0x00
            if is_v2 and self.protocol != 1:
                if len(buf) < 7:
                    return out
                length = buf[5] | (buf[6] << 8)
                if length < 3 or length > self.max_length:
                    del buf[0]
                    continue
                if len(buf) < 7 + length:
                    return out
                raw = bytes(buf[: 7 + length])
                del buf[: 7 + length]
                out.append(Frame(raw, crc16(raw[:-2]) == (raw[-2] | (raw[-1] << 8)), 2))
            elif not is_v2 and self.protocol != 2:
                length = buf[3]
                if length < 2:
                    del buf[0]
                    continue
                if len(buf) < 4 + length:
                    return out
                raw = bytes(buf[: 4 + length])
                del buf[: 4 + length]
                out.append(Frame(raw, checksum1(raw[2:-1]) == raw[-1], 1))
            else:
                del buf[0]
