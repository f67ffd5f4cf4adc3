"""The Dynamixel hot path's fast forms equal the general ones: the SYNC_WRITE packets (against
dynamixel-sdk's bytes), the struct-read fast replies (against dynamixel-sdk's own parsing), the
per-element goal ticks and positions, and the split-phase tick read in one pass
(``_read_arrived``) against the general path, on the byte-level emulator."""

from __future__ import annotations

import math

import numpy as np
import pytest
import test_dxl_pipeline
from dynamixel_sdk import GroupBulkRead, PacketHandler, PortHandler
from hypothesis import given, settings
from hypothesis import strategies as st
from test_dxl_codec import CapturePort, sdk_sync_write  # tests/ is on sys.path (pytest, prepend mode)
from test_dxl_transport import XM, make, wait_for

from firmware_cfg.config import load_config, robot_config_path
from ros_free_bridge.dynamixel import protocol as dp
from ros_free_bridge.dynamixel.group_codec import FastBulkReadDecoder, FastSyncReadDecoder, SyncWriteEncoder
from ros_free_bridge.dynamixel.protocol import PacketError, crc16
from ros_free_bridge.dynamixel.transport import DynamixelTransport
from ros_free_bridge.errors import BridgeError

IDS = list(range(1, 21))


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(-5000, 9000), min_size=20, max_size=20))
def test_sync_write_of_signed_goals_equals_the_sdk_packet(values):
    """Goal Position is a signed 4-byte register: negative ticks and ticks past one turn
    are the SDK's packet byte for byte (values here never form FF FF FD, which the SDK would
    leave unstuffed), from a list or an integer array."""
    port = CapturePort()
    sdk_sync_write(port, 116, 4, IDS, values)
    enc = SyncWriteEncoder(116, 4, IDS)
    assert enc.encode(values) == port.sent[-1] == enc.encode(np.array(values))


def test_sync_write_refuses_values_that_do_not_fit_and_wrong_counts():
    enc = SyncWriteEncoder(102, 2, [1, 2, 3])
    for v in ([-885, 0, 885], [-32768, 32767, 0]):
        raw = enc.encode(v)
        assert crc16(raw[:-2]) == raw[-2] | (raw[-1] << 8)
        assert dp.decode_packet(raw).params[4:] == b"".join(
            bytes((i,)) + x.to_bytes(2, "little", signed=True) for i, x in zip([1, 2, 3], v)
        )
    with pytest.raises(PacketError, match="does not fit"):
        enc.encode([0, 40000, 0])
    with pytest.raises(PacketError, match="expects 3 values"):
        enc.encode([1, 2])


class ReplayPort(PortHandler):
    """The SDK's port replaying one recorded reply, for the SDK's own parsing of it."""

    def __init__(self, reply: bytes):
        super().__init__("replay")
        self.is_open = True
        self.reply = reply

    def readPort(self, length):  # noqa: N802
        out, self.reply = self.reply[:length], self.reply[length:]
        return out

    def setPacketTimeout(self, packet_length):  # noqa: N802
        self.packet_start_time = self.getCurrentTime()
        self.packet_timeout = 1000.0


