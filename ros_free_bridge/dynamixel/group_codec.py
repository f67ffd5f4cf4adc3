"""The control loop's hot-path packets, built and read with one ``struct`` call each.

:class:`SyncWriteEncoder` (one SYNC_WRITE of a register to a fixed set of servos),
:class:`FastSyncReadDecoder` (the FAST_SYNC_READ request and the one-unpack read of its
reply) and :class:`FastBulkReadDecoder` (the same for FAST_BULK_READ, each servo its own
span). Their bytes equal dynamixel-sdk's GroupSyncWrite / GroupSyncRead.fastSyncRead /
GroupBulkRead packets (tested); for a 20-servo packet the cost is interpreter steps, not
bytes, so these take few. A malformed reply is a :class:`~.protocol.PacketError` naming
what is wrong.
"""

from __future__ import annotations

import operator
import struct

import numpy as np

from ros_free_bridge.dynamixel.protocol import (
    BROADCAST_ID,
    FAST_BULK_READ,
    FAST_SYNC_READ,
    HEADER2,
    INT_FORMAT,
    STATUS,
    SYNC_WRITE,
    PacketError,
    crc16,
    encode_instruction,
)


class SyncWriteEncoder:
    """The SYNC_WRITE packet of one register (``address``, ``size`` bytes) to the servos
    ``ids``, in that order, built per call from n integers.

    Layout (broadcast ID 0xFE, no reply)::

        FF FF FD 00 FE LEN_L LEN_H 83 ADDR_L ADDR_H SIZE_L SIZE_H {ID DATA[size]} × n CRC_L CRC_H

    The bytes equal dynamixel-sdk's ``GroupSyncWrite.txPacket`` for the same data (tested).
    Values are little-endian two's complement (``signed``) or unsigned; one outside the
    register's size is a :class:`PacketError`. A packet whose data happens to contain
    ``FF FF FD`` is byte-stuffed as the protocol requires (the scalar path); dynamixel-sdk
    4.1.0 sends those unstuffed.

    Per call: one ``struct`` pack of the {ID DATA} pairs behind the fixed 12 header bytes,
    and the CRC (:func:`crc16`, compiled)."""

    def __init__(self, address: int, size: int, ids, signed: bool = True) -> None:
        ids = [int(i) for i in ids]
        if size not in (1, 2, 4):
            raise PacketError(f"SYNC_WRITE data size must be 1, 2 or 4 bytes, got {size}")
        if not ids or any(not 0 <= i <= 252 for i in ids):
            raise PacketError(f"SYNC_WRITE needs servo IDs in 0..252, got {ids}")
        n = len(ids)
        self.address, self.size, self.ids, self.signed = address, size, tuple(ids), signed
        length = 1 + 4 + n * (1 + size) + 2
        self._head = HEADER2 + bytes(
            (BROADCAST_ID, length & 0xFF, length >> 8, SYNC_WRITE, address & 0xFF, address >> 8, size & 0xFF, size >> 8)
        )
        self._pack = struct.Struct("<" + ("B" + INT_FORMAT[size, signed]) * n).pack
        self._args = [x for i in ids for x in (i, 0)]  # ID, value, ID, value, ...; values set per call
        self.n = n

    def encode(self, values) -> bytes:
        """(n,) integers (already range-checked by the caller; a numpy integer array or a
        list of ints) → the packet's bytes."""
        if isinstance(values, np.ndarray):
            if values.shape != (self.n,):
                raise PacketError(f"SYNC_WRITE expects {self.n} values, got shape {values.shape}")
            values = (values if values.dtype.kind in "iu" else values.astype(np.int64)).tolist()
        elif len(values) != self.n:
            raise PacketError(f"SYNC_WRITE expects {self.n} values, got {len(values)}")
        args = self._args
        args[1::2] = values
        try:
            body = self._head + self._pack(*args)
        except struct.error as exc:
            raise PacketError(
                f"SYNC_WRITE value does not fit {self.size} {'signed' if self.signed else 'unsigned'} bytes: {exc}"
            ) from None
        if body.find(b"\xff\xff\xfd", 7) >= 0:
            return encode_instruction(BROADCAST_ID, SYNC_WRITE, body[8:])
        crc = crc16(body)
        return body + bytes((crc & 0xFF, crc >> 8))


