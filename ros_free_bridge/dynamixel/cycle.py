"""The bus cycle: goals out, positions (and one servo's status block) in, blocking or split.

:class:`BusCycle` owns the hot-path packets of one bus (:mod:`.group_codec`): the
SYNC_WRITE of Goal Position, the FAST_SYNC_READ of Present Position (the SDK's
GroupSyncRead where the servos lack it), and per status servo j a FAST_BULK_READ of every
position plus j's status block. Blocking: :meth:`BusCycle.read_positions` /
:meth:`BusCycle.read_slow`. Split phase: :meth:`BusCycle.send_cycle` writes the goals and
the read request in one write and leaves the reply on the wire (``pending``);
:meth:`BusCycle.settle`, hooked to the bus's ``before_io``, collects it before anything
else is sent (the bus is half duplex) into ``fast_ready`` / ``slow_ready`` /
``bulk_status``; :meth:`BusCycle.take_arrived` is the one-pass read of a reply that has
fully arrived. Raw values only: units, alerts and the state are the transport's job.
"""

from __future__ import annotations

import operator
import time

import dynamixel_sdk as sdk
import numpy as np

from firmware_cfg.servo_models import Register
from ros_free_bridge.dynamixel.bus import DynamixelBus
from ros_free_bridge.dynamixel.group_codec import FastBulkReadDecoder, FastSyncReadDecoder, SyncWriteEncoder
from ros_free_bridge.dynamixel.protocol import PacketError
from ros_free_bridge.dynamixel.servos import Servo, ServoSet
from ros_free_bridge.errors import BridgeError


def tx_op(port, packet: bytes) -> int:
    """Send one instruction packet through the SDK's port as its ``txPacket`` does (busy
    flag, ``writePort``); no reply is awaited. Unlike ``txPacket`` it does not call
    ``clearPort`` first: that is pyserial's ``flush`` (tcdrain), which on a USB adapter
    blocks until the previous packet has left the wire (0.57 ms for a 20-servo SYNC_WRITE
    at 2 Mbit/s), and the UART keeps the packets' order anyway."""
    if port.is_using:
        return sdk.COMM_PORT_BUSY
    port.is_using = True
    return sdk.COMM_SUCCESS if port.writePort(packet) == len(packet) else sdk.COMM_TX_FAIL


def status_registers(sv: Servo) -> dict[str, Register]:
    """The registers of servo ``sv``'s status block by field (current or load, velocity,
    voltage, temperature, and the bus watchdog when it is armed)."""
    m = sv.model
    regs = {}
    for key, names in (
        ("current", ("present_current", "present_load")),
        ("velocity", ("present_velocity", "present_speed")),
        ("voltage", ("present_input_voltage", "present_voltage")),
        ("temperature", ("present_temperature",)),
    ):
        for name in names:
            if m.has(name):
                regs[key] = m.register(name)
                break
    if sv.settings.get("bus_watchdog", 0) > 0:
        regs["watchdog"] = m.register("bus_watchdog")  # same READ, from address 98 on
    return regs


