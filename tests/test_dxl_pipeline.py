"""The Dynamixel transport's split-phase bus cycle (``DynamixelTransport.pipeline``): the real
dynamixel-sdk over a pty against the byte-level emulator. The write sends the position read
request, the next read takes its reply; faults keep the blocking path's policy, nothing is
ever sent over a reply still on the wire, and no goal outside the limits reaches a servo."""

from __future__ import annotations

import time

import numpy as np
import pytest
from test_dxl_transport import (  # tests/ is on sys.path (pytest, prepend mode)
    XM,
    guarded_emulator,
    make,
    small_bus,
    wait_for,
)

from ros_free_bridge.dynamixel import protocol as dp
from ros_free_bridge.errors import BridgeError


@pytest.fixture
def bus_and_emu():
    bus = small_bus(4)
    emu = guarded_emulator(bus)
    try:
        yield bus, emu
    finally:
        assert emu.violations == [], "a goal outside the configured limits reached the bus"
        emu.stop()


def watch_writes(t):
    """Record, for every packet the host writes, its instruction and whether a split-phase
    reply was still pending at that moment (it must never be: the bus is half duplex)."""
    sent = []
    port = t.bus.port
    write = port.writePort
    parser = dp.StreamParser(protocol=2)

    def write_port(packet):
        pending = t.cycle.pending is not None
        sent.extend((frame.raw[7], pending) for frame in parser.feed(bytes(packet)))  # a write may carry two
        return write(packet)

    port.writePort = write_port
    return sent


def test_codec_fast_bulk_read_request_equals_the_sdk_packet(bus_and_emu):
    import dynamixel_sdk as sdk

    from ros_free_bridge.dynamixel.group_codec import FastBulkReadDecoder
    from ros_free_bridge.dynamixel.protocol import PacketError

    bus, emu = bus_and_emu
    items = [(1, 132, 4), (2, 98, 49), (3, 132, 4), (4, 132, 4)]
    with make(bus, emu, slow_per_cycle=0) as t:
        group = sdk.GroupBulkRead(t.bus.port, t.bus.ph)
        for sid, addr, size in items:
            group.addParam(sid, addr, size)
        t.bus.call(lambda port: group.fastBulkReadTxPacket())
        assert wait_for(lambda: emu.received[-1][7] == dp.FAST_BULK_READ)
        dec = FastBulkReadDecoder(items)
        assert emu.received[-1] == dec.request
        # the emulator's reply parses; a flipped data byte is a CRC error naming its servo
        reply = dp.encode_fast_status([(0, sid, bytes(range(size))) for sid, _, size in items])
        a, errors = dec.decode(reply)
        assert a[dec.data_starts[1] : dec.data_starts[1] + 49].tobytes() == bytes(range(49)) and not errors.any()
        bad = bytearray(reply)
        bad[dec.data_starts[2]] ^= 0xFF
        with pytest.raises(PacketError, match="servo ID 3"):
            dec.decode(bytes(bad))
    with pytest.raises(PacketError, match="twice"):
        FastBulkReadDecoder([(1, 132, 4), (1, 98, 4)])


def test_write_sends_the_read_request_and_the_next_read_takes_its_reply(bus_and_emu):
    bus, emu = bus_and_emu
    with make(bus, emu, slow_per_cycle=0) as t:
        t.set_torque(True)
        assert t.pipeline(True) and t.pipelined
        sent = watch_writes(t)
        goal = np.array([0.3, -0.2, 0.1, 0.25])
        for _ in range(40):
            t.write_goal(goal)
            before = time.monotonic()
            s = t.read_state()
            assert s.stamp <= before  # the positions were requested by the write, before this call
        # one SYNC_WRITE then one FAST_SYNC_READ per cycle; read_state itself sent nothing
        assert [inst for inst, _ in sent] == [dp.SYNC_WRITE, dp.FAST_SYNC_READ] * 40
        assert not any(pending for _, pending in sent)
        # the servos got there, and the split-phase reading says so (one tick old at most)
        assert wait_for(
            lambda: all(
                abs(emu.read_register(i + 1, "present_position") - g) <= 2
                for i, g in enumerate(np.rint(t.servos.to_ticks(goal)))
            )
        )
        t.write_goal(goal)
        np.testing.assert_allclose(t.read_state().position, goal, atol=2.5 / XM.ticks_per_rad)
        # the blocking path reads the same pose
        t.pipeline(False)
        np.testing.assert_allclose(t.read_state().position, goal, atol=2.5 / XM.ticks_per_rad)
        assert t.stats.read_retries == 0


