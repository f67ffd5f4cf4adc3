"""The IMU device on the Dynamixel bus (the OP3's OpenCR, ID 200): its control table as
data, the config's checks, the byte-level emulator answering for it, and the transport
reading it in the bus cycle over the real dynamixel-sdk on a pty, in SI units and the
robot's IMU frame (x forward, y left, z up)."""

from __future__ import annotations

import copy
import math

import dynamixel_sdk as sdk
import numpy as np
import pytest

from firmware_cfg.config import load_config, parse_config, robot_config_path
from firmware_cfg.device_models import OPENCR, STANDARD_GRAVITY, find_device_model
from firmware_cfg.errors import ConfigError
from ros_free_bridge.commands.servo import start_emulator
from ros_free_bridge.dynamixel.imu import quat_from_rpy, rotate_into
from ros_free_bridge.dynamixel.transport import DynamixelTransport
from ros_free_bridge.emulators import DynamixelBusEmulator, ServoSpec
from ros_free_bridge.errors import BridgeError

LAT = 30.0
GYRO_LSB = 2000.0 / 32800.0 * math.pi / 180.0  # rad/s per count
ACC_LSB = 2.0 / 32768.0 * STANDARD_GRAVITY  # m/s^2 per count
RPY_LSB = 0.1 * math.pi / 180.0  # rad per count


def imu_bus(n=3, devices=({"id": 200, "model": "OpenCR", "role": "imu"},), protocol="2.0", model="XM430-W350"):
    servos = [{"id": i + 1, "joint": f"j{i + 1}", "model": model, "limits": [-1.0, 1.0]} for i in range(n)]
    raw = {
        "robot": "t",
        "buses": [
            {
                "name": "b",
                "port": "/dev/null",
                "baud": 1000000,
                "protocol": protocol,
                "servos": servos,
                "devices": [dict(d) for d in devices],
            }
        ],
    }
    return raw


@pytest.fixture(autouse=True)
def patient_sdk(monkeypatch):
    monkeypatch.setattr(sdk.port_handler, "LATENCY_TIMER", 50)


def same_rotation(q, p, tol):
    return min(np.abs(np.asarray(q) - p).max(), np.abs(np.asarray(q) + p).max()) < tol


# ----------------------------------------------------------------------------- table and config


def test_opencr_table_is_the_op3_firmware_layout():
    assert OPENCR.model_number == 0x7400 == 29696
    regs = {n: (r.address, r.size, r.signed) for n, r in OPENCR.registers.items()}
    assert regs["gyro_x"] == (32, 2, True) and regs["acc_z"] == (42, 2, True) and regs["yaw"] == (48, 2, True)
    assert OPENCR.block(OPENCR.imu_registers) == (32, 18)  # one READ holds gyro, accel and roll/pitch/yaw
    assert "FAST_SYNC_READ" not in OPENCR.instructions and "BULK_READ" in OPENCR.instructions
    assert find_device_model("open-cr") is OPENCR and find_device_model(29696) is OPENCR


@pytest.mark.parametrize(
    "change, pattern",
    [
        (
            lambda d: d.update(model="MPU6050"),
            r"devices\[0\]\.model: 'MPU6050' is not a known device model; use one of \['OpenCR'\]",
        ),
        (lambda d: d.update(model=""), r"devices\[0\]\.model: required"),
    ],
)
def test_unknown_device_model_is_a_config_error_naming_the_field(change, pattern):
    raw = imu_bus()
    change(raw["buses"][0]["devices"][0])
    with pytest.raises(ConfigError, match=r"^hw\.yaml: buses\[0\]\." + pattern):
        parse_config(raw, source="hw.yaml")


def test_opencr_on_a_protocol_1_bus_is_refused():
    with pytest.raises(ConfigError, match=r"devices\[0\]\.model: OpenCR speaks protocol 2\.0 but the bus is 1\.0"):
        parse_config(imu_bus(protocol="1.0", model="AX-12A"), source="hw.yaml")


def test_alias_is_stored_under_the_canonical_name():
    raw = imu_bus()
    raw["buses"][0]["devices"][0]["model"] = "OPEN-CR"  # ROBOTIS's own robot files spell it so
    assert parse_config(raw).buses[0].devices[0].model == "OpenCR"


# ----------------------------------------------------------------------------- emulator


