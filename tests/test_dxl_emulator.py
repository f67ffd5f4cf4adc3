"""The real dynamixel-sdk driving the byte-level bus emulator over a pseudo-terminal."""

from __future__ import annotations

import os
import termios
import time
from contextlib import contextmanager

import dynamixel_sdk as sdk
import pytest
import serial

from firmware_cfg.servo_models import load_servo_model
from ros_free_bridge import BridgeError
from ros_free_bridge.dynamixel import protocol as dp
from ros_free_bridge.emulators import DynamixelBusEmulator, ServoSpec

# XM430-W350 control table addresses (e-Manual).
TORQUE, LED, SRL, HW_ERR = 64, 65, 68, 70
RETURN_DELAY, MAX_POS, MIN_POS = 9, 48, 52
GOAL, PRESENT_VEL, PRESENT_POS, TEMP = 116, 128, 132, 146
PROFILE_VEL = 112


@pytest.fixture(autouse=True)
def patient_sdk(monkeypatch):
    """dynamixel-sdk waits 2 x LATENCY_TIMER + 2 ms (34 ms) for a reply, sized for a USB
    adapter's 16 ms latency timer. On a loaded CI machine the emulator's thread can be
    descheduled for longer than that, so the tests give the SDK a 50 ms latency timer
    (a module setting, not a change to its packet code)."""
    monkeypatch.setattr(sdk.port_handler, "LATENCY_TIMER", 50)


@contextmanager
def bus(servos, baud=1_000_000, protocol=2, **kwargs):
    """An emulator plus an open SDK port and packet handler; the port is always closed."""
    with DynamixelBusEmulator(servos=servos, baud=baud, protocol=protocol, **kwargs) as emu:
        port = sdk.PortHandler(emu.port_path)
        assert port.openPort()
        assert port.setBaudRate(baud)
        try:
            yield emu, port, sdk.PacketHandler(float(protocol))
        finally:
            if port.is_open:
                try:
                    port.closePort()
                except OSError:
                    pass


def wait_until(predicate, limit_s=3.0):
    """Poll ``predicate`` until true; fail (not time out silently) after ``limit_s``."""
    end = time.monotonic() + limit_s
    while time.monotonic() < end:
        if predicate():
            return
        time.sleep(0.01)
    raise AssertionError("condition not reached")


def to_u32(value: int) -> list[int]:
    return list((value & 0xFFFFFFFF).to_bytes(4, "little"))


# ---------------------------------------------------------------- basics


def test_ping_reports_each_models_number_and_absent_ids_time_out():
    servos = [(1, "XM430-W350"), (2, "XL430-W250"), (3, "XL330-M288")]
    with bus(servos) as (emu, port, ph):
        assert [ph.ping(port, i) for i in (1, 2, 3)] == [
            (1020, sdk.COMM_SUCCESS, 0),
            (1060, sdk.COMM_SUCCESS, 0),
            (1200, sdk.COMM_SUCCESS, 0),
        ]
        assert ph.ping(port, 9)[1] == sdk.COMM_RX_TIMEOUT
        assert emu.instruction_counts["PING"] == 4


def test_goal_moves_the_servo_only_with_torque_on_and_push_follows_with_torque_off():
    with bus([ServoSpec(1, position=2048)]) as (emu, port, ph):
        assert ph.write4ByteTxRx(port, 1, GOAL, 2600) == (sdk.COMM_SUCCESS, 0)
        time.sleep(0.05)
        assert ph.read4ByteTxRx(port, 1, PRESENT_POS) == (2048, sdk.COMM_SUCCESS, 0)  # torque off: goal ignored
        emu.push(1, 1500)
        assert ph.read4ByteTxRx(port, 1, PRESENT_POS)[0] == 1500  # limp horn follows the hand
        assert ph.write1ByteTxRx(port, 1, TORQUE, 1) == (sdk.COMM_SUCCESS, 0)
        time.sleep(0.02)
        moving = ph.read4ByteTxRx(port, 1, PRESENT_VEL)[0]
        assert 0 < moving <= 1023  # heading up towards 2600
        wait_until(lambda: ph.read4ByteTxRx(port, 1, PRESENT_POS)[0] == 2600)
        emu.push(1, 2000)  # with torque on it returns to its goal
        wait_until(lambda: ph.read4ByteTxRx(port, 1, PRESENT_POS)[0] == 2600)
        assert [r.ticks for r in emu.goal_history[1]] == [2600]