def test_one_fast_bulk_read_per_cycle_brings_positions_and_a_status_block(bus_and_emu):
    bus, emu = bus_and_emu
    emu.overheat(3, 80.0)
    emu.push(2, 2048 + 300)
    with make(bus, emu, slow_per_cycle=1) as t:
        assert t.pipeline(True)
        sent = watch_writes(t)
        for _ in range(8):
            t.write_goal(t.lower * 0)  # torque off: the servos stay where they are
            s = t.read_state()
        # per cycle one SYNC_WRITE and one FAST_BULK_READ; the reported alert of servo 3 is read
        # again (register 70, torque: two READs) each time its status block comes round (twice)
        cycle = [inst for inst, _ in sent if inst != dp.READ]
        assert cycle == [dp.SYNC_WRITE, dp.FAST_BULK_READ] * 8
        assert [inst for inst, _ in sent].count(dp.READ) == 4
        assert not any(pending for _, pending in sent)
        # every servo's status block came round; the positions are every servo's
        assert np.all(np.isfinite(s.temperature)) and np.all(np.isfinite(s.voltage))
        assert s.temperature[2] == pytest.approx(80.0, abs=1.0) and s.temperature[0] == pytest.approx(25.0, abs=1.0)
        assert "overheating" in s.errors["j3"] and "policy does not reboot" in s.errors["j3"]
        assert s.position[1] == pytest.approx(t.servos.to_joint(np.array([0, 2348, 0, 0]))[1], abs=1e-9)
        # a new alert in the reply that also carries that servo's status block is handled once
        j = t.cycle.slow_next
        emu.overheat(j + 1, 80.0)
        alerts = t.stats.alerts
        t.write_goal(t.lower * 0)
        s = t.read_state()
        assert t.stats.alerts == alerts + 1 and "overheating" in s.errors[f"j{j + 1}"]


def test_firmware_without_fast_bulk_read_gets_a_split_status_read(bus_and_emu):
    bus, emu = bus_and_emu
    emu.unsupported = frozenset({"FAST_BULK_READ"})
    emu.overheat(3, 80.0)
    with make(bus, emu, slow_per_cycle=1) as t:
        t.set_torque(True)
        assert t.pipeline(True) and any("FAST_BULK_READ" in n for n in t.stats.notes)
        sent = watch_writes(t)
        for _ in range(10):
            t.write_goal(np.zeros(4))
            s = t.read_state()
        insts = [inst for inst, _ in sent]
        assert insts.count(dp.FAST_SYNC_READ) == 10 and dp.FAST_BULK_READ not in insts
        assert insts.count(dp.READ) >= 9  # one status READ per cycle, sent without waiting for its reply
        assert not any(pending for _, pending in sent)
        assert np.all(np.isfinite(s.temperature)) and np.all(np.isfinite(s.voltage))
        assert "overheating" in s.errors["j3"]
        assert s.temperature[2] == pytest.approx(80.0, abs=1.0)


def test_firmware_without_fast_group_reads_stays_blocking(bus_and_emu):
    bus, emu = bus_and_emu
    emu.unsupported = frozenset({"FAST_SYNC_READ", "FAST_BULK_READ"})
    with make(bus, emu, slow_per_cycle=1) as t:
        assert not t.stats.fast_sync_read  # SYNC_READ fallback
        assert t.pipeline(True) is False
        t.write_goal(np.zeros(4))
        assert t.cycle.pending is None and np.all(np.isfinite(t.read_state().position))