def test_emulated_opencr_answers_like_its_firmware():
    with DynamixelBusEmulator([1, 2, (200, "OpenCR")], baud=1_000_000) as emu:
        port = sdk.PortHandler(emu.port_path)
        port.openPort()
        port.setBaudRate(1_000_000)
        ph = sdk.PacketHandler(2.0)
        assert ph.ping(port, 200)[:2] == (29696, sdk.COMM_SUCCESS)
        # still upright by default: gyro 0, +1 g on z (16384 counts), level
        data, result, _ = ph.readTxRx(port, 200, 32, 18)
        assert result == sdk.COMM_SUCCESS
        assert np.frombuffer(bytes(data), "<i2").tolist() == [
            0,
            0,
            0,
            0,
            0,
            16384,
            0,
            0,
            1800,
        ]  # yaw: board turned 180°
        # the board is mounted turned 180° about z: robot +x rate is a negative board x count
        emu.set_imu(200, gyro=[0.5, 0.25, -1.0])
        data, _, _ = ph.readTxRx(port, 200, 32, 6)
        assert np.frombuffer(bytes(data), "<i2").tolist() == [
            round(-0.5 / GYRO_LSB),
            round(-0.25 / GYRO_LSB),
            round(-1.0 / GYRO_LSB),
        ]
        # it has no REBOOT and no fast group reads: an instruction error, and a fast chain cut at it
        assert ph.reboot(port, 200) == (sdk.COMM_SUCCESS, 2)
        bulk = sdk.GroupBulkRead(port, ph)
        for sid, addr, n in ((1, 132, 4), (200, 32, 18), (2, 132, 4)):
            bulk.addParam(sid, addr, n)
        assert bulk.txRxPacket() == sdk.COMM_SUCCESS  # plain BULK_READ: each answers in turn
        assert bulk.getData(200, 36, 2) == -round(1.0 / GYRO_LSB) & 0xFFFF  # z is not flipped
        assert bulk.fastBulkRead() != sdk.COMM_SUCCESS
        port.closePort()


def test_emulator_reports_a_physics_source_when_given_one():
    with DynamixelBusEmulator([1, (200, "OpenCR")], baud=1_000_000) as emu:
        calls = []
        emu.set_imu_source(
            200,
            lambda: (calls.append(1), (np.array([0, 0, 2.0]), np.array([1.0, 0, 9.0]), np.array([1.0, 0, 0, 0])))[1],
        )
        port = sdk.PortHandler(emu.port_path)
        port.openPort()
        port.setBaudRate(1_000_000)
        data, _, _ = sdk.PacketHandler(2.0).readTxRx(port, 200, 36, 4)
        assert np.frombuffer(bytes(data), "<i2").tolist() == [round(2.0 / GYRO_LSB), round(-1.0 / ACC_LSB)]
        assert calls
        port.closePort()


# ----------------------------------------------------------------------------- transport


@pytest.fixture
def bus_with_imu():
    return parse_config(imu_bus()).buses[0]


def expected(gyro, quat):
    return np.asarray(gyro, float), rotate_into(quat, np.array([0.0, 0.0, STANDARD_GRAVITY]))


@pytest.mark.parametrize("split_phase", [False, True])
def test_transport_reads_the_imu_in_si_and_the_robot_frame(bus_with_imu, split_phase):
    emu = start_emulator(bus_with_imu, provisioned=True)
    try:
        # pitched nose-down 0.3 rad, rolled 0.1 rad, turned 0.4 rad; turning left and rolling right
        quat = quat_from_rpy(0.1, 0.3, 0.4)
        gyro = [-0.7, 0.2, 1.3]
        emu.set_imu(200, gyro=gyro, quat=quat)
        with DynamixelTransport(bus_with_imu, port=emu.port_path, latency_ms=LAT) as tr:
            assert tr.pipeline(split_phase) is split_phase
            readings = []
            for _ in range(4):
                st = tr.read_state()
                tr.write_goal(np.clip(st.position, -0.5, 0.5))
                readings.append(st.imu)
            imu = readings[-1]
            g, a = expected(gyro, quat)
            assert np.allclose(imu.gyro, g, atol=GYRO_LSB)
            assert np.allclose(imu.accel, a, atol=ACC_LSB)
            assert imu.accel[0] < -2.5 and imu.accel[2] > 8.0  # nose down: gravity's specific force leans to -x
            assert same_rotation(imu.quat, quat, 2 * RPY_LSB)
            assert all(r is not None for r in readings)
            assert [r.stamp for r in readings] == sorted(r.stamp for r in readings)
            assert tr.stats.imu_reads >= 4 and tr.stats.imu_misses == 0
            # within the bus cycle: exactly one READ of the IMU block reaches the device per cycle
            served, tried = emu.device(200).imu_reads, tr.imu.reads + tr.imu.misses
            for _ in range(5):
                tr.write_goal(np.clip(tr.read_state().position, -0.5, 0.5))
            assert emu.device(200).imu_reads - served == 5 and tr.imu.reads + tr.imu.misses - tried == 5
        assert emu.violations == []
    finally:
        emu.stop()