class FastSyncReadDecoder:
    """FAST_SYNC_READ of one register for a fixed list of servos: the request bytes and
    the parse of the single reply in one ``struct`` unpack.

    Request: ``FF FF FD 00 FE LEN 8A ADDR_L ADDR_H SIZE_L SIZE_H ID... CRC`` (equal to
    dynamixel-sdk's ``GroupSyncRead.fastSyncRead`` packet; tested). Reply (never
    stuffed; e-Manual, "Fast Sync Read")::

        FF FF FD 00 FE LEN_L LEN_H 55 {ERR ID DATA[size] CRC_L CRC_H} × n

    of ``reply_length`` = 8 + n · (size + 4) bytes. Each servo's CRC covers the packet up
    to its own part, so the last one is the whole packet's CRC; :meth:`decode_fields` checks
    that one (as the SDK does), the IDs and the length, names the
    first broken part when the CRC fails, and reads every part with one ``struct`` unpack."""

    def __init__(self, address: int, size: int, ids, signed: bool = True) -> None:
        ids = [int(i) for i in ids]
        if size not in (1, 2, 4):
            raise PacketError(f"FAST_SYNC_READ data size must be 1, 2 or 4 bytes, got {size}")
        if not ids or any(not 0 <= i <= 252 for i in ids):
            raise PacketError(f"FAST_SYNC_READ needs servo IDs in 0..252, got {ids}")
        n = len(ids)
        self.ids, self.size, self.n = tuple(ids), size, n
        self.request = encode_instruction(
            BROADCAST_ID, FAST_SYNC_READ, bytes((address & 0xFF, address >> 8, size & 0xFF, size >> 8)) + bytes(ids)
        )
        self.reply_length = 8 + n * (size + 4)
        length = self.reply_length - 7
        self.head = HEADER2 + bytes((BROADCAST_ID, length & 0xFF, length >> 8, STATUS))
        starts = 8 + np.arange(n) * (size + 4)
        self._part_ends = starts + 2 + size  # where each part's CRC starts
        # the whole reply in one unpack: (ERR, ID, value) per part, header and CRCs skipped
        self._unpack = struct.Struct("<8x" + ("BB" + INT_FORMAT[size, signed] + "2x") * n).unpack

    def decode_fields(self, raw: bytes) -> tuple[tuple[int, ...], tuple[int, ...]]:
        """One reply → (status error bytes, values), tuples of n ints in ``ids`` order. A
        wrong header, length, ID order or CRC is a :class:`PacketError` naming it."""
        if len(raw) != self.reply_length:
            raise PacketError(
                f"fast-sync-read reply is {len(raw)} bytes, expected {self.reply_length} "
                f"for {self.n} servos of {self.size} bytes"
            )
        if not raw.startswith(self.head):
            raise PacketError(f"fast-sync-read reply header {raw[:8].hex(' ')} is not {self.head.hex(' ')}")
        if crc16(memoryview(raw)[:-2]) != raw[-2] | (raw[-1] << 8):
            raise PacketError(f"fast-sync-read CRC mismatch{self._first_bad_part(raw)}")
        fields = self._unpack(raw)
        if fields[1::3] != self.ids:
            got = fields[1::3]
            k = next(k for k, (g, e) in enumerate(zip(got, self.ids)) if g != e)
            raise PacketError(f"fast-sync-read part {k} carries servo ID {got[k]}, expected {self.ids[k]}")
        return fields[0::3], fields[2::3]

    def decode(self, raw: bytes) -> tuple[np.ndarray, np.ndarray]:
        """One reply → (values (n,) int64, status error bytes (n,) uint8), in ``ids`` order
        (:meth:`decode_fields` as arrays)."""
        errors, values = self.decode_fields(raw)
        return np.array(values, dtype=np.int64), np.array(errors, dtype=np.uint8)

    def _first_bad_part(self, raw: bytes) -> str:
        """Only on a CRC failure: recompute every part's running CRC to name the culprit."""
        for k, end in enumerate(self._part_ends):
            if crc16(raw[:end]) != raw[end] | (raw[end + 1] << 8):
                return f" in the part for servo ID {self.ids[k]}"
        return ""