def test_a_dropped_or_corrupted_reply_is_retried_then_the_silent_servo_is_named(bus_and_emu):
    bus, emu = bus_and_emu
    with make(bus, emu, slow_per_cycle=1, retries=2) as t:
        t.set_torque(True)
        t.pipeline(True)
        t.write_goal(np.zeros(4))
        t.read_state()
        emu.drop_replies(2, 1)  # the next fast reply is cut short at servo 2
        t.write_goal(np.zeros(4))
        s = t.read_state()
        assert t.stats.read_retries >= 1 and np.all(np.isfinite(s.position))
        retries = t.stats.read_retries
        emu.corrupt_replies(4, 1)
        t.write_goal(np.zeros(4))
        t.read_state()
        assert t.stats.read_retries > retries
        emu.disconnect(3)
        t.write_goal(np.zeros(4))
        with pytest.raises(BridgeError, match=r"servo ID 3 \(j3\)"):
            t.read_state()


def test_an_alert_in_the_split_phase_reply_is_recovered(bus_and_emu):
    bus, emu = bus_and_emu
    with make(bus, emu, slow_per_cycle=0) as t:
        t.set_torque(True)
        t.pipeline(True)
        t.write_goal(np.full(4, 0.2))
        t.read_state()
        emu.set_hardware_error(2, 0x20)  # overload: torque off by Shutdown, alert bit in every status
        t.write_goal(np.full(4, 0.2))
        s = t.read_state()
        assert t.stats.alerts == 1 and t.stats.reboots == 1
        assert "j2" not in s.errors and emu.read_register(2, "torque_enable") == 1


def test_stop_and_estop_collect_the_pending_reply_first(bus_and_emu):
    bus, emu = bus_and_emu
    with make(bus, emu, slow_per_cycle=1, stop_policy="limp") as t:
        t.set_torque(True)
        t.pipeline(True)
        sent = watch_writes(t)
        t.write_goal(np.full(4, 0.1))
        assert t.cycle.pending is not None
        t.safe_stop("limp")  # an e-stop while the position reply is on the wire
        assert not any(pending for _, pending in sent)
        assert all(emu.read_register(i, "torque_enable") == 0 for i in (1, 2, 3, 4))
        t.read_state()  # still usable: the collected reply (or a fresh read) gives positions
    assert t.bus.port is None


def test_the_port_vanishing_with_a_reply_pending_is_a_bridge_error(bus_and_emu):
    bus, emu = bus_and_emu
    t = make(bus, emu, slow_per_cycle=1, retries=0)
    t.open()
    t.pipeline(True)
    t.write_goal(np.zeros(4))
    emu.vanish()
    with pytest.raises(BridgeError, match="Dynamixel bus|servo ID"):
        for _ in range(3):
            t.read_state()
            t.write_goal(np.zeros(4))
    t.close()
    assert t.bus.port is None and t.cycle.pending is None


def test_protocol_1_and_sync_read_buses_stay_blocking():
    from test_dxl_transport import LAT, DynamixelBusEmulator, DynamixelTransport, ServoSpec, parse_config

    cfg = parse_config(
        {
            "robot": "t",
            "buses": [
                {
                    "name": "b",
                    "port": "/dev/null",
                    "baud": 1000000,
                    "protocol": "1.0",
                    "servos": [{"id": 1, "joint": "a", "model": "AX-12A", "limits": [-1, 1]}],
                }
            ],
        }
    )
    with DynamixelBusEmulator([ServoSpec(1, "AX-12A")], baud=1_000_000, protocol=1) as emu:
        with DynamixelTransport(cfg.buses[0], port=emu.port_path, latency_ms=LAT) as t:
            assert t.pipeline(True) is False and not t.pipelined
            t.write_goal(np.zeros(1))
            assert t.cycle.pending is None and np.isfinite(t.read_state().position[0])
