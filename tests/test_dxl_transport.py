"""The Dynamixel transport: the real dynamixel-sdk over a pty against the byte-level bus
emulator. Every fault ends in a named error or a recovery, and no goal outside the
configured limits reaches a servo (asserted on the emulator side)."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from firmware_cfg.config import load_config, parse_config, robot_config_path
from firmware_cfg.servo_models import load_servo_model
from ros_free_bridge.commands.servo import start_emulator
from ros_free_bridge.dynamixel.port import set_latency_timer
from ros_free_bridge.dynamixel.protocol import decode_hardware_error
from ros_free_bridge.dynamixel.servos import servo_register_settings, servo_tick_limits
from ros_free_bridge.dynamixel.transport import DynamixelTransport
from ros_free_bridge.emulators import DynamixelBusEmulator, ServoSpec
from ros_free_bridge.errors import BridgeError
from ros_free_bridge.transports.base import Transport

XM = load_servo_model("XM430-W350")
LAT = 30.0  # ms of reply-timeout latency: generous, the emulator shares this process's GIL


def small_bus(n=4, **servo_overrides):
    servos = []
    for i in range(n):
        s = {
            "id": i + 1,
            "joint": f"j{i + 1}",
            "model": "XM430-W350",
            "limits": [-1.0, 1.0],
            "direction": -1 if i % 2 else 1,
            "zero_offset": 0.05 * i,
            "pid": {"p": 900, "i": 10, "d": 5},
            "profile_velocity": 3.0,
            "return_delay_us": 0,
        }
        s.update(servo_overrides)
        servos.append(s)
    return parse_config(
        {
            "robot": "t",
            "buses": [{"name": "b", "port": "/dev/null", "baud": 1000000, "protocol": "2.0", "servos": servos}],
        }
    ).buses[0]


def guarded_emulator(bus, **kw):
    """An emulator started from ``bus`` whose servos flag any goal outside the config's
    limits (in ticks) as a violation."""
    emu = start_emulator(bus, provisioned=True, **kw)
    for s in bus.servos:
        emu.allowed_range(s.id, *servo_tick_limits(s, XM))
    return emu


def make(bus, emu, **kw):
    kw.setdefault("latency_ms", LAT)
    return DynamixelTransport(bus, port=emu.port_path, **kw)


def wait_for(pred, timeout=3.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.01)
    return False


def test_units_direction_offset_and_settings():
    bus = small_bus()
    emu = guarded_emulator(bus)
    try:
        start = {1: 2300, 2: 1900, 3: 2048, 4: 2600}
        for sid, t in start.items():
            emu.push(sid, t)
        t = make(bus, emu)
        assert isinstance(t, Transport)
        with t:
            s = t.read_state()
            for i, sv in enumerate(bus.servos):
                expect = sv.direction * ((start[sv.id] - 2048) * 2 * math.pi / 4096 - sv.zero_offset)
                assert s.position[i] == pytest.approx(expect, abs=1e-9)
            # RAM settings applied at open
            assert emu.read_register(2, "position_p_gain") == 900 and emu.read_register(2, "position_i_gain") == 10
            assert emu.read_register(2, "profile_velocity") == XM.rad_s_to_velocity(3.0)
            t.set_torque(True)
            goal = np.array([0.5, 0.5, -0.25, 0.0])
            t.write_goal(goal)
            for i, sv in enumerate(bus.servos):  # SYNC_WRITE has no reply: wait for the emulator to take it
                want = round(2048 + (sv.direction * goal[i] + sv.zero_offset) * 4096 / (2 * math.pi))
                assert wait_for(lambda sv=sv, want=want: emu.read_register(sv.id, "goal_position") == want), (
                    sv.id,
                    want,
                )
            assert wait_for(lambda: np.allclose(t.read_state().position, goal, atol=2e-3))
            # every slow field gets refreshed within n cycles
            for _ in range(len(bus.servos)):
                s = t.read_state()
            assert np.all(np.isfinite(s.temperature)) and np.allclose(s.voltage, 12.0)
            assert np.all(np.isfinite(s.velocity)) and np.all(np.isfinite(s.effort))
            assert s.errors == {}
        assert emu.violations == []
    finally:
        emu.stop()


def test_torque_on_only_after_goal_equals_present():
    bus = small_bus(2)
    emu = guarded_emulator(bus)
    try:
        emu.push(1, 2500)
        emu.write_register(1, "goal_position", 2100)  # a stale goal far from the horn
        with make(bus, emu) as t:
            t.set_torque(True)
            hist = emu.goal_history[1]
            enabled_at = [r for r in hist if r.accepted][-1]
            assert enabled_at.ticks == 2500
            time.sleep(0.1)
            assert abs(emu.servo(1).position - 2500) < 1.0  # it did not jump to the stale goal
            assert emu.read_register(1, "torque_enable") == 1
    finally:
        emu.stop()


@pytest.mark.parametrize("policy, torque_after", [("hold", 1), ("limp", 0)])
def test_close_applies_stop_policy_and_releases_the_port(policy, torque_after):
    bus = small_bus(2)
    emu = guarded_emulator(bus)
    try:
        t = make(bus, emu, stop_policy=policy)
        t.open()
        t.set_torque(True)
        t.write_goal(np.array([0.3, 0.3]))
        t.close()
        t.close()  # twice is fine
        assert [emu.read_register(i, "torque_enable") for i in (1, 2)] == [torque_after] * 2
        with make(bus, emu) as again:  # the port is free again
            again.read_state()
    finally:
        emu.stop()


def test_port_is_exclusive_and_never_left_in_use_after_an_error():
    bus = small_bus(2)
    emu = guarded_emulator(bus)
    try:
        with make(bus, emu, retries=1) as t:
            with pytest.raises(BridgeError, match="cannot open"):
                make(bus, emu).open()
            emu.drop_replies(2, None)
            with pytest.raises(BridgeError, match=r"servo ID 2 \(j2\): no status packet for present position"):
                t.read_state()
            emu.clear_faults()
            t.read_state()  # no "port is in use" afterwards
            assert t.bus.port.is_using is False
    finally:
        emu.stop()


def test_limits_never_exceeded_on_the_bus():
    bus = small_bus(3)
    emu = guarded_emulator(bus)
    try:
        with make(bus, emu) as t:
            t.set_torque(True)
            n_before = sum(len(h) for h in emu.goal_history.values())
            for bad in ([1.2, 0, 0], [0, -1.01, 0], [0, 0, np.nan], [0, 0, np.inf]):
                with pytest.raises(BridgeError, match="outside the joint limits .*; refusing"):
                    t.write_goal(np.array(bad))
            assert sum(len(h) for h in emu.goal_history.values()) == n_before
            rng = np.random.default_rng(0)
            for _ in range(30):
                t.write_goal(rng.uniform(t.lower, t.upper))
            t.write_goal(t.upper)
            t.write_goal(t.lower)
            t.read_state()
        assert emu.violations == []
        assert all(r.accepted for h in emu.goal_history.values() for r in h)
    finally:
        emu.stop()


def test_eeprom_limits_narrow_the_config_limits():
    bus = small_bus(1, direction=1, zero_offset=0.0)
    emu = guarded_emulator(bus)
    try:
        emu.write_register(1, "max_position_limit", 2048 + 512)  # +45°
        with make(bus, emu) as t:
            assert t.upper[0] == pytest.approx(math.pi / 4)
            assert t.lower[0] == pytest.approx(-1.0, abs=XM.ticks_to_rad(2049))
            with pytest.raises(BridgeError, match="outside the joint limits"):
                t.write_goal(np.array([0.9]))
            assert any("narrowed" in n for n in t.stats.notes)
    finally:
        emu.stop()


def test_model_mismatch_and_missing_servo_are_named():
    bus = small_bus(3)
    emu = DynamixelBusEmulator([ServoSpec(1), ServoSpec(2, "XL430-W250"), ServoSpec(3)], baud=1_000_000).start()
    try:
        with pytest.raises(
            BridgeError, match=r"servo ID 2 \(j2\): model number 1060 \(XL430-W250\) but the config says XM430-W350"
        ):
            make(bus, emu).open()
    finally:
        emu.stop()
    emu = guarded_emulator(bus)
    try:
        emu.disconnect(3)
        with pytest.raises(BridgeError, match=r"servo ID 3 \(j3\) .*no answer to PING after 3 tries"):
            make(bus, emu).open()
        make(bus, emu).close()  # never opened: a no-op
    finally:
        emu.stop()


def test_corrupted_and_dropped_replies_are_retried():
    bus = small_bus(3)
    emu = guarded_emulator(bus)
    try:
        with make(bus, emu, retries=2) as t:
            emu.corrupt_replies(2, 1)
            emu.drop_replies(3, 1)
            t.read_state()
            assert t.stats.read_retries >= 1
            emu.corrupt_replies(1, 5)
            with pytest.raises(BridgeError, match=r"servo ID 1 \(j1\)|servo ID 1"):
                for _ in range(3):
                    t.read_state()
    finally:
        emu.stop()


def test_overload_alert_is_decoded_and_recovered_by_reboot():
    bus = small_bus(3)
    emu = guarded_emulator(bus)
    try:
        with make(bus, emu, slow_per_cycle=3) as t:
            t.set_torque(True)
            t.write_goal(np.array([0.2, 0.2, 0.2]))
            emu.set_hardware_error(2, 0x20)  # overload; Shutdown(63) switches its torque off
            s = t.read_state()
            assert t.stats.reboots == 1 and t.stats.alerts == 1
            assert "j2" not in s.errors and s.torque_enabled.all()
            assert emu.read_register(2, "hardware_error_status") == 0
            assert emu.read_register(2, "torque_enable") == 1
            # after the reboot the goal was set to the present position before torque on
            present = emu.read_register(2, "present_position")
            assert abs(emu.read_register(2, "goal_position") - present) <= 1
            assert emu.read_register(2, "position_p_gain") == 900  # settings re-applied
            assert any("rebooted after overload" in n for n in t.stats.notes)
        assert emu.violations == []
    finally:
        emu.stop()


def test_overheating_is_reported_not_rebooted():
    bus = small_bus(2)
    emu = guarded_emulator(bus)
    try:
        with make(bus, emu, slow_per_cycle=2) as t:
            t.set_torque(True)
            emu.overheat(1)
            s = t.read_state()
            assert "overheating" in s.errors["j1"] and "policy does not reboot" in s.errors["j1"]
            assert t.stats.reboots == 0
            assert not s.torque_enabled[0] and s.torque_enabled[1]
    finally:
        emu.stop()


def test_persistent_hardware_error_after_reboot_is_an_error():
    bus = small_bus(2)
    emu = guarded_emulator(bus)
    try:
        with make(bus, emu, slow_per_cycle=2) as t:
            t.set_torque(True)
            emu.set_hardware_error(1, 0x10, survives_reboot=True)  # electrical shock, stays
            s = t.read_state()
            assert "electrical shock" in s.errors["j1"] and "persists after REBOOT" in s.errors["j1"]
            assert emu.read_register(1, "torque_enable") == 0
    finally:
        emu.stop()


def test_vanished_port_is_a_bridge_error_and_close_still_works():
    bus = small_bus(2)
    emu = guarded_emulator(bus)
    t = make(bus, emu, retries=0)
    t.open()
    emu.vanish()
    with pytest.raises(BridgeError, match="Dynamixel bus|servo ID"):
        for _ in range(3):
            t.read_state()
    t.close()
    assert t.bus.port is None


def test_hardware_error_decoding_and_latency_timer_on_a_pty():
    assert decode_hardware_error(0x25) == ["input voltage", "overheating", "overload"]
    assert decode_hardware_error(0x42) == ["unknown bits 0x42"]
    assert decode_hardware_error(0x24, protocol=1) == ["overheating", "overload"]
    timer, note = set_latency_timer("/dev/ptmx")
    assert timer is None and "no USB-serial latency timer" in note


def test_register_settings_from_the_op3_config():
    cfg = load_config(robot_config_path("op3"), check_mjcf=False)
    knee = cfg.servo("r_knee")
    regs = servo_register_settings(knee, XM)
    assert regs["return_delay_time"] == 0 and regs["temperature_limit"] == 75
    assert regs["min_voltage_limit"] == 100 and regs["max_voltage_limit"] == 148
    lo, hi = regs["min_position_limit"], regs["max_position_limit"]
    assert XM.ticks_to_rad(lo) >= knee.lower - 1e-12 and XM.ticks_to_rad(hi) <= knee.upper + 1e-12
    assert XM.ticks_to_rad(lo - 1) < knee.lower and XM.ticks_to_rad(hi + 1) > knee.upper
    assert regs["position_p_gain"] == 800 and regs["bus_watchdog"] == 5  # 100 ms in 20 ms units


def test_communication_error_with_limp_policy_switches_every_servo_off():
    bus = small_bus(3)
    emu = guarded_emulator(bus)
    try:
        t = make(bus, emu, stop_policy="limp", retries=0)
        t.open()
        t.set_torque(True)
        emu.disconnect(2)
        with pytest.raises(BridgeError, match=r"servo ID 2 \(j2\)"):
            t.read_state()
        # the broadcast torque-off reached the servos that still listen
        assert wait_for(
            lambda: emu.read_register(1, "torque_enable") == 0 and emu.read_register(3, "torque_enable") == 0
        )
        t.close()
    finally:
        emu.stop()


EXIT_SCRIPT = """
import sys, numpy as np
from firmware_cfg.config import parse_config
from ros_free_bridge.dynamixel.transport import DynamixelTransport
bus = parse_config({config!r}).buses[0]
t = DynamixelTransport(bus, port=sys.argv[1], stop_policy="limp", latency_ms=30.0)
t.open()
t.set_torque(True)
t.write_goal(np.zeros(len(bus.servos)))
raise SystemExit(0)  # no close(): the atexit hook must apply the stop policy
"""


def test_interpreter_exit_applies_the_stop_policy():
    import subprocess
    import sys

    config = {
        "robot": "t",
        "buses": [
            {
                "name": "b",
                "port": "/dev/null",
                "baud": 1000000,
                "protocol": "2.0",
                "servos": [{"id": i, "joint": f"j{i}", "model": "XM430-W350", "limits": [-1, 1]} for i in (1, 2)],
            }
        ],
    }
    bus = parse_config(config).buses[0]
    emu = guarded_emulator(bus)
    try:
        proc = subprocess.run(
            [sys.executable, "-c", EXIT_SCRIPT.format(config=config), emu.port_path],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert proc.returncode == 0, proc.stderr
        assert any(r.accepted for r in emu.goal_history[1])  # it did run with torque on
        assert emu.read_register(1, "torque_enable") == 0 and emu.read_register(2, "torque_enable") == 0
    finally:
        emu.stop()


def test_protocol_1_bus_ax12():
    cfg = parse_config(
        {
            "robot": "t",
            "buses": [
                {
                    "name": "b",
                    "port": "/dev/null",
                    "baud": 1000000,
                    "protocol": "1.0",
                    "servos": [
                        {"id": 1, "joint": "a", "model": "AX-12A", "limits": [-1.5, 1.5]},
                        {"id": 2, "joint": "b", "model": "AX-12A", "limits": [-1.0, 1.0], "direction": -1},
                    ],
                }
            ],
        }
    )
    bus = cfg.buses[0]
    ax = load_servo_model("AX-12A")
    emu = DynamixelBusEmulator([ServoSpec(1, "AX-12A"), ServoSpec(2, "AX-12A")], baud=1_000_000, protocol=1).start()
    try:
        emu.push(1, 512 + 100)
        with DynamixelTransport(bus, port=emu.port_path, latency_ms=LAT, slow_per_cycle=2) as t:
            s = t.read_state()
            assert s.position[0] == pytest.approx(100 / ax.ticks_per_rad)
            t.set_torque(True)
            t.write_goal(np.array([0.5, 0.5]))
            assert wait_for(lambda: emu.read_register(2, "goal_position") == ax.rad_to_ticks(-0.5))
            emu.overheat(2)
            s = t.read_state()
            assert "overheating" in s.errors.get("b", "")
    finally:
        emu.stop()


def test_bus_watchdog_stops_servos_when_the_host_goes_silent_and_is_recovered():
    bus = small_bus(3, bus_watchdog_ms=100)
    emu = guarded_emulator(bus)
    try:
        with make(bus, emu, slow_per_cycle=1) as t:
            assert emu.read_register(2, "bus_watchdog") == 5
            t.set_torque(True)
            t.write_goal(np.array([0.8, 0.8, 0.8]))
            time.sleep(0.35)  # the host "hangs": every servo stops where it is
            assert all(emu.read_register(i, "bus_watchdog") in (-1, 255) for i in (1, 2, 3))
            t.read_state()
            assert t.stats.watchdog_trips == 3
            assert [emu.read_register(i, "bus_watchdog") for i in (1, 2, 3)] == [5, 5, 5]
            t.write_goal(np.array([0.1, 0.1, 0.1]))  # goals are accepted again
            assert wait_for(lambda: np.allclose(t.read_state().position, 0.1, atol=3e-3))
        assert emu.violations == []
    finally:
        emu.stop()


def test_a_goal_exactly_at_a_limit_never_rounds_past_it():
    # 0.5π rad is 3071.9999 ticks from the centre: rounding alone would send 3072, one tick
    # past the config limit rounded inwards (3071); the EEPROM is factory (not provisioned),
    # so only the transport's own rounding stands between the goal and the bus
    bus = small_bus(2, limits=[-0.9424778, 1.5707963], direction=1, zero_offset=0.0)
    with start_emulator(bus) as emu:
        for s in bus.servos:
            emu.allowed_range(s.id, *servo_tick_limits(s, XM))
        t = make(bus, emu)
        t.open()
        try:
            t.set_torque(True)
            t.write_goal(np.array([1.5707963, -0.9424778]))
        finally:
            t.close()
        assert emu.violations == []
        assert emu.goal_history[1][-1].ticks <= servo_tick_limits(bus.servos[0], XM)[1]
