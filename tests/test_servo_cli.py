"""``dualflow-bridge servo ...`` against an emulated 20-servo op3 bus: provision → verify,
refusals, calibrate, scan, monitor, and a faulted session in which no goal outside the
configured limits ever reaches a servo (asserted on the emulator side)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import yaml

from firmware_cfg.config import load_config, robot_config_path
from firmware_cfg.servo_models import load_servo_model
from ros_free_bridge.cli import main
from ros_free_bridge.commands.servo import start_emulator
from ros_free_bridge.dynamixel.servos import servo_register_settings, servo_tick_limits
from ros_free_bridge.dynamixel.transport import DynamixelTransport
from ros_free_bridge.emulators import DynamixelBusEmulator, ServoSpec

OP3 = str(robot_config_path("op3"))
XM = load_servo_model("XM430-W350")


@pytest.fixture
def op3_bus():
    return load_config(OP3).buses[0]


@pytest.fixture
def factory_emu(op3_bus):
    """20 servos with factory settings (return delay 500 µs, full position range)."""
    emu = start_emulator(op3_bus)
    yield emu
    emu.stop()


def run(capsys, *argv):
    code = main(["servo", *argv])
    out = capsys.readouterr()
    return code, out.out, out.err


def test_provision_then_verify_on_20_servos(capsys, op3_bus, factory_emu):
    port = factory_emu.port_path
    code, out, _ = run(capsys, "verify", OP3, "--port", port)
    assert code == 1 and "20 servo(s) differ" in out
    code, out, _ = run(capsys, "provision", OP3, "--port", port, "--dry-run")
    assert code == 0 and "nothing written" in out
    assert factory_emu.read_register(13, "return_delay_time") == 250  # dry run wrote nothing
    code, out, _ = run(capsys, "provision", OP3, "--port", port)
    assert code == 0 and "read back and verified" in out
    assert "return_delay_time   250" in out.replace("  ", "  ")  # the diff shows the old value
    for s in op3_bus.servos:
        for name, value in servo_register_settings(s, XM).items():
            assert factory_emu.read_register(s.id, name) == value, (s.id, name)
    code, out, _ = run(capsys, "verify", OP3, "--port", port)
    assert code == 0 and "all 20 servos match" in out
    # a register changed behind our back is caught
    factory_emu.write_register(7, "temperature_limit", 90)
    code, out, _ = run(capsys, "verify", OP3, "--port", port)
    assert code == 1 and "temperature_limit=90 (want 75)" in out


def test_provision_turns_torque_off_before_eeprom_writes(capsys, factory_emu):
    factory_emu.write_register(5, "torque_enable", 1)
    code, _, err = run(capsys, "provision", OP3, "--port", factory_emu.port_path)
    assert code == 0 and "servo ID 5 (r_el): torque off to unlock EEPROM" in err
    assert factory_emu.read_register(5, "return_delay_time") == 0


def test_provision_refuses_on_model_mismatch_and_writes_nothing(capsys, op3_bus):
    specs = [ServoSpec(s.id, "XL430-W250" if s.id == 9 else s.model) for s in op3_bus.servos]
    emu = DynamixelBusEmulator(specs, baud=2_000_000, return_delay_us=None).start()
    try:
        code, _, err = run(capsys, "provision", OP3, "--port", emu.port_path)
        assert code == 2
        assert "refusing: servo ID 9 (r_hip_roll): model number 1060 (XL430-W250), config says XM430-W350 (1020)" in err
        assert all(emu.read_register(s.id, "return_delay_time") == 250 for s in op3_bus.servos)
    finally:
        emu.stop()


def test_provision_refuses_when_a_servo_is_missing(capsys, factory_emu):
    factory_emu.disconnect(14)
    code, _, err = run(capsys, "provision", OP3, "--port", factory_emu.port_path, "--retries", "0")
    assert code == 2 and "servo ID 14 (l_knee)" in err and "no answer to PING" in err
    assert factory_emu.read_register(1, "return_delay_time") == 250


def test_faulted_session_never_sends_a_goal_outside_the_limits(capsys, op3_bus, factory_emu):
    """provision → verify → stream, with dropped/corrupted replies and a hardware alert on
    the way: each fault ends in a recovery or a named error, and the emulator sees no goal
    outside the config's limits."""
    emu = factory_emu
    assert run(capsys, "provision", OP3, "--port", emu.port_path)[0] == 0
    assert run(capsys, "verify", OP3, "--port", emu.port_path)[0] == 0
    for s in op3_bus.servos:
        emu.allowed_range(s.id, *servo_tick_limits(s, XM))
    rng = np.random.default_rng(1)
    with DynamixelTransport(op3_bus, port=emu.port_path, latency_ms=30.0, slow_per_cycle=2) as t:
        t.set_torque(True)
        q = t.read_state().position
        errors_seen = []
        for k in range(60):
            if k == 10:
                emu.drop_replies(4, 1)
            if k == 20:
                emu.corrupt_replies(11, 1)
            if k == 30:
                emu.set_hardware_error(13, 0x20)  # overload on r_knee: reboot and recover
            if k == 45:
                emu.overheat(19)  # head_pan overheats: reported, not rebooted
            target = np.clip(q + rng.normal(0, 0.3, q.shape), t.lower, t.upper)
            t.write_goal(target)
            s = t.read_state()
            errors_seen += list(s.errors)
        assert t.stats.reboots == 1 and emu.read_register(13, "torque_enable") == 1
        assert "head_pan" in errors_seen and "r_knee" not in t.read_state().errors
        # beyond the limits never leaves the host
        with pytest.raises(Exception, match="outside the joint limits"):
            t.write_goal(t.upper + 0.1)
        trips = t.stats.watchdog_trips
    assert emu.violations == []
    # every goal was accepted, unless a stalled test machine tripped the 100 ms bus watchdog
    # (the servos then refuse goals until the transport clears it, which it did)
    assert all(r.accepted for h in emu.goal_history.values() for r in h) or trips > 0