def test_fast_bulk_read_fields_equal_the_sdk_parse():
    """A 20-servo FAST_BULK_READ reply (19 positions + one 49-byte status block) read by
    ``decode_fields`` equals dynamixel-sdk's GroupBulkRead parse of the same bytes."""
    rng = np.random.default_rng(7)
    # dynamixel-sdk 4.x finds each reply part's length with param.index(ID) over the flat
    # [ID, ADDR_L, ADDR_H, LEN_L, LEN_H, ...] list, so an ID equal to an earlier address or
    # length byte (4 here: LEN_L of a Present Position item) is misparsed by the SDK; the
    # cross-check leaves such IDs out (our decoder reads parts by position, not by search)
    ids = [sid for sid in range(1, 22) if sid != 4]
    items = [(sid, 132, 4) for sid in ids]
    items[5] = (7, 98, 49)
    data = [bytes(rng.integers(0, 256, size, dtype=np.uint8)) for _, _, size in items]
    reply = dp.encode_fast_status([(0x80 if sid == 9 else 0, sid, d) for (sid, _, _), d in zip(items, data)])
    fields = [
        [(0, 4, True)]
        if size == 4
        else [(0, 1, True), (28, 2, True), (30, 4, True), (34, 4, True), (46, 2, False), (48, 1, False)]
        for _, _, size in items
    ]
    dec = FastBulkReadDecoder(items, fields)
    errors, values = dec.decode_fields(reply)
    assert errors == tuple(0x80 if sid == 9 else 0 for sid in ids)

    group = GroupBulkRead(ReplayPort(reply), PacketHandler(2.0))
    for sid, addr, size in items:
        group.addParam(sid, addr, size)
    group.makeParam()  # what fastBulkReadTxPacket would do before sending
    assert group.fastBulkReadRxPacket() == 0
    expect = []
    for sid, addr, _size in items:
        for off, fsize, signed in fields[5] if sid == 7 else [(0, 4, True)]:
            raw = group.getData(sid, addr + off, fsize)
            expect.append(raw - (1 << 8 * fsize) if signed and raw >= 1 << (8 * fsize - 1) else raw)
    assert list(values) == expect
    # a flipped byte is a CRC error naming the servo; a swapped ID is named too
    bad = bytearray(reply)
    bad[dec.data_starts[5] + 3] ^= 0x40
    with pytest.raises(PacketError, match="servo ID 7"):
        dec.decode_fields(bytes(bad))
    swapped = dp.encode_fast_status([(0, sid if sid != 5 else 40, d) for (sid, _, _), d in zip(items, data)])
    with pytest.raises(PacketError, match="carries servo ID 40"):
        dec.decode_fields(swapped)


def test_fast_sync_read_fields_equal_the_array_decode():
    rng = np.random.default_rng(5)
    values = rng.integers(-(2**31), 2**31, 20)
    raw = dp.encode_fast_status([(0, sid, int(v).to_bytes(4, "little", signed=True)) for sid, v in zip(IDS, values)])
    dec = FastSyncReadDecoder(132, 4, IDS)
    errors, got = dec.decode_fields(raw)
    assert got == tuple(values.tolist()) and errors == (0,) * 20


def op3_transport() -> DynamixelTransport:
    """The bundled robot's bus (20 servos, both directions, zero offsets), not opened:
    the conversions need only the config."""
    return DynamixelTransport(load_config(robot_config_path("op3"), check_mjcf=False).buses[0])


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-0.02, 1.02), min_size=20, max_size=20))
def test_goal_ticks_equal_the_numpy_conversion(fractions):
    """Per-element goal ticks = ``_to_ticks`` of the clipped goal, tick for tick, at and
    just beyond the limits (inside the half tick of slack)."""
    t = op3_transport()
    lo, hi = t.lower, t.upper
    q = lo + np.asarray(fractions) * (hi - lo)
    q = np.clip(q, lo - t.servos.half_tick * 0.999, hi + t.servos.half_tick * 0.999)
    assert t.servos.goal_ticks(q.tolist()) == t.servos.to_ticks(np.clip(q, lo, hi)).tolist()


def test_goal_ticks_refuse_what_the_limits_refuse():
    t = op3_transport()
    q = (t.lower + t.upper) / 2
    for bad in (math.nan, math.inf, -math.inf, t.upper[4] + 0.01):
        g = q.copy()
        g[4] = bad
        with pytest.raises(BridgeError, match=r"servo ID 5 \(r_el\).*outside the joint limits"):
            t.servos.goal_ticks(g.tolist())


def test_positions_from_ticks_equal_the_numpy_conversion():
    t = op3_transport()
    ticks = np.random.default_rng(2).integers(-100, 4200, 20)
    t.servos.set_position(tuple(ticks.tolist()))
    fast = t.servos.state.position.copy()
    assert np.array_equal(fast, t.servos.to_joint(ticks))  # bit for bit


