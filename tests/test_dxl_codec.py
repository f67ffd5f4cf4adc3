"""The transport's hot-path packet code (ros_free_bridge.dynamixel.group_codec): the numpy
SYNC_WRITE encoder and FAST_SYNC_READ decoder against dynamixel-sdk's own packets, captured
on the emulator side, and the linear CRC against the scalar one."""

from __future__ import annotations

import time

import numpy as np
import pytest
from dynamixel_sdk import GroupSyncRead, GroupSyncWrite, PacketHandler, PortHandler
from hypothesis import given, settings
from hypothesis import strategies as st

from firmware_cfg.config import parse_config
from firmware_cfg.servo_models import load_servo_model
from ros_free_bridge.commands.servo import start_emulator
from ros_free_bridge.dynamixel import protocol as dp
from ros_free_bridge.dynamixel.group_codec import FastSyncReadDecoder, SyncWriteEncoder
from ros_free_bridge.dynamixel.protocol import PacketError, encode_instruction
from ros_free_bridge.dynamixel.transport import DynamixelTransport
from ros_free_bridge.errors import BridgeError

XM = load_servo_model("XM430-W350")
IDS = list(range(1, 21))


def bus_config(n=6):
    servos = [
        {
            "id": i + 1,
            "joint": f"j{i + 1}",
            "model": "XM430-W350",
            "limits": [-2.5, 2.5],
            "direction": -1 if i % 2 else 1,
            "zero_offset": 0.03 * i,
            "return_delay_us": 0,
        }
        for i in range(n)
    ]
    return parse_config(
        {
            "robot": "t",
            "buses": [{"name": "b", "port": "/dev/null", "baud": 2000000, "protocol": "2.0", "servos": servos}],
        }
    ).buses[0]


class CapturePort(PortHandler):
    """The SDK's port with writePort captured and nothing to read (no device)."""

    def __init__(self):
        super().__init__("capture")
        self.is_open = True
        self.sent: list[bytes] = []

    def clearPort(self):  # noqa: N802 - SDK naming
        pass

    def writePort(self, packet):  # noqa: N802
        self.sent.append(bytes(packet))
        return len(packet)

    def readPort(self, length):  # noqa: N802
        return b""

    def setPacketTimeout(self, packet_length):  # noqa: N802
        self.packet_start_time = self.getCurrentTime()
        self.packet_timeout = 0.0


