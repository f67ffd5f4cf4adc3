"""Servo model tables (firmware_cfg/servo_models/*.yaml) and their loader."""

from __future__ import annotations

import math

import numpy as np
import pytest

from firmware_cfg import ConfigError
from firmware_cfg.servo_models import (
    MODELS_DIR,
    all_servo_models,
    load_servo_model,
    load_servo_model_file,
)


def test_bundled_models_and_lookups():
    by_name = {m.name: (m.model_number, m.protocol) for m in all_servo_models()}
    assert by_name == {
        "XM430-W350": (1020, 2),
        "XL430-W250": (1060, 2),
        "XL330-M288": (1200, 2),
        "MX-28": (29, 1),
        "AX-12A": (12, 1),
    }
    assert load_servo_model("xm430-w350") is load_servo_model(1020) is load_servo_model("1020")
    with pytest.raises(ConfigError, match="unknown servo model 'XM999'.*XM430-W350"):
        load_servo_model("XM999")
    with pytest.raises(ConfigError, match="unknown servo model number 4242"):
        load_servo_model(4242)


# (model, register, address, size, access, area) spot checks against the e-Manual tables.
ADDRESSES = [
    ("XM430-W350", "torque_enable", 64, 1, "RW", "RAM"),
    ("XM430-W350", "hardware_error_status", 70, 1, "R", "RAM"),
    ("XM430-W350", "goal_position", 116, 4, "RW", "RAM"),
    ("XM430-W350", "present_position", 132, 4, "R", "RAM"),
    ("XM430-W350", "present_current", 126, 2, "R", "RAM"),
    ("XM430-W350", "return_delay_time", 9, 1, "RW", "EEPROM"),
    ("XM430-W350", "current_limit", 38, 2, "RW", "EEPROM"),
    ("XL430-W250", "present_load", 126, 2, "R", "RAM"),
    ("XL330-M288", "pwm_slope", 62, 1, "RW", "EEPROM"),
    ("MX-28", "goal_position", 30, 2, "RW", "RAM"),
    ("MX-28", "goal_acceleration", 73, 1, "RW", "RAM"),
    ("AX-12A", "present_position", 36, 2, "R", "RAM"),
    ("AX-12A", "ccw_angle_limit", 8, 2, "RW", "EEPROM"),
]


@pytest.mark.parametrize("model,name,address,size,access,area", ADDRESSES)
def test_register_addresses_match_the_emanual(model, name, address, size, access, area):
    r = load_servo_model(model).register(name)
    assert (r.address, r.size, r.access, r.area) == (address, size, access, area)


def test_initial_values_and_ranges_differ_per_model():
    xm, xl, x3 = (load_servo_model(n) for n in ("XM430-W350", "XL430-W250", "XL330-M288"))
    assert (
        xm.register("velocity_limit").initial,
        xl.register("velocity_limit").initial,
        x3.register("velocity_limit").initial,
    ) == (350, 265, 445)
    assert (
        xm.register("temperature_limit").initial,
        xl.register("temperature_limit").initial,
        x3.register("temperature_limit").initial,
    ) == (80, 72, 70)
    assert x3.register("current_limit").range == (0, 1750)
    assert not xl.has("current_limit") and not xl.has("goal_current")
    with pytest.raises(ConfigError, match="XL430-W250: no register named 'present_current'"):
        xl.register("present_current")


def test_units_and_ratings():
    xm, xl, x3, ax = (load_servo_model(n) for n in ("XM430-W350", "XL430-W250", "XL330-M288", "AX-12A"))
    assert (xm.velocity_rpm, xm.current_ma, x3.current_ma, xl.load_percent) == (0.229, 2.69, 1.0, 0.1)
    assert xm.current_to_amps(1000) == pytest.approx(2.69)
    assert x3.amps_to_current(1.0) == 1000
    with pytest.raises(ConfigError, match="no current sensing"):
        xl.current_to_amps(10)
    assert (xm.ratings.stall_torque_nm, xm.ratings.no_load_speed_rpm, xm.ratings.rated_voltage_v) == (4.1, 46.0, 12.0)
    assert xm.no_load_speed_rad_s == pytest.approx(46 * 2 * math.pi / 60)
    assert xm.velocity_to_rad_s(100) == pytest.approx(100 * 0.229 * 2 * math.pi / 60)
    assert xm.rad_s_to_velocity(xm.velocity_to_rad_s(123)) == 123
    assert xm.voltage_to_volts(121) == pytest.approx(12.1)
    assert xm.return_delay_s(250) == pytest.approx(500e-6)
    assert ax.velocity_rpm == 0.111 and ax.ratings.stall_torque_nm == 1.5


