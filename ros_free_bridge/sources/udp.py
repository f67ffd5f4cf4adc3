"""Live actor joints over UDP (packet format: :mod:`ros_free_bridge.sources.udp_packet`).

Binds 127.0.0.1; another address needs ``allow_remote`` (and the CLI warns). Non-blocking:
:meth:`poll` returns whatever arrived since the last call (up to a budget), so the caller's
thread never blocks on the network. Bad datagrams are dropped and counted by kind
(:class:`UdpStats`), never raised.
"""

from __future__ import annotations

import ipaddress
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


#: The drop counters, by kind, in the order reports list them.
DROP_KINDS = ("garbage", "out_of_range", "out_of_order", "seq_jump", "foreign")


@dataclass
class UdpStats:
    """What the source received and what it dropped, by kind:

    - ``garbage``: not a version-1 packet (size, magic, version, type);
    - ``out_of_range``: a NaN/inf timestamp or position, or a joint beyond 10 m;
    - ``out_of_order``: a sequence number not newer than the last accepted (stale, duplicate);
    - ``seq_jump``: a sequence number more than ``udp_packet.MAX_SEQ_JUMP`` ahead (forged);
    - ``foreign``: a frame from another sender while the locked sender streams.

    ``flooded``: polls that hit their packet budget with more waiting (a flood: the rest stays
    in the socket's buffer, whose overflow the kernel drops). ``senders``: times the source
    locked onto a sender (the first, a restart, a new sender after a silence)."""

    received: int = 0
    accepted: int = 0
    garbage: int = 0
    out_of_range: int = 0
    out_of_order: int = 0
    seq_jump: int = 0
    foreign: int = 0
    estops: int = 0
    flooded: int = 0
    senders: int = 0
    last_error: str = ""
    errors: dict = field(default_factory=dict)

    def drops(self) -> dict[str, int]:
        """The drop counters by kind (DROP_KINDS order), zeros included."""
        return {k: getattr(self, k) for k in DROP_KINDS}

    @property
    def dropped(self) -> int:
        return sum(self.drops().values())

    def describe(self) -> str:
        """e.g. "3 dropped (garbage 2, out_of_order 1)", or "none dropped"."""
        nonzero = [f"{k} {v}" for k, v in self.drops().items() if v]
        return f"{self.dropped} dropped ({', '.join(nonzero)})" if nonzero else "none dropped"


def is_loopback(host: str) -> bool:
    """Whether ``host`` (an address or a name) is this machine's loopback interface."""
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        pass
    try:
        return all(
            ipaddress.ip_address(info[4][0]).is_loopback
            for info in socket.getaddrinfo(host, None, socket.AF_INET, socket.SOCK_DGRAM)
        )
    except (OSError, ValueError):
        return False