class FastBulkReadDecoder:
    """FAST_BULK_READ of one span per servo, ``items`` = [(id, address, size)]: the request
    bytes and the one-pass check of its single reply.

    Request (broadcast; equal to dynamixel-sdk's ``GroupBulkRead.fastBulkReadTxPacket``,
    tested)::

        FF FF FD 00 FE LEN_L LEN_H 9A {ID ADDR_L ADDR_H SIZE_L SIZE_H} × n CRC_L CRC_H

    Reply, as for FAST_SYNC_READ but each part of its own size::

        FF FF FD 00 FE LEN_L LEN_H 55 {ERR ID DATA[size_k] CRC_L CRC_H} × n

    ``data_starts[k]``: where item k's data begins in the reply; ``timeout_bytes``: the
    SDK's reply-timeout size for it, Σ (size_k + 10).

    ``fields`` (optional), per item the values :meth:`decode_fields` reads from its data:
    (offset in the item's data, size, signed); sizes 1, 2, 4 give ints, any other size the
    raw bytes. The whole reply is then read with one ``struct`` unpack."""

    def __init__(self, items, fields=None) -> None:
        items = [(int(i), int(a), int(n)) for i, a, n in items]
        if not items or any(not 0 <= i <= 252 or n < 1 for i, _, n in items):
            raise PacketError(f"FAST_BULK_READ needs items (servo ID 0..252, address, size >= 1), got {items}")
        if len({i for i, _, _ in items}) != len(items):
            raise PacketError(f"FAST_BULK_READ lists a servo twice: {[i for i, _, _ in items]}")
        self.items = tuple(items)
        self.ids = tuple(i for i, _, _ in items)
        self.n = len(items)
        params = b"".join(bytes((i, a & 0xFF, a >> 8, n & 0xFF, n >> 8)) for i, a, n in items)
        self.request = encode_instruction(BROADCAST_ID, FAST_BULK_READ, params)
        sizes = np.array([n for _, _, n in items])
        self.reply_length = 8 + int((sizes + 4).sum())
        length = self.reply_length - 7
        self.head = HEADER2 + bytes((BROADCAST_ID, length & 0xFF, length >> 8, STATUS))
        starts = 8 + np.concatenate(([0], np.cumsum(sizes + 4)[:-1])).astype(np.int64)
        self.data_starts = starts + 2
        self._err_index = starts
        self._id_index = starts + 1
        self._part_ends = starts + 2 + sizes
        self._id_bytes = np.array(self.ids, dtype=np.uint8)
        self.timeout_bytes = int((sizes + 10).sum())
        self._unpack = None
        if fields is not None:
            self._make_unpack([list(f) for f in fields])

    def _make_unpack(self, fields) -> None:
        """One ``struct`` format for the whole reply, and where each kind of value lands in
        its result: ERR bytes, IDs, then every item's fields in order."""
        if len(fields) != self.n:
            raise PacketError(f"FAST_BULK_READ fields: {len(fields)} lists for {self.n} items")
        fmt, at, err_at, id_at, field_at = ["<8x"], 0, [], [], []
        for (sid, _, size), item_fields in zip(self.items, fields):
            fmt.append("BB")
            err_at.append(at)
            id_at.append(at + 1)
            at += 2
            pos = 0
            for offset, fsize, signed in sorted(item_fields):
                if offset < pos or offset + fsize > size:
                    raise PacketError(
                        f"FAST_BULK_READ fields of servo ID {sid}: ({offset}, {fsize}) overlaps "
                        f"another or leaves its {size} data bytes"
                    )
                if offset > pos:
                    fmt.append(f"{offset - pos}x")
                fmt.append(INT_FORMAT.get((fsize, bool(signed)), f"{fsize}s"))
                field_at.append(at)
                at += 1
                pos = offset + fsize
            fmt.append(f"{size - pos + 2}x")  # the rest of the data and the part's CRC
        unpack = struct.Struct("".join(fmt)).unpack
        take = [
            operator.itemgetter(*idx) if len(idx) > 1 else (lambda t, i=idx[0]: (t[i],))
            for idx in (err_at, id_at, field_at)
        ]
        self._unpack = (unpack, *take)

    def decode_fields(self, raw: bytes) -> tuple[tuple[int, ...], tuple]:
        """One reply → (status error bytes per item, the ``fields`` values: item by item,
        each item's in offset order), as tuples. The checks of :meth:`decode` (length,
        header, CRC, IDs), each a :class:`PacketError` naming what is wrong."""
        if self._unpack is None:
            raise PacketError("FastBulkReadDecoder.decode_fields needs the decoder built with fields=")
        if len(raw) != self.reply_length:
            raise PacketError(
                f"fast-bulk-read reply is {len(raw)} bytes, expected {self.reply_length} for {self.n} servos"
            )
        if not raw.startswith(self.head):
            raise PacketError(f"fast-bulk-read reply header {raw[:8].hex(' ')} is not {self.head.hex(' ')}")
        if crc16(memoryview(raw)[:-2]) != raw[-2] | (raw[-1] << 8):
            self.decode(raw)  # names the broken part
            raise PacketError("fast-bulk-read CRC mismatch")
        unpack, errors, ids, values = self._unpack
        out = unpack(raw)
        if ids(out) != self.ids:
            self.decode(raw)  # names the part
            raise PacketError("fast-bulk-read reply carries the wrong servo IDs")
        return errors(out), values(out)

    def decode(self, raw: bytes) -> tuple[np.ndarray, np.ndarray]:
        """One reply → (its bytes as a (reply_length,) uint8 array, status error bytes (n,)
        in ``items`` order). A wrong length, header, CRC or ID is a :class:`PacketError`."""
        if len(raw) != self.reply_length:
            raise PacketError(
                f"fast-bulk-read reply is {len(raw)} bytes, expected {self.reply_length} for {self.n} servos"
            )
        if raw[:8] != self.head:
            raise PacketError(f"fast-bulk-read reply header {raw[:8].hex(' ')} is not {self.head.hex(' ')}")
        a = np.frombuffer(raw, dtype=np.uint8)
        if crc16(memoryview(raw)[:-2]) != raw[-2] | (raw[-1] << 8):
            bad = next(
                (
                    self.ids[k]
                    for k, end in enumerate(self._part_ends)
                    if crc16(raw[:end]) != raw[end] | (raw[end + 1] << 8)
                ),
                None,
            )
            raise PacketError(
                "fast-bulk-read CRC mismatch" + ("" if bad is None else f" in the part for servo ID {bad}")
            )
        got = a[self._id_index]
        if not np.array_equal(got, self._id_bytes):
            k = int(np.flatnonzero(got != self._id_bytes)[0])
            raise PacketError(f"fast-bulk-read part {k} carries servo ID {got[k]}, expected {self.ids[k]}")
        return a, a[self._err_index]