def next_packet(emu, instruction, before: int, timeout=5.0) -> bytes:
    """The first packet with ``instruction`` the emulator hears after it had heard
    ``before`` of them (a SYNC_WRITE has no reply, so wait for the emulator's thread)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        seen = [r for r in list(emu.received) if r[7] == instruction]
        if len(seen) > before:
            return seen[before]
        time.sleep(0.002)
    raise AssertionError(f"the emulator heard no new 0x{instruction:02X} packet")


def count(emu, instruction) -> int:
    return sum(1 for r in list(emu.received) if r[7] == instruction)


def sdk_sync_write(port, address, size, ids, values) -> None:
    group = GroupSyncWrite(port, PacketHandler(2.0), address, size)
    for sid, v in zip(ids, values):
        group.addParam(sid, list(int(v).to_bytes(size, "little", signed=True)))
    group.txPacket()
    port.is_using = False


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(0, 4095), min_size=20, max_size=20), st.sampled_from([(116, 4), (104, 4), (102, 2)]))
def test_sync_write_encoder_equals_the_sdk_packet(values, reg):
    address, size = reg
    port = CapturePort()
    sdk_sync_write(port, address, size, IDS, values)
    assert SyncWriteEncoder(address, size, IDS).encode(np.array(values)) == port.sent[-1]


def test_sync_write_with_a_header_pattern_in_the_data_is_stuffed_as_the_protocol_requires():
    # -131073 is FF FF FD FF little-endian: FF FF FD in a packet body must be followed by FD.
    values = np.array([-131073, 5, -1])
    ours = SyncWriteEncoder(116, 4, [1, 2, 3]).encode(values)
    params = bytes((116, 0, 4, 0)) + b"".join(
        bytes((i,)) + int(v).to_bytes(4, "little", signed=True) for i, v in zip((1, 2, 3), values)
    )
    assert ours == encode_instruction(0xFE, dp.SYNC_WRITE, params)
    assert b"\xff\xff\xfd\xfd" in ours
    # the SDK computes the same stuffed packet (addStuffing's result), though its txPacket
    # 4.1.0 then sends the unstuffed one; the decoder of the emulator reads ours back
    port = CapturePort()
    sdk_sync_write(port, 116, 4, [1, 2, 3], values)
    stuffed = PacketHandler(2.0).addStuffing(list(port.sent[-1]))
    assert bytes(stuffed[:-2]) == ours[:-2]
    assert dp.decode_packet(ours).params == params


def test_fast_sync_read_request_equals_the_sdk_packet():
    port = CapturePort()
    group = GroupSyncRead(port, PacketHandler(2.0), 132, 4)
    for sid in IDS:
        group.addParam(sid)
    group.fastSyncRead()
    assert FastSyncReadDecoder(132, 4, IDS).request == port.sent[-1]


def test_fast_sync_read_reply_parsed_in_one_pass():
    rng = np.random.default_rng(3)
    values = rng.integers(-(2**31), 2**31, len(IDS))
    errors = np.zeros(len(IDS), np.uint8)
    errors[[4, 17]] = [0x80, 0x07]
    raw = dp.encode_fast_status(
        [(int(e), sid, int(v).to_bytes(4, "little", signed=True)) for e, sid, v in zip(errors, IDS, values)]
    )
    dec = FastSyncReadDecoder(132, 4, IDS)
    assert len(raw) == dec.reply_length == 8 + 20 * 8
    got, err = dec.decode(raw)
    np.testing.assert_array_equal(got, values)
    np.testing.assert_array_equal(err, errors)
    unsigned, _ = FastSyncReadDecoder(132, 4, IDS, signed=False).decode(raw)
    np.testing.assert_array_equal(unsigned, values % 2**32)


def test_fast_sync_read_reply_errors_are_named():
    dec = FastSyncReadDecoder(132, 4, [1, 2, 3])
    good = dp.encode_fast_status([(0, i, bytes(4)) for i in (1, 2, 3)])
    bad = bytearray(good)
    bad[8 + 8 + 3] ^= 0x10  # a data byte of servo 2's part
    with pytest.raises(PacketError, match="CRC mismatch in the part for servo ID 2"):
        dec.decode(bytes(bad))
    with pytest.raises(PacketError, match="23 bytes, expected 32"):
        dec.decode(good[:23])
    swapped = dp.encode_fast_status([(0, i, bytes(4)) for i in (1, 3, 2)])
    with pytest.raises(PacketError, match="part 1 carries servo ID 3, expected 2"):
        dec.decode(swapped)
    with pytest.raises(PacketError, match="header"):
        FastSyncReadDecoder(132, 4, [1, 2, 3, 4]).decode(good + bytes(8))
    with pytest.raises(PacketError):
        SyncWriteEncoder(116, 3, [1])
    with pytest.raises(PacketError):
        FastSyncReadDecoder(132, 4, [253])


def test_transport_packets_equal_the_sdk_packets_on_the_wire():
    """Captured where a servo would see them: the emulator's received packets."""
    bus = bus_config()
    emu = start_emulator(bus, provisioned=True)
    try:
        with DynamixelTransport(bus, port=emu.port_path, latency_ms=30.0, slow_per_cycle=0) as t:
            ids = [s.id for s in bus.servos]
            t.read_state()
            fsr_ours = [r for r in emu.received if r[7] == dp.FAST_SYNC_READ][-1]
            rng = np.random.default_rng(0)
            for _ in range(5):
                goal = rng.uniform(t.lower, t.upper)
                n = count(emu, dp.SYNC_WRITE)
                t.write_goal(goal)
                ours = next_packet(emu, dp.SYNC_WRITE, n)
                ticks = t.servos.to_ticks(np.clip(goal, t.lower, t.upper))
                sdk_sync_write(t.bus.port, 116, 4, ids, ticks)
                theirs = next_packet(emu, dp.SYNC_WRITE, n + 1)
                assert ours == theirs
            group = GroupSyncRead(t.bus.port, t.bus.ph, 132, 4)
            for sid in ids:
                group.addParam(sid)
            assert group.fastSyncRead() == 0
            t.bus.port.is_using = False
            assert [r for r in emu.received if r[7] == dp.FAST_SYNC_READ][-1] == fsr_ours
            # and the positions parsed from the fast reply are the servos' own
            st = t.read_state()
            present = np.array([emu.read_register(sid, "present_position") for sid in ids])
            expect = np.array(
                [s.direction * ((p - 2048) * 2 * np.pi / 4096 - s.zero_offset) for s, p in zip(bus.servos, present)]
            )
            np.testing.assert_allclose(st.position, expect, atol=1e-12)
            assert t.stats.fast_sync_read
    finally:
        emu.stop()


def test_hardware_alert_seen_in_the_fast_reply_without_a_status_read():
    """slow_per_cycle=0: no individual status reads at all, yet an overheating servo is
    reported, because the fast reply keeps each servo's error byte."""
    bus = bus_config(4)
    emu = start_emulator(bus, provisioned=True)
    try:
        with DynamixelTransport(bus, port=emu.port_path, latency_ms=30.0, slow_per_cycle=0) as t:
            assert t.read_state().errors == {}
            emu.overheat(3)
            errors = t.read_state().errors
            assert list(errors) == ["j3"] and "overheating" in errors["j3"]
            assert t.stats.alerts == 1
            t.read_state()
            assert t.stats.alerts == 1  # reported once, not re-read every tick
    finally:
        emu.stop()


def test_reply_wait_sleeps_instead_of_spinning():
    """A read that times out must sleep in poll, not call read thousands of times."""
    bus = bus_config(2)
    emu = start_emulator(bus, provisioned=True)
    try:
        t = DynamixelTransport(bus, port=emu.port_path, latency_ms=30.0, slow_per_cycle=0, retries=0)
        t.open()
        try:
            port = t.bus.port
            calls = [0]
            read = port._read_now  # every read of the port goes through it (one os.read)

            def counting_read(n=1):
                calls[0] += 1
                return read(n)

            port._read_now = counting_read
            emu.disconnect(1)
            with pytest.raises(BridgeError, match="servo ID 1"):
                t.read_state()
            # one timed-out fast read (~60 ms) and a PING per servo to name the silent one
            assert 0 < calls[0] < 60
        finally:
            emu.disconnect(1, False)
            t.close()
    finally:
        emu.stop()