emu4 = test_dxl_pipeline.bus_and_emu  # four emulated servos; no goal outside the limits reaches them


def run_ticks(t, n: int, fast: bool):
    """n split-phase ticks, each read once the reply is in; returns the readings and how
    many took the one-pass path."""
    taken = [0]
    one_pass = DynamixelTransport._read_arrived

    def counted(self):
        out = one_pass(self)
        taken[0] += out is not None
        return out

    t._read_arrived = (lambda: counted(t)) if fast else (lambda: None)
    out = []
    for _ in range(n):
        t.write_goal(t.lower * 0)
        j = t.cycle.pending[1]
        need = (t.cycle.bulk[j][0] if j >= 0 else t.cycle.fast).reply_length
        assert wait_for(lambda need=need: t.bus.port.ser.in_waiting >= need)
        out.append(t.read_state())
    del t._read_arrived
    return out, taken[0]


@pytest.mark.parametrize("slow", [1, 0])
def test_one_pass_tick_gives_the_general_paths_state(emu4, slow):
    """Torque off, distinct positions, temperatures and supply voltages: a round of ticks
    through the one-pass read and a round through the general path give the same state,
    bit for bit, and both match the emulator's registers through the model's units.
    ``slow`` 1: FAST_BULK_READ with one status block per tick; 0: FAST_SYNC_READ alone."""
    bus, emu = emu4
    for sid in range(1, 5):
        emu.push(sid, 2048 + 111 * sid)
        emu.overheat(sid, 30.0 + sid) if sid != 2 else None
        emu.set_supply_voltage(sid, 11.0 + 0.3 * sid)
    with make(bus, emu, slow_per_cycle=slow) as t:
        if slow == 0:  # the status fields come from one blocking round first (the one-pass read keeps them)
            t.slow_per_cycle = 1
            for _ in range(4):
                t.read_state()
            t.slow_per_cycle = 0
        assert t.pipeline(True) and (t.cycle.bulk is not None) == (slow == 1)
        fast, taken = run_ticks(t, 8, fast=True)
        general, skipped = run_ticks(t, 8, fast=False)
        assert taken == 8 and skipped == 0
        a, b = fast[-1], general[-1]
        for name in ("position", "velocity", "effort", "temperature", "voltage", "torque_enabled"):
            assert np.array_equal(getattr(a, name), getattr(b, name)), name
        assert a.errors == b.errors
        ticks = np.array([emu.read_register(sid, "present_position") for sid in range(1, 5)])
        assert np.array_equal(a.position, t.servos.to_joint(ticks))
        volts = [emu.read_register(sid, "present_input_voltage") * XM.voltage_v for sid in range(1, 5)]
        temps = [emu.read_register(sid, "present_temperature") * XM.temperature_c for sid in range(1, 5)]
        assert a.voltage.tolist() == volts and a.temperature.tolist() == temps
        assert t.stats.read_retries == 0
        # the reading is the caller's: changing it leaves the transport's state alone
        a.position[:] = 99.0
        a.temperature[:] = 99.0
        assert not np.any(t.read_state().position == 99.0)


def test_one_pass_hands_a_corrupt_reply_to_the_general_path(emu4):
    """A corrupted reply that has fully arrived: the one-pass read declines it and the
    general path counts the retry and reads again; an alert bit is declined the same way
    and handled by the general path (read register 70)."""
    bus, emu = emu4
    with make(bus, emu, slow_per_cycle=1) as t:
        assert t.pipeline(True)
        run_ticks(t, 2, fast=True)
        emu.corrupt_replies(1, 1)
        states, taken = run_ticks(t, 1, fast=True)
        assert taken == 0 and t.stats.read_retries == 1
        assert np.all(np.isfinite(states[0].position))
        emu.overheat(3, 80.0)
        alerts = t.stats.alerts
        states, taken = run_ticks(t, 1, fast=True)
        assert taken == 0 and t.stats.alerts == alerts + 1 and "overheating" in states[0].errors["j3"]