def test_eeprom_is_locked_while_torque_is_on():
    with bus([1]) as (emu, port, ph):
        ph.write1ByteTxRx(port, 1, TORQUE, 1)
        assert ph.write1ByteTxRx(port, 1, RETURN_DELAY, 10) == (sdk.COMM_SUCCESS, 7)  # access error
        assert ph.read1ByteTxRx(port, 1, RETURN_DELAY)[0] == 0
        ph.write1ByteTxRx(port, 1, TORQUE, 0)
        assert ph.write1ByteTxRx(port, 1, RETURN_DELAY, 10) == (sdk.COMM_SUCCESS, 0)
        assert ph.read1ByteTxRx(port, 1, RETURN_DELAY)[0] == 10


def test_write_errors_name_what_is_wrong_and_change_nothing():
    with bus([1]) as (emu, port, ph):
        assert ph.write4ByteTxRx(port, 1, PRESENT_POS, 5)[1] == 7  # read-only: access error
        assert ph.write2ByteTxRx(port, 1, GOAL, 100)[1] == 5  # half a register: length error
        assert ph.write1ByteTxRx(port, 1, SRL, 3)[1] == 4  # outside 0..2: range error
        ph.write4ByteTxRx(port, 1, MAX_POS, 3000)
        assert ph.write4ByteTxRx(port, 1, GOAL, 3500)[1] == 6  # beyond Max Position Limit
        assert ph.read4ByteTxRx(port, 1, GOAL)[0] == 2048
        assert [(r.ticks, r.accepted) for r in emu.goal_history[1]] == [((2048 & ~0xFFFF) | 100, False), (3500, False)]
        assert ph.getRxPacketError(6) == "[RxPacketError] The data value exceeds the limit value!"


def test_status_return_level_controls_which_instructions_are_answered():
    with bus([1]) as (emu, port, ph):
        assert ph.write1ByteTxRx(port, 1, SRL, 1)[0] == sdk.COMM_RX_TIMEOUT  # the new level applies at once
        assert ph.read1ByteTxRx(port, 1, SRL) == (1, sdk.COMM_SUCCESS, 0)
        assert ph.write1ByteTxRx(port, 1, LED, 1)[0] == sdk.COMM_RX_TIMEOUT  # writes go unanswered...
        assert ph.read1ByteTxRx(port, 1, LED) == (1, sdk.COMM_SUCCESS, 0)  # ...but were applied
        emu.write_register(1, "status_return_level", 0)
        assert ph.read1ByteTxRx(port, 1, LED)[1] == sdk.COMM_RX_TIMEOUT
        assert ph.ping(port, 1) == (1020, sdk.COMM_SUCCESS, 0)  # ping always answers


# ---------------------------------------------------------------- group instructions


def test_sync_write_and_fast_sync_read_of_twenty_servos():
    ids = list(range(1, 21))
    goals = {i: 2048 + 10 * i - 100 for i in ids}
    with bus(ids, baud=2_000_000) as (emu, port, ph):
        torque = sdk.GroupSyncWrite(port, ph, TORQUE, 1)
        goal = sdk.GroupSyncWrite(port, ph, GOAL, 4)
        for i in ids:
            torque.addParam(i, [1])
            goal.addParam(i, to_u32(goals[i]))
        assert torque.txPacket() == sdk.COMM_SUCCESS
        assert goal.txPacket() == sdk.COMM_SUCCESS
        fast = sdk.GroupSyncRead(port, ph, PRESENT_POS, 4)
        for i in ids:
            fast.addParam(i)

        def settled():
            return fast.fastSyncRead() == sdk.COMM_SUCCESS and all(
                fast.getData(i, PRESENT_POS, 4) == goals[i] for i in ids
            )

        wait_until(settled)
        slow = sdk.GroupSyncRead(port, ph, PRESENT_POS, 4)
        bulk = sdk.GroupBulkRead(port, ph)
        for i in ids:
            slow.addParam(i)
            bulk.addParam(i, PRESENT_POS, 4)
        assert slow.txRxPacket() == sdk.COMM_SUCCESS
        assert bulk.txRxPacket() == sdk.COMM_SUCCESS
        assert [slow.getData(i, PRESENT_POS, 4) for i in ids] == [goals[i] for i in ids]
        assert [bulk.getData(i, PRESENT_POS, 4) for i in ids] == [goals[i] for i in ids]
        assert {i: [r.ticks for r in h] for i, h in emu.goal_history.items()} == {i: [goals[i]] for i in ids}
        assert all(r.instruction == "SYNC_WRITE" for h in emu.goal_history.values() for r in h)