class UdpActorSource:
    """Receive actor frames (and e-stop requests) on ``host:port`` (port 0: any free port).

    One sender drives the robot at a time. The first valid frame locks the source onto its
    sender (address and stream id); while that sender streams, frames from any other address
    are dropped (``foreign``). A restarted sender is recognised from its own fields: the same
    address with a new stream id, or any sender once the locked one has been silent for
    ``takeover_s`` (a restart that also changed its port). A higher sequence number alone
    never is: a frame more than ``udp_packet.MAX_SEQ_JUMP`` ahead is dropped (``seq_jump``),
    so one forged packet cannot make the genuine frames stale. E-stop packets are honoured
    from any sender. Each :meth:`poll` reads at most ``max_packets`` datagrams, so a flood
    costs bounded work per poll. ``on_event(kind, **info)`` receives ``udp_sender`` when the
    lock changes and ``udp_drops`` (the counters by kind) when a drop of a new kind happens,
    then at most every ``report_every_s``.

    Binding anything but a loopback address needs ``allow_remote=True`` (CLI:
    ``--allow-remote-actor``): any host that reaches the port can then move the robot.
    """

    live = True  #: frames sent before start() are stale and dropped
    finished = False  #: a live stream ends by a stop request, an e-stop or its watchdog

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 0,
        on_estop=None,
        *,
        allow_remote: bool = False,
        on_event=None,
        takeover_s: float = 0.5,
        max_packets: int = 256,
        report_every_s: float = 1.0,
    ):
        self.stats = UdpStats()
        self._on_estop = on_estop
        self.on_event = on_event
        self.takeover_s = float(takeover_s)
        self.max_packets = int(max_packets)
        self.report_every_s = float(report_every_s)
        self.remote = not is_loopback(host)
        if self.remote and not allow_remote:
            raise BridgeError(
                f"udp actor source: {host} is not a loopback address; any host that can reach it could "
                "move the robot. Use udp://127.0.0.1:PORT, or pass --allow-remote-actor to listen there "
                "on purpose (on a trusted network only)"
            )
        self._last_seq: int | None = None
        self._sender: tuple | None = None  # (address, stream id) the source is locked onto
        self._last_accept = float("-inf")
        self._index = 0
        self._reported: dict[str, int] = {}
        self._report_at = 0.0
        try:
            self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self._sock.bind((host, port))
        except OSError as exc:
            raise BridgeError(
                f"udp actor source: cannot listen on {host}:{port} ({exc.strerror}); pick another port"
            ) from None
        self._sock.setblocking(False)
        self.estopped = False

    @property
    def address(self) -> tuple[str, int]:
        return self._sock.getsockname()

    def start(self) -> None:
        """Nothing to start: the socket is already listening."""

    def _drop(self, kind: str, error: str = "") -> None:
        setattr(self.stats, kind, getattr(self.stats, kind) + 1)
        if error:
            self.stats.last_error = error

    def _estop(self) -> None:
        self.stats.estops += 1
        self.estopped = True
        if self._on_estop is not None:
            self._on_estop("udp e-stop packet")

    def _lock(self, addr, stream: int, why: str) -> None:
        self._sender = (addr, stream)
        self._last_seq = None
        self.stats.senders += 1
        if self.on_event is not None:
            self.on_event("udp_sender", address=f"{addr[0]}:{addr[1]}", stream=stream, why=why)

    def poll(self, max_packets: int | None = None) -> list[ActorFrame]:
        frames: list[ActorFrame] = []
        budget = self.max_packets if max_packets is None else int(max_packets)
        for _ in range(budget):
            try:
                data, addr = self._sock.recvfrom(2048)
            except BlockingIOError:
                break
            except OSError as exc:
                raise BridgeError(f"udp actor source: socket error ({exc.strerror})") from None
            now = time.monotonic()
            self.stats.received += 1
            locked = self._sender is not None and now - self._last_accept <= self.takeover_s
            if locked and addr != self._sender[0] and not (len(data) == pk.ESTOP_SIZE and data[5:6] == b"\x02"):
                self._drop("foreign")  # another sender while the locked one streams: not even decoded
                continue
            try:
                packet = pk.decode(data)
            except pk.PacketError as exc:
                self._drop(exc.kind, str(exc))
                continue
            if isinstance(packet, pk.EStopPacket):
                self._estop()  # from anyone: stopping is always allowed
                continue
            if not locked:
                self._lock(
                    addr,
                    packet.stream,
                    "first sender"
                    if self._sender is None
                    else f"the previous sender was silent for more than {self.takeover_s:g} s",
                )
            elif packet.stream != self._sender[1]:
                self._lock(addr, packet.stream, "the sender restarted (new stream id)")
            elif self._last_seq is not None:
                if not pk.is_newer(packet.seq, self._last_seq):
                    self._drop("out_of_order")
                    continue
                if (packet.seq - self._last_seq) & 0xFFFFFFFF > pk.MAX_SEQ_JUMP:
                    self._drop("seq_jump", f"sequence jumped from {self._last_seq} to {packet.seq}")
                    continue
            self._last_seq = packet.seq
            self._last_accept = now
            self.stats.accepted += 1
            frames.append(ActorFrame(self._index, packet.positions, now, packet.seq, packet.stamp))
            self._index += 1
        else:
            self.stats.flooded += 1
        self._report()
        return frames

    def _report(self) -> None:
        """A ``udp_drops`` event when a new kind of drop appeared, else at most every report_every_s."""
        if self.on_event is None:
            return
        drops = self.stats.drops()
        if drops == self._reported and self.stats.flooded == self._reported.get("flooded", 0):
            return
        now = time.monotonic()
        new_kind = any(v and not self._reported.get(k) for k, v in drops.items())
        if new_kind or now - self._report_at >= self.report_every_s:
            self._reported = {**drops, "flooded": self.stats.flooded}
            self._report_at = now
            self.on_event("udp_drops", **self._reported, received=self.stats.received, accepted=self.stats.accepted)

    def close(self) -> None:
        self._sock.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