class BusCycle:
    """The packets and the split-phase bookkeeping of one bus (module docstring). ``imu``:
    the bus's :class:`~ros_free_bridge.dynamixel.imu.ImuDevice`, whose split-phase READ is
    one more kind of pending reply; ``stats``: the transport's counters."""

    def __init__(self, bus: DynamixelBus, servos: ServoSet, stats, imu=None) -> None:
        self.bus, self.servos, self.stats, self.imu = bus, servos, stats, imu
        n = len(servos)
        self.writer: SyncWriteEncoder | None = None
        self.fast: FastSyncReadDecoder | None = None
        self.reader = None  # SDK GroupSyncRead: the SYNC_READ fallback (protocol 2.0)
        self._sync_op = None
        self.fast_values: tuple[int, ...] = (0,) * n  # ticks of the last fast reply
        self.fast_errors: tuple[int, ...] = (0,) * n  # its status error bytes
        #: a reply still on the wire: ("fast", -1), ("bulk", status servo j), ("slow", servo i) or ("imu", -1)
        self.pending: tuple[str, int] | None = None
        self.fast_sent = 0.0  # monotonic second the pending position read request left
        self.fast_ready: tuple[int, float] | None = None  # (COMM code, request time) of a collected fast read
        self.slow_ready: tuple[int, list, int, int] | None = None  # (servo index, data, COMM code, error byte)
        self.bulk_status: tuple[int, dict, int] | None = None  # (servo index, status values by field, error byte)
        # per status servo j: (FAST_BULK_READ of all positions + j's status block, getter of the
        # positions among its decoded values, (field, index, Register) of j's status registers)
        self.bulk: list[tuple[FastBulkReadDecoder, operator.itemgetter, tuple]] | None = None
        self.bulk_refused = False  # the servos did not answer FAST_BULK_READ
        self.slow_next = 0  # the next status servo, round robin
        self._slow_blocks: dict[int, tuple[dict[str, Register], int, int]] = {}
        self._rx_carry = b""  # reply bytes take_arrived read but left to the general path

    def reset(self) -> None:
        """Forget every reply in flight (the port closed)."""
        self.pending = self.fast_ready = self.slow_ready = self.bulk_status = None
        self._rx_carry = b""
        if self.imu is not None:
            self.imu.reset()

    def next_status_servo(self) -> int:
        i = self.slow_next
        self.slow_next = (i + 1) % len(self.servos)
        return i

    # ------------------------------------------------------------------ set-up
    def make_groups(self) -> None:
        """Protocol 2.0: the hot path's SYNC_WRITE encoder and FAST_SYNC_READ decoder (ours;
        the same bytes as the SDK's groups), and the SDK's GroupSyncRead for buses
        whose servos do not answer FAST_SYNC_READ (firmware < v45 on X series)."""
        if self.bus.protocol != 2.0:
            return
        first, ids = self.servos.servos[0], self.servos.ids
        self.writer = SyncWriteEncoder(first.goal.address, first.goal.size, ids, first.goal.signed)
        self.fast = FastSyncReadDecoder(first.present.address, first.present.size, ids, first.present.signed)
        self.reader = sdk.GroupSyncRead(self.bus.port, self.bus.ph, first.present.address, first.present.size)
        for sid in ids:
            self.reader.addParam(sid)
        reader = self.reader
        self._sync_op = lambda port: reader.txRxPacket()
        # decide once whether the servos answer FAST_SYNC_READ
        if self.bus.call(self.fast_read_op) != sdk.COMM_SUCCESS:
            if self.bus.call(self._sync_op, malformed=sdk.COMM_RX_CORRUPT) == sdk.COMM_SUCCESS:
                self.stats.fast_sync_read = False
                self.stats.notes.append("servos did not answer FAST_SYNC_READ; using SYNC_READ")

    def make_bulk(self) -> None:
        """Build the FAST_BULK_READ of every position + servo j's status block, for each j,
        and check once that the servos answer it (firmware without FAST_BULK_READ: keep the
        FAST_SYNC_READ and a separate status READ). Each decoder reads, in one unpack, every
        servo's Present Position and servo j's status registers (``decode_fields``)."""
        self.bulk = [self._bulk_for(j) for j in range(len(self.servos))]

        def probe(port) -> int:
            result = self._bulk_send_op(port, 0)
            return self._bulk_collect_op(port, 0) if result == sdk.COMM_SUCCESS else result

        for _ in range(self.bus.retries + 1):
            if self.bus.call(probe, malformed=sdk.COMM_RX_CORRUPT) == sdk.COMM_SUCCESS:
                self.bulk_status = None  # a probe, not a status reading to act on
                return
        self.bulk, self.bulk_refused = None, True
        self.stats.notes.append("servos did not answer FAST_BULK_READ; split phase uses FAST_SYNC_READ + a status READ")

    def _bulk_for(self, j: int) -> tuple[FastBulkReadDecoder, operator.itemgetter, tuple]:
        """Status servo j's FAST_BULK_READ decoder, the getter of every position among its
        decoded values, and (field, index, Register) of j's status registers there."""
        servos = self.servos.servos
        pres = servos[0].present
        regs, start, length = self.slow_block(j)
        b0, b1 = min(start, pres.address), max(start + length, pres.end)  # j's span holds its position too
        # j's fields, by offset in its span: its status registers and its position; a
        # sign-magnitude register is read unsigned and decoded by its Register
        span = sorted(
            [(r.address - b0, r.size, r.signed and r.sign_bit is None, key) for key, r in regs.items()]
            + [(pres.address - b0, pres.size, pres.signed, "position")]
        )
        fields = [[(0, pres.size, pres.signed)] if k != j else [f[:3] for f in span] for k in range(len(servos))]
        dec = FastBulkReadDecoder(
            [
                (sv.cfg.id, b0, b1 - b0) if k == j else (sv.cfg.id, pres.address, pres.size)
                for k, sv in enumerate(servos)
            ],
            fields,
        )
        keys = [f[3] for f in span]
        at_j = j + keys.index("position")  # where j's position lands among the decoded values
        pos = [k if k < j else at_j if k == j else k + len(span) - 1 for k in range(len(servos))]
        status = [(key, j + m, regs[key]) for m, key in enumerate(keys) if key != "position"]
        return dec, operator.itemgetter(*pos), tuple(status)

    # ------------------------------------------------------------------ fast reads
    def fast_read_op(self, port) -> int:
        """One FAST_SYNC_READ of Present Position, blocking. Returns an SDK COMM_* code."""
        result = self._fast_send_op(port)
        if result != sdk.COMM_SUCCESS:
            return result
        return self._fast_collect_op(port)

    def _fast_send_op(self, port) -> int:
        """Send the prebuilt FAST_SYNC_READ request and start the SDK's sync-read timeout.
        Stale input (a reply that came after an earlier timeout) is discarded first, so it
        cannot be taken for this one's."""
        if port.is_using:
            return sdk.COMM_PORT_BUSY
        port.discardInput()
        self._rx_carry = b""
        result = tx_op(port, self.fast.request)
        if result == sdk.COMM_SUCCESS:
            port.setPacketTimeout((11 + self.fast.size) * self.fast.n)  # the SDK's sync-read timeout
        return result

    def _fast_collect_op(self, port) -> int:
        """Collect the FAST_SYNC_READ reply into ``fast_values`` / ``fast_errors``."""
        result, buf = self._collect_reply(port, self.fast.reply_length, self.fast.head)
        if result != sdk.COMM_SUCCESS:
            return result
        try:
            self.fast_errors, self.fast_values = self.fast.decode_fields(buf)
        except PacketError:
            return sdk.COMM_RX_CORRUPT
        return sdk.COMM_SUCCESS

    def _collect_reply(self, port, need: int, head: bytes) -> tuple[int, bytes]:
        """(COMM code, the reply's ``need`` bytes) read through ``port.readPort`` (which
        sleeps while the reply is on the wire) until the packet timeout, after any bytes
        :meth:`take_arrived` already took; bytes before the header are skipped (resync)."""
        head = head[:5]
        buf, self._rx_carry = self._rx_carry, b""
        while True:
            if buf and not buf.startswith(head):  # garbage before the header: resync
                at = buf.find(head)
                buf = buf[at:] if at >= 0 else buf[-4:]
            if len(buf) >= need:
                return sdk.COMM_SUCCESS, buf[:need]
            chunk = port.readPort(need - len(buf))
            if chunk:
                buf += chunk
            elif port.isPacketTimeout():
                return (sdk.COMM_RX_TIMEOUT if not buf else sdk.COMM_RX_CORRUPT), buf

    def _bulk_send_op(self, port, j: int) -> int:
        """Send servo j's FAST_BULK_READ, start the SDK's bulk-read timeout."""
        if port.is_using:
            return sdk.COMM_PORT_BUSY
        port.discardInput()
        self._rx_carry = b""
        dec = self.bulk[j][0]
        result = tx_op(port, dec.request)
        if result == sdk.COMM_SUCCESS:
            port.setPacketTimeout(dec.timeout_bytes)
        return result

    def _bulk_collect_op(self, port, j: int) -> int:
        """Collect servo j's FAST_BULK_READ reply: every position into ``fast_values`` /
        ``fast_errors`` (as a fast sync read), j's status registers into ``bulk_status``."""
        dec, positions, status = self.bulk[j]
        result, buf = self._collect_reply(port, dec.reply_length, dec.head)
        if result != sdk.COMM_SUCCESS:
            return result
        try:
            errors, values = dec.decode_fields(buf)
        except PacketError:
            return sdk.COMM_RX_CORRUPT
        self.fast_values = positions(values) if len(errors) > 1 else (positions(values),)
        self.fast_errors = errors
        self.bulk_status = (j, status_values(status, values), errors[j])
        return sdk.COMM_SUCCESS

    # ------------------------------------------------------------------ blocking reads
    def read_positions(self) -> tuple[object, str, object]:
        """Every servo's Present Position, blocking, with bounded retries (then a BridgeError
        naming the silent servo). Returns (ticks, kind, errors): kind "p1" (servo by servo,
        ``errors`` their status bytes), "fast" (``errors`` the fast reply's status bytes)
        or "sync" (the SDK's SYNC_READ, no status bytes: None)."""
        out = self._read_positions()
        self.fast_ready = None  # a split-phase reply collected meanwhile is older than this
        return out

    def _read_positions(self) -> tuple[object, str, object]:
        if self.reader is None:
            ticks, errors = np.empty(len(self.servos)), []
            for i, sv in enumerate(self.servos.servos):
                ticks[i], error = self.bus.read(sv.cfg.id, sv.present)
                errors.append(error)
            return ticks, "p1", errors
        fast = self.stats.fast_sync_read
        op = self.fast_read_op if fast else self._sync_op
        result = sdk.COMM_TX_FAIL
        for _ in range(self.bus.retries + 1):
            result = self.bus.call(op, malformed=sdk.COMM_RX_CORRUPT)
            if result == sdk.COMM_SUCCESS:
                break
            self.stats.read_retries += 1
        if result != sdk.COMM_SUCCESS:
            self.raise_missing("present position", result)
        if fast:
            return self.fast_values, "fast", self.fast_errors
        reg = self.servos.servos[0].present
        ticks = np.array([self.reader.getData(sid, reg.address, reg.size) for sid in self.servos.ids], dtype=np.int64)
        if reg.signed:
            ticks[ticks >= 1 << (8 * reg.size - 1)] -= 1 << (8 * reg.size)
        return ticks, "sync", None

    def raise_missing(self, what: str, result: int) -> None:
        """A group read failed: find which servo is silent, to name it."""
        for sid in self.servos.ids:
            try:
                self.bus.ping(sid, retries=0)
            except BridgeError:
                raise BridgeError(
                    f"{self.bus.label(sid)}: no status packet for {what} after "
                    f"{self.bus.retries + 1} tries; check its cable and power"
                ) from None
        raise BridgeError(
            f"Dynamixel bus {self.bus.port_name}: group read of {what} failed after "
            f"{self.bus.retries + 1} tries ({self.bus.comm_text(result)}), though every servo answers PING; "
            "check for noise or a wrong baud rate"
        )

    def slow_block(self, i: int) -> tuple[dict[str, Register], int, int]:
        """(registers by field, start address, length) of servo ``i``'s status block."""
        block = self._slow_blocks.get(i)
        if block is None:
            regs = status_registers(self.servos.servos[i])
            start = min(r.address for r in regs.values())
            block = self._slow_blocks[i] = (regs, start, max(r.end for r in regs.values()) - start)
        return block

    def read_slow(self, i: int) -> tuple[bytes, int]:
        """Servo ``i``'s status block (bytes from its start) and status error byte, blocking."""
        _, start, length = self.slow_block(i)
        return self.bus.read_raw(self.servos.ids[i], start, length, "status block")

    def decode_slow(self, i: int, data: bytes) -> dict[str, int]:
        """Servo ``i``'s status block bytes → raw values by field."""
        regs, start, _ = self.slow_block(i)
        return {k: r.decode(data[r.address - start : r.end - start]) for k, r in regs.items()}

    # ------------------------------------------------------------------ writes and split phase
    def send_goals(self, ticks) -> None:
        """One SYNC_WRITE of Goal Position ``ticks`` (n,), no reply."""
        if self.writer is None:  # protocol 1.0: SYNC_WRITE exists there too
            first = self.servos.servos[0]
            self.bus.sync_write(first.goal, dict(zip(self.servos.ids, np.asarray(ticks).tolist())))
            return
        result = self.bus.call(tx_op, self.writer.encode(ticks))
        if result != sdk.COMM_SUCCESS:
            raise BridgeError(
                f"Dynamixel bus {self.bus.port_name}: SYNC_WRITE goal position failed ({self.bus.comm_text(result)})"
            )

    def send_cycle(self, ticks) -> None:
        """Split phase: the SYNC_WRITE of ``ticks`` and, right behind it in the same write,
        the position read request (the FAST_BULK_READ carrying the next servo's status
        block, else the FAST_SYNC_READ), whose reply is left on the wire (collected by
        :meth:`settle`). One system call and one wake-up of the other end per cycle; the
        reply timeout counts the SYNC_WRITE's bytes too. A failed write is a BridgeError."""
        goals = self.writer.encode(ticks)
        if self.bulk is not None:
            j = self.next_status_servo()
            dec = self.bulk[j][0]
            request, timeout_bytes, pending = dec.request, dec.timeout_bytes, ("bulk", j)
        else:
            fast = self.fast
            request, timeout_bytes, pending = fast.request, (11 + fast.size) * fast.n, ("fast", -1)
        packets = goals + request

        def op(port) -> int:
            if port.is_using:
                return sdk.COMM_PORT_BUSY
            port.discardInput()  # stale input cannot be taken for this reply
            self._rx_carry = b""
            port.is_using = True
            if port.writePort(packets) != len(packets):
                return sdk.COMM_TX_FAIL
            port.setPacketTimeout(len(goals) + timeout_bytes)
            return sdk.COMM_SUCCESS

        result = self.bus.call(op)
        if result != sdk.COMM_SUCCESS:
            raise BridgeError(
                f"Dynamixel bus {self.bus.port_name}: SYNC_WRITE goal position + read request failed "
                f"({self.bus.comm_text(result)})"
            )
        self.fast_sent = time.monotonic()
        self._leave_pending(pending)

    def send_slow(self, i: int) -> bool:
        """Split phase: send servo ``i``'s status-block READ, leave its reply on the wire;
        False when the request could not be sent (read it the blocking way then)."""
        _, start, length = self.slow_block(i)
        sid, ph = self.servos.ids[i], self.bus.ph

        def op(port) -> int:
            port.discardInput()
            self._rx_carry = b""
            return ph.readTx(port, sid, start, length)

        if self.bus.call(op) != sdk.COMM_SUCCESS:
            return False
        self._leave_pending(("slow", i))
        return True

    def send_imu(self) -> None:
        """Split phase: the IMU device's READ, its reply left on the wire."""
        self._rx_carry = b""
        if self.imu.send():
            self._leave_pending(("imu", -1))

    def _leave_pending(self, pending: tuple[str, int]) -> None:
        self.pending = pending
        self.bus.before_io = self.settle

    def settle(self) -> None:
        """Collect the reply of the split-phase request still on the wire, if any, into
        ``fast_ready`` / ``slow_ready`` / ``bulk_status`` (the IMU's into the device). Waits
        only for bytes not yet arrived, at most until the request's reply timeout. Never
        raises for a missing or garbled reply (that is recorded as the COMM code); a dead
        port raises."""
        pending, self.pending = self.pending, None
        self.bus.before_io = None
        if pending is None:
            return
        kind, i = pending
        if kind == "imu":
            self.imu.collect()  # its misses are the IMU's own count, not the servos' read retries
            return
        if kind == "fast":
            result = self.bus.call(self._fast_collect_op, malformed=sdk.COMM_RX_CORRUPT)
            self.fast_ready = (result, self.fast_sent)
        elif kind == "bulk":
            result = self.bus.call(lambda port: self._bulk_collect_op(port, i), malformed=sdk.COMM_RX_CORRUPT)
            self.fast_ready = (result, self.fast_sent)
        else:
            _, _, length = self.slow_block(i)
            data, result, error = self.bus.call(
                self.bus.ph.readRx, self.servos.ids[i], length, malformed=([], sdk.COMM_RX_CORRUPT, 0)
            )
            self.slow_ready = (i, data, result, error)
        if result != sdk.COMM_SUCCESS:
            self.stats.read_retries += 1  # counted here: a newer request may supersede it before it is used

    def take_arrived(self) -> tuple | None:
        """The one-pass read of the pending position request's reply: when it has fully
        arrived, is valid (length, header, CRC, IDs) and carries no status error bit,
        returns (position ticks, (status servo j, its raw status values) or None) and
        clears ``pending``. Anything else - bytes still on the wire, a corrupt reply, an
        error bit - returns None with the bytes read kept for the general path, which then
        proceeds as if it had read them itself (waits, retries, alerts)."""
        if self.fast_ready is not None or self.slow_ready is not None or self.bulk_status is not None:
            return None
        j = self.pending[1]
        dec, positions, status = self.bulk[j] if j >= 0 else (self.fast, None, None)
        try:
            raw = self.bus.port._read_now(dec.reply_length)
        except OSError:
            return None  # the general path reads again and reports the port's failure
        try:
            errors, values = dec.decode_fields(raw)
        except PacketError:
            self._rx_carry = raw
            return None
        if any(errors):
            self._rx_carry = raw
            return None
        self.pending = None
        self.bus.before_io = None
        if positions is None:
            return values, None
        ticks = positions(values) if len(errors) > 1 else (positions(values),)
        return ticks, (j, status_values(status, values))


def status_values(status: tuple, values: tuple) -> dict[str, int]:
    """Servo j's status registers by field from a decoded FAST_BULK_READ reply ((field,
    index in ``values``, Register) per register); a sign-magnitude register was read
    unsigned and is decoded here."""
    return {
        key: values[at] if reg.sign_bit is None else reg.decode(values[at].to_bytes(reg.size, "little"))
        for key, at, reg in status
    }