def test_bulk_write_and_fast_bulk_read_mix_addresses():
    with bus([1, 2, 3]) as (emu, port, ph):
        write = sdk.GroupBulkWrite(port, ph)
        write.addParam(1, LED, 1, [1])
        write.addParam(2, PROFILE_VEL, 4, to_u32(77))
        write.addParam(3, RETURN_DELAY, 1, [20])
        assert write.txPacket() == sdk.COMM_SUCCESS
        read = sdk.GroupBulkRead(port, ph)
        read.addParam(1, LED, 1)
        read.addParam(2, PROFILE_VEL, 4)
        read.addParam(3, RETURN_DELAY, 1)
        assert read.fastBulkRead() == sdk.COMM_SUCCESS
        assert (read.getData(1, LED, 1), read.getData(2, PROFILE_VEL, 4), read.getData(3, RETURN_DELAY, 1)) == (
            1,
            77,
            20,
        )


def test_reg_write_waits_for_action():
    with bus([1, 2]) as (emu, port, ph):
        assert ph.regWriteTxRx(port, 1, LED, 1, [1]) == (sdk.COMM_SUCCESS, 0)
        assert ph.read1ByteTxRx(port, 1, LED)[0] == 0
        assert ph.read1ByteTxRx(port, 1, 69)[0] == 1  # Registered Instruction
        assert ph.action(port, dp.BROADCAST_ID) == sdk.COMM_SUCCESS
        wait_until(lambda: ph.read1ByteTxRx(port, 1, LED)[0] == 1)
        assert ph.read1ByteTxRx(port, 1, 69)[0] == 0


def test_broadcast_write_reaches_every_servo_without_replies():
    with bus([1, 2, 3]) as (emu, port, ph):
        assert ph.write1ByteTxOnly(port, dp.BROADCAST_ID, LED, 1) == sdk.COMM_SUCCESS
        wait_until(lambda: all(emu.read_register(i, "led") == 1 for i in (1, 2, 3)))
        assert emu.tx_bytes == 0


# ---------------------------------------------------------------- reboot, reset, errors


def test_hardware_alert_blocks_torque_until_reboot():
    with bus([1], reboot_time_s=0.5) as (emu, port, ph):
        emu.set_hardware_error(1, 0x20)  # overload, in the default Shutdown mask (52)
        assert ph.read1ByteTxRx(port, 1, HW_ERR) == (0x20, sdk.COMM_SUCCESS, 0x80)
        assert "Hardware error" in ph.getRxPacketError(0x80)
        assert ph.write1ByteTxRx(port, 1, TORQUE, 1) == (sdk.COMM_SUCCESS, 0x80)
        assert ph.read1ByteTxRx(port, 1, TORQUE)[0] == 0  # shutdown keeps torque off
        assert ph.reboot(port, 1) == (sdk.COMM_SUCCESS, 0x80)
        assert ph.ping(port, 1)[1] == sdk.COMM_RX_TIMEOUT  # still booting
        wait_until(lambda: ph.ping(port, 1) == (1020, sdk.COMM_SUCCESS, 0))
        assert ph.read1ByteTxRx(port, 1, HW_ERR) == (0, sdk.COMM_SUCCESS, 0)
        assert ph.write1ByteTxRx(port, 1, TORQUE, 1) == (sdk.COMM_SUCCESS, 0)
        assert ph.read1ByteTxRx(port, 1, TORQUE)[0] == 1


def test_reboot_keeps_eeprom_and_resets_ram():
    with bus([1]) as (emu, port, ph):
        ph.write1ByteTxRx(port, 1, RETURN_DELAY, 5)
        ph.write1ByteTxRx(port, 1, LED, 1)
        ph.write4ByteTxRx(port, 1, PROFILE_VEL, 50)
        ph.reboot(port, 1)
        wait_until(lambda: ph.ping(port, 1)[1] == sdk.COMM_SUCCESS)
        assert ph.read1ByteTxRx(port, 1, RETURN_DELAY)[0] == 5
        assert ph.read1ByteTxRx(port, 1, LED)[0] == 0
        assert ph.read4ByteTxRx(port, 1, PROFILE_VEL)[0] == 0


