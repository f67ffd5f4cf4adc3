"""The live actor stream's UDP packet format, version 1: encode and decode actor frames and
e-stops (16-byte header with magic, version, type, sequence number and stream id; 22 x 3
float32 positions in metres). The byte layout and the receiver's drop rules: docs/actor_stream.md.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

MAGIC = b"DFA1"
VERSION = 1
TYPE_FRAME = 1
TYPE_ESTOP = 2
HEADER = struct.Struct("<4sBBHII")
STAMP = struct.Struct("<d")
N_VALUES = 22 * 3
FRAME_SIZE = HEADER.size + STAMP.size + 4 * N_VALUES  # 288
ESTOP_SIZE = HEADER.size + STAMP.size  # 24
#: Largest accepted |coordinate| of an actor joint, metres (a person within 10 m of the origin).
MAX_ABS_M = 10.0
#: Largest accepted forward jump of the sequence number within one stream: 3000 packets, more
#: than a minute and a half of frames at 30 fps lost in a row.
MAX_SEQ_JUMP = 3000


class PacketError(ValueError):
    """A datagram that is not a valid version-1 packet (it is dropped and counted); ``kind``
    says which counter: ``garbage`` (not a packet) or ``out_of_range`` (a packet whose values
    cannot be a person)."""

    def __init__(self, message: str, kind: str = "garbage"):
        super().__init__(message)
        self.kind = kind


@dataclass(frozen=True)
class ActorFramePacket:
    seq: int
    stamp: float
    positions: np.ndarray  # (22, 3) float64 metres
    stream: int = 0  #: the sender's stream id (0: not given)


@dataclass(frozen=True)
class EStopPacket:
    seq: int
    stamp: float
    stream: int = 0


def encode_frame(seq: int, stamp: float, positions, stream: int = 0) -> bytes:
    pos = np.asarray(positions, dtype="<f4")
    if pos.shape != (22, 3):
        raise PacketError(f"positions must have shape (22, 3), got {pos.shape}")
    return (
        HEADER.pack(MAGIC, VERSION, TYPE_FRAME, 0, seq & 0xFFFFFFFF, stream & 0xFFFFFFFF)
        + STAMP.pack(stamp)
        + pos.tobytes()
    )


def encode_estop(seq: int, stamp: float, stream: int = 0) -> bytes:
    return HEADER.pack(MAGIC, VERSION, TYPE_ESTOP, 0, seq & 0xFFFFFFFF, stream & 0xFFFFFFFF) + STAMP.pack(stamp)


def decode(data: bytes) -> ActorFramePacket | EStopPacket:
    if len(data) < HEADER.size:
        raise PacketError(f"datagram of {len(data)} bytes is shorter than the {HEADER.size}-byte header")
    magic, version, kind, _, seq, stream = HEADER.unpack_from(data)
    if magic != MAGIC:
        raise PacketError(f"bad magic {magic!r}, expected {MAGIC!r}")
    if version != VERSION:
        raise PacketError(f"unsupported packet version {version}, this receiver speaks version {VERSION}")
    if kind == TYPE_FRAME:
        if len(data) != FRAME_SIZE:
            raise PacketError(f"actor frame must be {FRAME_SIZE} bytes, got {len(data)}")
        (stamp,) = STAMP.unpack_from(data, HEADER.size)
        pos = np.frombuffer(data, dtype="<f4", count=N_VALUES, offset=HEADER.size + STAMP.size)
        if not (np.isfinite(stamp) and np.all(np.isfinite(pos))):
            raise PacketError(f"actor frame {seq} has NaN or inf values", "out_of_range")
        if np.abs(pos).max() > MAX_ABS_M:  # finite, but no person: 3e38 overflows float32 arithmetic
            raise PacketError(
                f"actor frame {seq} has a joint {float(np.abs(pos).max()):.3g} m from the origin "
                f"(more than {MAX_ABS_M:g} m)",
                "out_of_range",
            )
        return ActorFramePacket(seq, stamp, pos.reshape(22, 3).astype(np.float64), stream)
    if kind == TYPE_ESTOP:
        if len(data) != ESTOP_SIZE:
            raise PacketError(f"e-stop packet must be {ESTOP_SIZE} bytes, got {len(data)}")
        (stamp,) = STAMP.unpack_from(data, HEADER.size)
        return EStopPacket(seq, stamp, stream)
    raise PacketError(f"unknown packet type {kind}")


def is_newer(seq: int, last: int | None) -> bool:
    """Sequence comparison with wrap-around (RFC 1982 style serial arithmetic)."""
    if last is None:
        return True
    diff = (seq - last) & 0xFFFFFFFF
    return 0 < diff < 0x80000000