def test_radians_to_ticks_with_direction_and_offset():
    xm, ax = load_servo_model("XM430-W350"), load_servo_model("AX-12A")
    assert xm.rad_to_ticks(0.0) == 2048
    assert xm.rad_to_ticks(math.pi / 2) == 2048 + 1024
    assert xm.rad_to_ticks(math.pi / 2, direction=-1, offset_ticks=10) == 2048 - 1024 + 10
    assert ax.rad_to_ticks(math.radians(150)) - 512 == 512  # 1024 ticks over 300 deg
    rad = np.linspace(-2.0, 2.0, 9)
    ticks = xm.rad_to_ticks(rad, direction=-1, offset_ticks=-37)
    assert ticks.dtype == np.int64
    assert np.allclose(xm.ticks_to_rad(ticks, direction=-1, offset_ticks=-37), rad, atol=math.pi / 4096)


def test_register_encoding():
    xm, ax = load_servo_model("XM430-W350"), load_servo_model("AX-12A")
    vel = xm.register("present_velocity")
    assert vel.encode(-1) == b"\xff\xff\xff\xff" and vel.decode(b"\xfe\xff\xff\xff") == -2
    speed = ax.register("present_speed")  # sign-magnitude, bit 10 = CW
    assert speed.encode(-300) == (1024 + 300).to_bytes(2, "little") and speed.decode(speed.encode(-300)) == -300
    assert xm.register("goal_position").in_range(4095) and not xm.register("status_return_level").in_range(3)


def test_baud_tables():
    xm, x3, ax, mx = (load_servo_model(n) for n in ("XM430-W350", "XL330-M288", "AX-12A", "MX-28"))
    assert xm.baud_to_register(2_000_000) == 4 and xm.register_to_baud(7) == 4_500_000
    with pytest.raises(ConfigError, match="does not support 4500000 bps"):
        x3.baud_to_register(4_500_000)
    assert ax.baud_to_register(1_000_000) == 1 and ax.register_to_baud(34) == 57142
    assert ax.register_to_baud(2) == 666667  # 2 Mbps / (value + 1)
    assert ax.baud_to_register(57600) == 34  # within the 3 % a UART tolerates
    assert mx.register_to_baud(250) == 2_250_000
    with pytest.raises(ConfigError, match="Baud Rate value 9"):
        xm.register_to_baud(9)


def test_every_table_is_consistent():
    for m in all_servo_models():
        regs = sorted(m.registers.values(), key=lambda r: r.address)
        assert all(a.end <= b.address for a, b in zip(regs, regs[1:])), m.name
        assert m.register("model_number").initial == m.model_number
        for r in regs:
            if r.initial is not None and r.range is not None and r.writable:
                assert r.in_range(r.initial), (m.name, r.name)
        assert m.register_at(m.register("goal_position").address).name == "goal_position"
        assert m.position.min_tick <= m.position.center_tick <= m.position.max_tick


BASE = """
name: TEST-1
model_number: 5
protocol: 2
position: {ticks_per_turn: 4096, min_tick: 0, max_tick: 4095, center_tick: 2048}
units: {velocity_rpm: 0.229, voltage_v: 0.1, temperature_c: 1.0, return_delay_us: 2.0}
ratings: {stall_torque_nm: 1, stall_current_a: 1, no_load_speed_rpm: 50, rated_voltage_v: 12, voltage_range_v: [10, 14]}
baud_rates: {3: 1000000}
registers:
  model_number: {address: 0, size: 2, access: R, area: EEPROM, initial: 5}
  id: {address: 7, size: 1, access: RW, area: EEPROM, initial: 1}
  return_delay_time: {address: 9, size: 1, access: RW, area: EEPROM, initial: 0}
  torque_enable: {address: 64, size: 1, access: RW, area: RAM, initial: 0}
  goal_position: {address: 116, size: 4, access: RW, area: RAM, initial: 0}
  present_position: {address: 132, size: 4, access: R, area: RAM, initial: 0}
"""


@pytest.mark.parametrize(
    "edit,message",
    [
        (("registers:", "regs:"), "missing field 'registers'"),
        (("{address: 9, size: 1", "{address: 6, size: 4"), "overlap"),
        (
            ("access: R, area: RAM, initial: 0}", "access: X, area: RAM, initial: 0}"),
            "registers.present_position: access must be",
        ),
        (("protocol: 2", "protocol: 3"), "protocol must be 1 or 2"),
        (
            ("size: 4, access: RW, area: RAM, initial: 0}", "size: 3, access: RW, area: RAM, initial: 0}"),
            "size 1, 2 or 4",
        ),
        (("initial: 5}", "initial: 6}"), "model_number.initial"),
        (("name: TEST-1", "name: [1]"), "field 'name' must be a str"),
    ],
)
def test_bad_model_files_name_the_file_and_field(tmp_path, edit, message):
    path = tmp_path / "bad.yaml"
    path.write_text(BASE.replace(*edit, 1))
    with pytest.raises(ConfigError, match=message) as err:
        load_servo_model_file(path)
    assert str(path) in str(err.value)
    good = tmp_path / "good.yaml"
    good.write_text(BASE)
    assert load_servo_model_file(good).model_number == 5


def test_model_files_cite_their_source():
    for path in MODELS_DIR.glob("*.yaml"):
        assert "emanual.robotis.com" in path.read_text(), path.name