def test_factory_reset_options():
    with bus([7]) as (emu, port, ph):
        ph.write1ByteTxRx(port, 7, RETURN_DELAY, 5)
        assert ph.factoryReset(port, 7, 0x02) == (sdk.COMM_SUCCESS, 0)  # all but ID and baud
        assert ph.read1ByteTxRx(port, 7, RETURN_DELAY) == (250, sdk.COMM_SUCCESS, 0)
        assert ph.factoryReset(port, 7, 0x01) == (sdk.COMM_SUCCESS, 0)  # all but ID: back to 57600 bps
        assert ph.ping(port, 7)[1] == sdk.COMM_RX_TIMEOUT
        assert port.setBaudRate(57600)
        assert ph.ping(port, 7) == (1020, sdk.COMM_SUCCESS, 0)
        assert ph.factoryReset(port, 7, 0xFF) == (sdk.COMM_SUCCESS, 0)  # answered by ID 7, then it is ID 1
        assert ph.ping(port, 7)[1] == sdk.COMM_RX_TIMEOUT
        assert ph.ping(port, 1) == (1020, sdk.COMM_SUCCESS, 0)


def test_corrupt_instruction_and_unknown_instruction_get_error_replies():
    with bus([1]) as (emu, port, ph):
        raw = bytearray(dp.encode_instruction(1, dp.READ, bytes([132, 0, 4, 0])))
        raw[-1] ^= 0xFF
        port.writePort(bytes(raw))
        port.setPacketTimeout(11)
        rx, result = ph.rxPacket(port, False)
        assert result == sdk.COMM_SUCCESS and rx[8] == dp.ERR_CRC
        port.writePort(dp.encode_instruction(1, 0x77))
        port.setPacketTimeout(11)
        rx, result = ph.rxPacket(port, False)
        assert result == sdk.COMM_SUCCESS and rx[8] == dp.ERR_INSTRUCTION
        assert emu.crc_errors == 1


# ---------------------------------------------------------------- fault injection


def test_dropped_and_corrupted_replies_are_what_the_sdk_reports():
    with bus([1, 2]) as (emu, port, ph):
        emu.drop_replies(1, 1)
        assert ph.write1ByteTxRx(port, 1, LED, 1)[0] == sdk.COMM_RX_TIMEOUT
        assert ph.read1ByteTxRx(port, 1, LED) == (1, sdk.COMM_SUCCESS, 0)  # the write itself happened
        emu.corrupt_replies(2, 2)
        assert ph.ping(port, 2)[1] == sdk.COMM_RX_CORRUPT
        assert ph.read1ByteTxRx(port, 2, LED)[1] == sdk.COMM_RX_CORRUPT
        assert ph.ping(port, 2)[1] == sdk.COMM_SUCCESS  # the count ran out
        emu.disconnect(2)
        assert ph.write1ByteTxRx(port, 2, LED, 1)[0] == sdk.COMM_RX_TIMEOUT
        emu.clear_faults(2)
        assert ph.read1ByteTxRx(port, 2, LED) == (0, sdk.COMM_SUCCESS, 0)  # a disconnected servo heard nothing


def test_fast_sync_read_chain_breaks_at_a_silent_servo():
    ids = [1, 2, 3, 4]
    with bus(ids) as (emu, port, ph):
        group = sdk.GroupSyncRead(port, ph, PRESENT_POS, 4)
        for i in ids:
            group.addParam(i)
        assert group.fastSyncRead() == sdk.COMM_SUCCESS
        emu.drop_replies(3, 1)  # the reply stops where servo 3's part should start
        assert group.fastSyncRead() == sdk.COMM_RX_CORRUPT
        emu.drop_replies(1, 1)  # the first servo sends the header: nothing at all arrives
        assert group.fastSyncRead() == sdk.COMM_RX_TIMEOUT
        emu.corrupt_replies(2, 1)
        assert group.fastSyncRead() == sdk.COMM_RX_CORRUPT
        assert group.fastSyncRead() == sdk.COMM_SUCCESS


def test_overheating_raises_the_alert_and_switches_torque_off():
    with bus([1]) as (emu, port, ph):
        ph.write1ByteTxRx(port, 1, TORQUE, 1)
        emu.overheat(1)
        temp, result, error = ph.read1ByteTxRx(port, 1, TEMP)
        assert (result, error) == (sdk.COMM_SUCCESS, 0x80) and temp == 85
        assert ph.read1ByteTxRx(port, 1, HW_ERR)[0] & 0x04
        assert ph.read1ByteTxRx(port, 1, TORQUE)[0] == 0
        emu.clear_faults(1)
        assert ph.read1ByteTxRx(port, 1, TEMP)[0] == 25


