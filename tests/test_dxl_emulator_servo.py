"""The emulated servo's motor, thermal and error model, on a controlled clock (no bus)."""

from __future__ import annotations

import math

import pytest

from firmware_cfg.servo_models import load_servo_model
from ros_free_bridge.emulators.emulated_servo import (
    HW_INPUT_VOLTAGE,
    HW_OVERHEATING,
    HW_OVERLOAD,
    EmulatedServo,
)


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def make(model="XM430-W350", position=2048.0):
    clock = Clock()
    return EmulatedServo(load_servo_model(model), 1, position, clock=clock), clock


def u32(v: int) -> bytes:
    return (v & 0xFFFFFFFF).to_bytes(4, "little")


def test_position_moves_at_profile_velocity():
    servo, clock = make()
    servo.write(112, u32(100))  # Profile Velocity 100 x 0.229 rpm = 22.9 rpm
    servo.write(116, u32(3000))
    servo.write(64, b"\x01")
    clock.t += 0.1
    servo.advance()
    expected = 100 * 0.229 / 60 * 4096 * 0.1  # ticks in 0.1 s
    assert servo.position - 2048 == pytest.approx(expected, rel=1e-9)
    assert servo.get("present_velocity") == 100
    assert servo.get("moving") == 1
    clock.t += 10.0
    servo.advance()
    assert servo.get("present_position") == 3000 and servo.get("present_velocity") == 0 and servo.get("moving") == 0


def test_speed_is_capped_by_velocity_limit_and_no_load_speed():
    servo, clock = make()
    servo.write(116, u32(4000))
    servo.write(64, b"\x01")
    clock.t += 0.05
    servo.advance()
    # Profile Velocity 0 = no profile: Velocity Limit 350 units (80 rpm) > no-load 46 rpm at 12 V.
    assert servo.position - 2048 == pytest.approx(46.0 / 60 * 4096 * 0.05)
    servo.write(64, b"\x00")
    servo.write(44, u32(100))  # Velocity Limit 22.9 rpm (EEPROM, torque off)
    servo.write(64, b"\x01")
    start = servo.position
    clock.t += 0.05
    servo.advance()
    assert servo.position - start == pytest.approx(100 * 0.229 / 60 * 4096 * 0.05)


def test_torque_off_ignores_goal_and_torque_on_goes_to_the_stored_goal():
    servo, clock = make()
    servo.write(116, u32(2500))
    clock.t += 1.0
    servo.advance()
    assert servo.get("present_position") == 2048
    servo.push(1000)
    assert servo.get("present_position") == 1000
    servo.write(64, b"\x01")  # the stale goal is where it goes: the transport must write goal = present first
    clock.t += 1.0
    servo.advance()
    assert servo.get("present_position") == 2500


def test_write_rules_and_gap_bytes():
    servo, _ = make()
    # 64 Torque Enable, 65 LED, 66-67 unassigned, 68 Status Return Level: one write, gaps ignored
    assert servo.write(64, bytes([0, 1, 0xAA, 0xBB, 1])).ok
    assert (servo.get("led"), servo.get("status_return_level")) == (1, 1)
    assert servo.write(116, u32(100)[:2]).error == "length"
    assert servo.write(132, u32(0)).error == "access"
    assert servo.write(68, b"\x05").error == "range"
    servo.write(64, b"\x01")
    assert servo.write(31, b"\x46").error == "access"  # EEPROM while torque on
    assert servo.write(116, u32(5000)).error == "limit"  # beyond Max Position Limit 4095
    assert servo.get("temperature_limit") == 80 and servo.get("goal_position") == 2048
    assert servo.read(0, 2) == (1020).to_bytes(2, "little")
    assert servo.read(140, 100) is None  # past the end of the table


def test_extended_position_mode_takes_goals_beyond_one_turn():
    servo, clock = make()
    assert servo.write(11, b"\x04").ok  # Operating Mode 4: extended position
    servo.write(64, b"\x01")
    assert servo.write(116, u32(6000)).ok
    clock.t += 5.0
    servo.advance()
    assert servo.get("present_position") == 6000