def test_op3_config_reads_the_opencr():
    bus = load_config(robot_config_path("op3"), check_mjcf=False).buses[0]
    emu = start_emulator(bus, provisioned=True)
    try:
        emu.set_imu(200, gyro=[0.0, 0.4, 0.0])
        with DynamixelTransport(bus, port=emu.port_path, latency_ms=LAT) as tr:
            st = tr.read_state()
            assert st.imu is not None and st.imu.gyro[1] == pytest.approx(0.4, abs=GYRO_LSB)
            assert st.imu.accel[2] == pytest.approx(STANDARD_GRAVITY, abs=ACC_LSB)
    finally:
        emu.stop()


def test_missing_imu_is_a_note_and_none_not_a_crash(bus_with_imu):
    emu = start_emulator(bus_with_imu, provisioned=True)
    emu.disconnect(200)
    try:
        with DynamixelTransport(bus_with_imu, port=emu.port_path, latency_ms=LAT, retries=0) as tr:
            assert (
                tr.imu.fault is not None
                and "OpenCR (ID 200, IMU)" in tr.imu.fault
                and "no answer to PING" in tr.imu.fault
            )
            assert any("JointState.imu is None" in n for n in tr.stats.notes)
            st = tr.read_state()
            assert st.imu is None and np.all(np.isfinite(st.position)) and st.errors == {}
    finally:
        emu.stop()


@pytest.mark.parametrize("split_phase", [False, True])
def test_imu_that_stops_answering_is_reported_then_resumes(bus_with_imu, split_phase):
    emu = start_emulator(bus_with_imu, provisioned=True)
    try:
        with DynamixelTransport(bus_with_imu, port=emu.port_path, latency_ms=LAT) as tr:
            tr.pipeline(split_phase)
            tr.imu.retry_s = 0.0  # try again at once once lost (the default waits 1 s)
            tick = lambda: (st := tr.read_state(), tr.write_goal(np.clip(st.position, -0.5, 0.5)))[0]  # noqa: E731
            assert tick().imu is not None
            emu.disconnect(200)
            states = [tick() for _ in range(6)]
            assert states[-1].imu is None and tr.imu.fault is not None and "reads in a row failed" in tr.imu.fault
            assert all(s.errors == {} for s in states)  # the servos are fine: no hardware fault for the loop
            emu.disconnect(200, False)
            states = [tick() for _ in range(3)]
            assert states[-1].imu is not None and tr.imu.fault is None
            assert "answers again" in tr.stats.notes[-1]
    finally:
        emu.stop()


def test_another_model_at_the_imu_id_is_refused(bus_with_imu):
    raw = imu_bus()
    with DynamixelBusEmulator([ServoSpec(1), ServoSpec(2), ServoSpec(3), ServoSpec(200)], baud=1_000_000) as emu:
        tr = DynamixelTransport(parse_config(raw).buses[0], port=emu.port_path, latency_ms=LAT)
        with pytest.raises(
            BridgeError, match=r"OpenCR \(ID 200, IMU\).*model number 1020 but the config says OpenCR \(29696\)"
        ):
            tr.open()
        assert tr.bus.port is None  # the port is released


def test_bus_without_imu_device_reads_no_imu():
    raw = imu_bus(devices=())
    bus = parse_config(raw).buses[0]
    emu = start_emulator(bus, provisioned=True)
    try:
        with DynamixelTransport(bus, port=emu.port_path, latency_ms=LAT, slow_per_cycle=0) as tr:
            before = emu.instruction_counts.get("READ", 0)
            assert tr.imu is None and tr.read_state().imu is None
            assert emu.instruction_counts.get("READ", 0) == before
    finally:
        emu.stop()


def test_scan_names_the_opencr(capsys):
    from ros_free_bridge.cli import main

    bus = parse_config(copy.deepcopy(imu_bus())).buses[0]
    emu = start_emulator(bus)
    try:
        code = main(["servo", "scan", "--port", emu.port_path, "--bauds", "1000000", "--protocols", "2"])
        out = capsys.readouterr().out
        assert code == 0
        rows = {line.split()[2]: line.split() for line in out.splitlines()[1:]}
        assert rows["200"][3:5] == ["29696", "OpenCR"] and rows["200"][5] == "2"
    finally:
        emu.stop()