def test_allowed_range_records_violating_goals():
    with bus([ServoSpec(1, allowed_range=(1800, 2300)), ServoSpec(2)]) as (emu, port, ph):
        goal = sdk.GroupSyncWrite(port, ph, GOAL, 4)
        goal.addParam(1, to_u32(2200))
        goal.addParam(2, to_u32(3900))
        goal.txPacket()
        goal.changeParam(1, to_u32(2400))
        goal.txPacket()
        wait_until(lambda: len(emu.goal_history[1]) == 2)
        assert [(v.servo_id, v.ticks) for v in emu.violations] == [(1, 2400)]


def test_vanishing_port_fails_loudly():
    with bus([1]) as (emu, port, ph):
        assert ph.ping(port, 1)[1] == sdk.COMM_SUCCESS
        emu.vanish()
        # pyserial raises SerialException, or termios.error where its flush meets the closed
        # pty first (once in the full suite); the bus wraps either in a BridgeError
        with pytest.raises((serial.SerialException, termios.error)):
            ph.ping(port, 1)
        with pytest.raises(BridgeError):
            DynamixelBusEmulator(servos=[1, 1])


def test_baud_mismatch_is_silence_and_a_new_baud_moves_the_servo():
    with bus([1], baud=1_000_000) as (emu, port, ph):
        assert port.setBaudRate(57600)
        assert ph.ping(port, 1)[1] == sdk.COMM_RX_TIMEOUT
        assert port.setBaudRate(1_000_000)
        assert ph.write1ByteTxRx(port, 1, 8, 4) == (sdk.COMM_SUCCESS, 0)  # Baud Rate 4 = 2 Mbps
        assert ph.ping(port, 1)[1] == sdk.COMM_RX_TIMEOUT
        assert port.setBaudRate(2_000_000)
        assert ph.ping(port, 1) == (1020, sdk.COMM_SUCCESS, 0)


def test_wire_timing_delays_replies_by_their_bytes_and_the_return_delay():
    # A lower bound only: the emulator must not answer before the bytes could have
    # crossed a 57.6 kbps wire (10 bits per byte) plus 500 us of Return Delay Time.
    with bus([1], baud=57600, wire_timing=True, return_delay_us=500.0) as (emu, port, ph):
        start = time.perf_counter()
        assert ph.ping(port, 1)[1] == sdk.COMM_SUCCESS
        elapsed = time.perf_counter() - start
        assert elapsed >= (10 + 14) * 10 / 57600 + 500e-6


# ---------------------------------------------------------------- protocol 1.0


def test_protocol1_ax12a_and_mx28():
    with bus([(1, "AX-12A"), (2, "MX-28")], protocol=1) as (emu, port, ph):
        assert ph.ping(port, 1) == (12, sdk.COMM_SUCCESS, 0)
        assert ph.ping(port, 2) == (29, sdk.COMM_SUCCESS, 0)
        assert ph.write1ByteTxRx(port, 1, 24, 1) == (sdk.COMM_SUCCESS, 0)
        assert ph.write2ByteTxRx(port, 1, 30, 700) == (sdk.COMM_SUCCESS, 0)
        wait_until(lambda: ph.read2ByteTxRx(port, 1, 36)[0] == 700)
        assert ph.write2ByteTxRx(port, 1, 30, 1100)[1] == sdk.ERRBIT_RANGE  # beyond 0..1023
        ph.write2ByteTxRx(port, 1, 8, 800)  # CCW Angle Limit (protocol 1.0 has no ROM lock)
        assert ph.write2ByteTxRx(port, 1, 30, 900)[1] == sdk.ERRBIT_ANGLE
        sync = sdk.GroupSyncWrite(port, ph, 30, 2)
        sync.addParam(1, [0x20, 0x01])
        sync.addParam(2, [0x00, 0x09])
        assert sync.txPacket() == sdk.COMM_SUCCESS
        wait_until(lambda: emu.read_register(2, "goal_position") == 0x900)
        # GroupBulkRead is broken for protocol 1.0 in dynamixel-sdk 4.1.0 (it passes an
        # extra argument to bulkReadTx), so drive the packet handler directly.
        assert ph.bulkReadTx(port, [2, 1, 30, 2, 2, 30], 6) == sdk.COMM_SUCCESS
        assert ph.readRx(port, 1, 2)[:2] == ([0x20, 0x01], sdk.COMM_SUCCESS)
        assert ph.readRx(port, 2, 2)[:2] == ([0x00, 0x09], sdk.COMM_SUCCESS)
        emu.overheat(1)
        assert ph.read1ByteTxRx(port, 1, 43)[2] & sdk.ERRBIT_OVERHEAT
        emu.corrupt_replies(2, 1)
        assert ph.ping(port, 2)[1] == sdk.COMM_RX_CORRUPT