def test_calibrate_records_zero_offsets(capsys, tmp_path, factory_emu):
    factory_emu.push(3, 2048 + 100)  # r_sho_roll held 100 ticks off centre in the zero pose
    factory_emu.push(20, 2048 - 40)
    out_path = tmp_path / "op3_cal.yaml"
    code, out, _ = run(
        capsys, "calibrate", OP3, "--port", factory_emu.port_path, "--out", str(out_path), "--samples", "2"
    )
    assert code == 0 and out_path.exists()
    cal = load_config(out_path)
    assert cal.servo("r_sho_roll").zero_offset == pytest.approx(100 * 2 * np.pi / 4096, abs=1e-6)
    assert cal.servo("head_tilt").zero_offset == pytest.approx(-40 * 2 * np.pi / 4096, abs=1e-6)
    assert cal.servo("l_knee").zero_offset == 0.0
    assert factory_emu.read_register(3, "torque_enable") == 0
    # with the new offsets, the held pose reads as the zero pose
    bus = cal.buses[0]
    with DynamixelTransport(bus, port=factory_emu.port_path, latency_ms=30.0) as t:
        np.testing.assert_allclose(t.read_state().position, 0.0, atol=1e-6)
    assert yaml.safe_load(out_path.read_text())["robot"] == "op3"


def test_scan_finds_models_and_firmware(capsys, factory_emu):
    code, out, _ = run(capsys, "scan", "--port", factory_emu.port_path, "--bauds", "57600,2000000", "--protocols", "2")
    assert code == 0
    lines = [line.split() for line in out.splitlines()[1:]]
    assert [int(line[2]) for line in lines] == list(range(1, 21)) + [200]  # the servos, then the OpenCR (IMU)
    assert {tuple(line[i] for i in (0, 1, 3, 4, 5)) for line in lines[:-1]} == {
        ("2.0", "2000000", "1020", "XM430-W350", "45")
    }
    assert lines[-1][3:] == ["29696", "OpenCR", "2"]


def test_scan_protocol_1_bus(capsys):
    emu = DynamixelBusEmulator([ServoSpec(3, "AX-12A"), ServoSpec(7, "MX-28")], baud=1_000_000, protocol=1).start()
    try:
        code, out, _ = run(
            capsys, "scan", "--port", emu.port_path, "--bauds", "1000000", "--protocols", "1", "--ids", "0-10"
        )
        assert code == 0
        rows = {int(r.split()[2]): r.split()[4] for r in out.splitlines()[1:]}
        assert rows == {3: "AX-12A", 7: "MX-28"}
    finally:
        emu.stop()


def test_monitor_once_and_errors(capsys, factory_emu):
    factory_emu.set_hardware_error(2, 0x04)
    code, out, _ = run(capsys, "monitor", OP3, "--port", factory_emu.port_path, "--once")
    assert code == 0
    rows = {r.split()[1]: r for r in out.splitlines()[1:]}
    assert set(rows) == set(load_config(OP3).joint_names)
    assert "overheating" in rows["l_sho_pitch"] and "12.0" in rows["r_knee"]


def test_emulate_command_prints_a_port_that_works(capsys):
    proc = subprocess.Popen(
        [sys.executable, "-m", "ros_free_bridge", "servo", "emulate", "op3", "--provisioned", "--duration", "30"],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        port = proc.stdout.readline().strip()
        assert port.startswith("/dev/")
        code, out, _ = run(capsys, "verify", "op3", "--port", port)
        assert code == 0 and "all 20 servos match" in out
    finally:
        proc.terminate()
        proc.wait(timeout=10)


def test_bad_invocations_are_one_line_errors(capsys):
    code, _, err = run(capsys, "verify", "no_such_robot")
    assert code == 2 and "unknown robot" in err and len(err.strip().splitlines()) == 1
    code, _, err = run(capsys, "scan")
    assert code == 2 and "give --port" in err
    code, _, err = run(capsys, "scan", "--port", "/dev/nonexistent-tty", "--bauds", "57600", "--protocols", "2")
    assert code == 2 and "cannot open" in err


def test_emulate_serial_link_board(tmp_path):
    from firmware_cfg.config import load_config as load
    from ros_free_bridge.transports.serial_link import SerialLinkTransport

    cfg_path = tmp_path / "arm.yaml"
    cfg_path.write_text(
        yaml.safe_dump(
            {
                "robot": "arm",
                "buses": [
                    {
                        "name": "board",
                        "port": "/dev/ttyACM0",
                        "baud": 1000000,
                        "protocol": "serial-link",
                        "servos": [
                            {"id": 0, "joint": "a", "limits": [-1, 1]},
                            {"id": 3, "joint": "b", "limits": [-1, 1]},
                        ],
                    }
                ],
            }
        )
    )
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "ros_free_bridge",
            "servo",
            "emulate",
            str(cfg_path),
            "--bus",
            "board",
            "--duration",
            "30",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        port = proc.stdout.readline().strip()
        with SerialLinkTransport(load(cfg_path).buses[0], port=port) as t:
            assert t.board.n_channels == 4
            assert t.read_state().position.shape == (2,)
    finally:
        proc.terminate()
        proc.wait(timeout=10)