def test_stalled_servo_overloads_then_shuts_down_until_reboot():
    servo, clock = make()
    servo.write(64, b"\x01")
    servo.faults.stuck = True
    servo.write(116, u32(2600))
    clock.t += 0.5
    servo.advance()
    assert servo.get("present_current") == round(2.3 * 1000 / 2.69)  # stall current, in 2.69 mA units
    assert servo.hardware_error() == 0 and servo.torque_enabled
    clock.t += 0.6
    servo.advance()
    assert servo.get("hardware_error_status") == HW_OVERLOAD
    assert not servo.torque_enabled and servo.status_error() == 0x80
    assert servo.write(64, b"\x01").ok and not servo.torque_enabled  # refused while shut down
    servo.faults.stuck = False
    servo.reboot(0.1)
    assert servo.hardware_error() == 0 and servo.booting_until == pytest.approx(clock.t + 0.1)
    assert servo.get("goal_position") == servo.get("present_position") == 2048


def test_stall_current_heats_the_motor_to_an_overheating_shutdown():
    servo, clock = make()
    servo.write(63, b"\x04")  # Shutdown on overheating only (not overload)
    servo.write(64, b"\x01")
    servo.faults.stuck = True
    servo.write(116, u32(2600))
    clock.t += 60.0
    servo.advance()
    # T(t) = T_ss + (T0 - T_ss) e^(-t/tau), T_ss = 25 + 60 at stall, tau = 60 s
    assert servo.temperature_c == pytest.approx(85 - 60 * math.exp(-1.0))
    assert servo.hardware_error() == HW_OVERLOAD and servo.torque_enabled
    clock.t += 300.0
    servo.advance()
    assert servo.hardware_error() & HW_OVERHEATING and not servo.torque_enabled
    assert servo.get("present_temperature") >= 80


def test_low_supply_voltage_sets_the_voltage_bit_without_shutdown_by_default():
    servo, clock = make()
    servo.write(64, b"\x01")
    servo.faults.supply_v = 9.0  # below Min Voltage Limit 9.5 V
    clock.t += 0.01
    servo.advance()
    assert servo.get("hardware_error_status") == HW_INPUT_VOLTAGE
    assert servo.get("present_input_voltage") == 90
    assert servo.torque_enabled  # bit 0 is not in the default Shutdown mask 52


def test_homing_offset_shifts_present_position():
    servo, _ = make()
    assert servo.write(20, u32(-100)).ok
    assert servo.get("present_position") == 1948


def test_protocol1_lock_register_protects_eeprom_and_errors_map_to_bits():
    servo, clock = make("AX-12A", 512)
    assert servo.write(5, b"\x00").ok  # EEPROM write with torque off
    servo.write(24, b"\x01")
    assert servo.write(5, b"\x01").ok  # protocol 1.0: no ROM lock by torque
    servo.write(47, b"\x01")  # Lock = 1
    assert servo.write(5, b"\x02").error == "access"
    servo.faults.held_temperature_c = 75.0  # Temperature Limit 70
    clock.t += 0.01
    servo.advance()
    assert servo.status_error() == 0x04  # protocol 1.0 overheating bit
    assert servo.get("present_load") == 0


def test_bus_watchdog_stops_a_servo_that_hears_nothing():
    servo, clock = make()
    assert servo.write(98, b"\x05").ok  # Bus Watchdog 5 x 20 ms = 100 ms
    servo.write(116, u32(4000))
    servo.write(64, b"\x01")
    clock.t += 0.08
    servo.heard()  # a packet at 80 ms restarts the interval
    clock.t += 0.15  # silence from 80 ms: fires at 180 ms
    servo.advance()
    stop = 2048 + 46.0 / 60 * 4096 * 0.18  # moved at no-load speed until the watchdog fired
    assert servo.get("bus_watchdog") == -1 and servo.get("goal_position") == round(stop)
    assert servo.position == round(stop)  # and holds there
    assert servo.write(116, u32(3000)).error == "range"  # goals are read-only now
    assert servo.goal_history[-1].accepted is False
    assert servo.write(98, b"\x00").ok  # writing 0 clears the error
    assert servo.write(116, u32(3000)).ok


def test_bus_watchdog_is_idle_with_torque_off():
    servo, clock = make()
    servo.write(98, b"\x01")
    clock.t += 1.0
    servo.advance()
    assert servo.get("bus_watchdog") == 1