def test_mixed_protocol_bus_answers_each_protocol_separately():
    with bus([(1, "XM430-W350"), (2, "AX-12A")]) as (emu, port, ph2):
        ph1 = sdk.PacketHandler(1.0)
        assert ph2.ping(port, 1) == (1020, sdk.COMM_SUCCESS, 0)
        assert ph2.ping(port, 2)[1] == sdk.COMM_RX_TIMEOUT
        assert ph1.ping(port, 2) == (12, sdk.COMM_SUCCESS, 0)
        assert ph1.ping(port, 1)[1] == sdk.COMM_RX_TIMEOUT


def test_protocol1_servo_at_57600_answers_a_host_within_uart_tolerance():
    # AX-12A Baud Rate 34 is 2 Mbps / 35 = 57142 bps: 0.8 % off the host's 57600.
    with bus([(1, "AX-12A")], baud=57600, protocol=1) as (emu, port, ph):
        assert emu.read_register(1, "baud_rate") == 34
        assert ph.ping(port, 1) == (12, sdk.COMM_SUCCESS, 0)


def test_bus_watchdog_trips_when_the_host_goes_quiet():
    with bus([1, 2]) as (emu, port, ph):
        assert ph.write1ByteTxRx(port, 1, 98, 2) == (sdk.COMM_SUCCESS, 0)  # 40 ms
        ph.write4ByteTxRx(port, 1, GOAL, 3000)
        ph.write1ByteTxRx(port, 1, TORQUE, 1)
        time.sleep(0.15)
        assert ph.read1ByteTxRx(port, 1, 98) == (0xFF, sdk.COMM_SUCCESS, 0)  # -1: watchdog error
        assert ph.write4ByteTxRx(port, 1, GOAL, 2500) == (sdk.COMM_SUCCESS, 4)  # Data Range Error
        assert ph.write1ByteTxRx(port, 1, 98, 0) == (sdk.COMM_SUCCESS, 0)
        assert ph.write4ByteTxRx(port, 1, GOAL, 2500) == (sdk.COMM_SUCCESS, 0)


