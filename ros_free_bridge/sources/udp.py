"""Live actor joints over UDP (packet format: :mod:`ros_free_bridge.sources.udp_packet`).

Binds 127.0.0.1 unless another host is given explicitly. Non-blocking: :meth:`poll`
returns whatever arrived since the last call, so the caller's thread never blocks on
the network. Bad datagrams are dropped and counted, never raised.
"""

from __future__ import annotations

import socket
import time
from dataclasses import dataclass, field

import numpy as np

from ros_free_bridge.errors import BridgeError
from ros_free_bridge.sources import udp_packet as pk


@dataclass(frozen=True)
class ActorFrame:
    """One actor pose as it arrived: positions (22, 3) m and the monotonic arrival second."""

    index: int
    positions: np.ndarray
    arrival: float
    seq: int = -1
    stamp: float = float("nan")


@dataclass
class UdpStats:
    received: int = 0
    accepted: int = 0
    garbage: int = 0
    out_of_order: int = 0
    estops: int = 0
    last_error: str = ""
    errors: dict = field(default_factory=dict)


class UdpActorSource:
    """Receive actor frames (and e-stop requests) on ``host:port`` (port 0: any free port)."""

    live = True  #: frames sent before start() are stale and dropped
    finished = False  #: a live stream ends by a stop request, an e-stop or its watchdog

    def __init__(self, host: str = "127.0.0.1", port: int = 0, on_estop=None):
        self.stats = UdpStats()
        self._on_estop = on_estop
        self._last_seq: int | None = None
        self._index = 0
        try:
            self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self._sock.bind((host, port))
        except OSError as exc:
            raise BridgeError(f"udp actor source: cannot listen on {host}:{port} ({exc.strerror}); pick another port") from None
        self._sock.setblocking(False)
        self.estopped = False

    @property
    def address(self) -> tuple[str, int]:
        return self._sock.getsockname()

    def start(self) -> None:
        """Nothing to start: the socket is already listening."""

    def poll(self, max_packets: int = 1000) -> list[ActorFrame]:
        frames: list[ActorFrame] = []
        for _ in range(max_packets):
            try:
                data = self._sock.recv(2048)
            except BlockingIOError:
                break
            except OSError as exc:
                raise BridgeError(f"udp actor source: socket error ({exc.strerror})") from None
            now = time.monotonic()
            self.stats.received += 1
            try:
                packet = pk.decode(data)
            except pk.PacketError as exc:
                self.stats.garbage += 1
                self.stats.last_error = str(exc)
                continue
            if not pk.is_newer(packet.seq, self._last_seq):
                self.stats.out_of_order += 1
                continue
            self._last_seq = packet.seq
            if isinstance(packet, pk.EStopPacket):
                self.stats.estops += 1
                self.estopped = True
                if self._on_estop is not None:
                    self._on_estop("udp e-stop packet")
                continue
            self.stats.accepted += 1
            frames.append(ActorFrame(self._index, packet.positions, now, packet.seq, packet.stamp))
            self._index += 1
        return frames

    def close(self) -> None:
        self._sock.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
