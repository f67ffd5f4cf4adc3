"""The pipe protocol between the bridge and its generator process: framing and message bodies.

Messages are ``<u4 payload length><u1 type><payload>``, little-endian, JSON or float64/int64
arrays only (no pickle); the message types: docs/partner_pipeline.md. :class:`Channel`
frames them over a pair of pipe file descriptors.
"""

from __future__ import annotations

import fcntl
import json
import os
import select
import struct

import numpy as np

from ros_free_bridge.errors import BridgeError
from ros_free_bridge.partner.core import PartnerTarget
from ros_free_bridge.sources.udp import ActorFrame

HEADER = struct.Struct("<IB")
ACTOR = struct.Struct("<qd")
TARGET = struct.Struct("<qqdddB")
N_POS = 22 * 3
PIPE_BYTES = 1 << 20  #: ask for 1 MiB pipes (~30 s of actor frames) so the parent never blocks writing


class Channel:
    """Framed messages over a pair of pipe file descriptors (read side buffered)."""

    def __init__(self, rfd: int, wfd: int):
        self.rfd, self.wfd = rfd, wfd
        self._buf = bytearray()
        self.eof = False
        for fd in (rfd, wfd):
            try:
                fcntl.fcntl(fd, fcntl.F_SETPIPE_SZ, PIPE_BYTES)
            except OSError:
                pass  # not Linux, or above the system's limit: the default 64 KiB pipe still works

    def send(self, kind: bytes, payload: bytes = b"") -> None:
        data = HEADER.pack(len(payload), kind[0]) + payload
        view = memoryview(data)
        while view:
            view = view[os.write(self.wfd, view) :]

    def send_json(self, kind: bytes, obj) -> None:
        self.send(kind, json.dumps(obj).encode())

    def receive(self, timeout: float | None) -> list[tuple[bytes, bytes]]:
        """Every complete message available, waiting up to ``timeout`` s (None: forever) for the first."""
        out = self._parse()
        if out or self.eof:
            return out
        ready, _, _ = select.select([self.rfd], [], [], timeout)
        while ready:
            chunk = os.read(self.rfd, 1 << 16)
            if not chunk:
                self.eof = True
                break
            self._buf += chunk
            ready, _, _ = select.select([self.rfd], [], [], 0)
        return self._parse()

    def _parse(self) -> list[tuple[bytes, bytes]]:
        out, buf, pos = [], self._buf, 0
        while len(buf) - pos >= HEADER.size:
            n, kind = HEADER.unpack_from(buf, pos)
            if len(buf) - pos - HEADER.size < n:
                break
            out.append((bytes([kind]), bytes(buf[pos + HEADER.size : pos + HEADER.size + n])))
            pos += HEADER.size + n
        del buf[:pos]
        return out

    def close(self) -> None:
        for fd in (self.rfd, self.wfd):
            try:
                os.close(fd)
            except OSError:
                pass


def encode_actor(index: int, arrival: float, positions) -> bytes:
    """An A message's body: index, arrival (monotonic s), positions (22, 3) m."""
    pos = np.ascontiguousarray(positions, dtype="<f8").reshape(N_POS)
    return ACTOR.pack(int(index), float(arrival)) + pos.tobytes()


def decode_actor(payload: bytes) -> ActorFrame:
    if len(payload) != ACTOR.size + 8 * N_POS:
        raise BridgeError(
            f"generator process: actor message of {len(payload)} bytes, expected {ACTOR.size + 8 * N_POS}"
        )
    index, arrival = ACTOR.unpack_from(payload)
    pos = np.frombuffer(payload, "<f8", N_POS, ACTOR.size).reshape(22, 3).copy()
    return ActorFrame(index, pos, arrival)


def encode_target(t: PartnerTarget) -> bytes:
    """A T message's body: a target's indices, timing and flags (held, settle, the partner's
    foot contacts), q (n,) rad, partner positions (22, 3) m."""
    q = np.ascontiguousarray(t.q, dtype="<f8")
    pos = np.ascontiguousarray(t.positions, dtype="<f8").reshape(N_POS)
    flags = int(t.held) | int(t.settle) << 1
    if t.contacts is not None:  # bit 2: contacts known; bits 3-6: the four contacts
        flags |= 4 | sum(int(bool(c)) << (3 + i) for i, c in enumerate(np.asarray(t.contacts).reshape(4)))
    head = TARGET.pack(t.index, t.actor_frame, t.arrival, t.gen_latency, t.rt_latency, flags)
    return head + q.tobytes() + pos.tobytes()


def decode_target(payload: bytes, n_joints: int) -> PartnerTarget:
    if len(payload) != TARGET.size + 8 * (n_joints + N_POS):
        raise BridgeError(
            f"generator process: target message of {len(payload)} bytes, expected "
            f"{TARGET.size + 8 * (n_joints + N_POS)} for {n_joints} joints"
        )
    index, actor_frame, arrival, gen, rt, flags = TARGET.unpack_from(payload)
    q = np.frombuffer(payload, "<f8", n_joints, TARGET.size).copy()
    pos = np.frombuffer(payload, "<f8", N_POS, TARGET.size + 8 * n_joints).reshape(22, 3).copy()
    contacts = np.array([bool(flags >> (3 + i) & 1) for i in range(4)]) if flags & 4 else None
    return PartnerTarget(index, q, pos, arrival, actor_frame, gen, rt, bool(flags & 1), bool(flags & 2), contacts)