def test_standalone_emulator_process_serves_another_process(tmp_path):
    import signal
    import subprocess
    import sys

    link = tmp_path / "ttyDXL"
    proc = subprocess.Popen(
        [sys.executable, "-m", "ros_free_bridge.emulators", "--ids", "1-3,7", "--baud", "2000000", "--link", str(link)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        path = proc.stdout.readline().strip()
        assert path.startswith("/dev/") and os.path.realpath(link) == path
        port = sdk.PortHandler(str(link))
        assert port.openPort() and port.setBaudRate(2_000_000)
        ph = sdk.PacketHandler(2.0)
        assert [ph.ping(port, i)[:2] for i in (1, 3, 7)] == [(1020, sdk.COMM_SUCCESS)] * 3
        assert ph.ping(port, 4)[1] == sdk.COMM_RX_TIMEOUT
        port.closePort()
    finally:
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=10) == 0
    assert not link.exists()
    bad = subprocess.run(
        [sys.executable, "-m", "ros_free_bridge.emulators", "--ids", "1-x"], capture_output=True, text=True
    )
    assert bad.returncode == 2 and "--ids: cannot read '1-x'" in bad.stderr


def test_stuck_servo_reports_stall_current_and_does_not_move():
    with bus([1, 2]) as (emu, port, ph):
        emu.stick(1)
        for i in (1, 2):
            ph.write1ByteTxRx(port, i, TORQUE, 1)
            ph.write4ByteTxRx(port, i, GOAL, 2400)
        wait_until(lambda: ph.read4ByteTxRx(port, 2, PRESENT_POS)[0] == 2400)
        assert ph.read4ByteTxRx(port, 1, PRESENT_POS)[0] == 2048
        current = ph.read2ByteTxRx(port, 1, 126)[0]
        assert current == round(2.3 / 2.69e-3)  # stall current, 2.69 mA units
        assert ph.read2ByteTxRx(port, 2, 126)[0] == 0  # the free one holds at no load


@pytest.mark.parametrize("baud", [57600, 115200, 1_000_000, 2_000_000, 3_000_000, 4_000_000])
def test_every_sdk_baud_rate_works_on_the_pty(baud):
    with bus([1], baud=baud) as (emu, port, ph):
        assert ph.ping(port, 1) == (1020, sdk.COMM_SUCCESS, 0)
        assert emu.read_register(1, "baud_rate") == load_servo_model("XM430-W350").baud_to_register(baud)


def test_unthreaded_emulator_answers_only_when_pumped():
    emu = DynamixelBusEmulator(servos=[1, 2]).start(threaded=False)
    try:
        port = sdk.PortHandler(emu.port_path)
        assert port.openPort()
        ph = sdk.PacketHandler(2.0)
        assert ph.write1ByteTxOnly(port, dp.BROADCAST_ID, LED, 1) == sdk.COMM_SUCCESS
        assert emu.read_register(1, "led") == 0  # nothing handled yet
        assert emu.pump() == 1
        assert emu.read_register(1, "led") == emu.read_register(2, "led") == 1
        ph.readTx(port, 2, LED, 1)
        emu.pump()
        assert ph.readRx(port, 2, 1) == ([1], sdk.COMM_SUCCESS, 0)
        port.closePort()
    finally:
        emu.stop()
    with pytest.raises(BridgeError, match="threaded=False"):
        with DynamixelBusEmulator(servos=[1]) as threaded:
            threaded.pump()


def test_changing_an_id_is_answered_from_the_old_id():
    with bus([1, 2]) as (emu, port, ph):
        assert ph.write1ByteTxRx(port, 1, 7, 9) == (sdk.COMM_SUCCESS, 0)  # ID(7) := 9
        assert ph.ping(port, 1)[1] == sdk.COMM_RX_TIMEOUT
        assert ph.ping(port, 9) == (1020, sdk.COMM_SUCCESS, 0)
        assert ph.write1ByteTxRx(port, 9, 7, 2)[1] == 0  # a clash is accepted...
        assert sorted(s.servo_id for s in emu.servos) == [2, 2]
        assert ph.ping(port, 2)[1] == sdk.COMM_RX_CORRUPT  # ...both answer at once
        ph.write1ByteTxRx(port, 2, LED, 1)
        assert [s.get("led") for s in emu.servos] == [1, 1]  # and both obey
        assert emu.instruction_counts["PING"] == 3


def test_broadcast_ping_and_clear():
    with bus([1, 5, (9, "XL330-M288")]) as (emu, port, ph):
        found, result = ph.broadcastPing(port)  # the SDK listens for its full window (~0.8 s)
        assert result == sdk.COMM_SUCCESS
        assert {i: model for i, (model, _fw) in found.items()} == {1: 1020, 5: 1020, 9: 1200}
        assert ph.clearMultiTurn(port, 1) == (sdk.COMM_SUCCESS, 0)


def test_protocol1_reg_write_action_and_status_return_level():
    with bus([(1, "AX-12A"), (2, "AX-12A")], protocol=1) as (emu, port, ph):
        assert ph.regWriteTxRx(port, 1, 25, 1, [1]) == (sdk.COMM_SUCCESS, 0)  # LED, registered
        assert ph.read1ByteTxRx(port, 1, 44)[0] == 1  # Registered
        assert ph.read1ByteTxRx(port, 1, 25)[0] == 0
        assert ph.action(port, dp.BROADCAST_ID) == sdk.COMM_SUCCESS
        wait_until(lambda: ph.read1ByteTxRx(port, 1, 25)[0] == 1)
        assert ph.write1ByteTxRx(port, 2, 16, 1)[0] == sdk.COMM_RX_TIMEOUT  # level 1: writes unanswered
        assert ph.read1ByteTxRx(port, 2, 16) == (1, sdk.COMM_SUCCESS, 0)
        port.writePort(dp.encode_instruction1(1, 0x77))  # unknown instruction
        port.setPacketTimeout(6)
        rx, result = ph.rxPacket(port)
        assert result == sdk.COMM_SUCCESS and rx[4] == sdk.ERRBIT_INSTRUCTION
