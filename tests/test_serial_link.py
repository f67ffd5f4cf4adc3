"""DFSL serial link: the codec against the spec's test vectors and an independent CRC,
and the pyserial transport against the emulated microcontroller on a pty."""

from __future__ import annotations

import re
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import firmware_cfg.serial_link as sl
from firmware_cfg.config import parse_config
from firmware_cfg.errors import ConfigError
from ros_free_bridge.emulators.serial_mcu import SerialMcuEmulator
from ros_free_bridge.errors import BridgeError
from ros_free_bridge.transports.base import Transport
from ros_free_bridge.transports.serial_link import SerialLinkTransport

SPEC = Path(sl.__file__).with_name("serial_link.md")


def crc_bitwise(data: bytes) -> int:
    """CRC-16/CCITT-FALSE written out bit by bit, independent of binascii."""
    crc = 0xFFFF
    for b in data:
        crc ^= b << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
    return crc


def spec_vectors() -> dict[str, bytes]:
    text = SPEC.read_text()
    block = text.split("## Test vectors", 1)[1].split("```", 2)[1]
    out = {}
    for line in block.splitlines():
        m = re.match(r"^(\w+)\s.*:\s*((?:[0-9A-F]{2}\s?)+)$", line.strip())
        if m:
            out[m.group(1)] = bytes.fromhex(m.group(2))
    return out


def test_crc_check_value_matches_spec_and_bitwise_reference():
    assert sl.crc16(b"123456789") == 0x29B1 == crc_bitwise(b"123456789")
    assert 'crc16("123456789") = 29B1' in SPEC.read_text()


def test_codec_reproduces_every_spec_vector():
    v = spec_vectors()
    expected = {
        "HELLO": sl.Frame(0, sl.MsgType.HELLO, sl.Hello(1, 200).pack()),
        "HELLO_ACK": sl.Frame(0, sl.MsgType.HELLO_ACK, sl.HelloAck(1, 1, 0, 20, "dfsl-emu").pack()),
        "TARGETS": sl.Frame(1, sl.MsgType.TARGETS, sl.Targets(0, (0, 9000, -4500)).pack()),
        "ENABLE": sl.Frame(2, sl.MsgType.ENABLE, sl.Enable(0x000FFFFF).pack()),
        "ACK": sl.Frame(2, sl.MsgType.ACK, sl.Ack(sl.MsgType.ENABLE).pack()),
        "HEARTBEAT": sl.Frame(3, sl.MsgType.HEARTBEAT, b""),
        "HEARTBEAT_ACK": sl.Frame(3, sl.MsgType.HEARTBEAT_ACK, sl.HeartbeatAck(123456).pack()),
        "TELEMETRY_REQ": sl.Frame(4, sl.MsgType.TELEMETRY_REQ, b""),
        "TELEMETRY": sl.Frame(
            4, sl.MsgType.TELEMETRY, sl.Telemetry(1000, 11100, 3, 0, (1500, -32768), (35, -128)).pack()
        ),
        "SET_LIMITS": sl.Frame(5, sl.MsgType.SET_LIMITS, sl.SetLimits(0, ((-9000, 9000), (-2700, 4500))).pack()),
        "ERROR": sl.Frame(6, sl.MsgType.ERROR, sl.Error(sl.ErrorCode.TARGET_OUT_OF_LIMITS, 1).pack()),
    }
    assert set(v) == set(expected), "spec and test disagree on the list of vectors"
    for name, frame in expected.items():
        raw = v[name]
        assert sl.encode(frame) == raw, name
        assert sl.decode(raw) == frame, name
        # the spec's CRC field is the independent CRC of SEQ..PAYLOAD, low byte first
        assert raw[-2] | raw[-1] << 8 == crc_bitwise(raw[2:-2]), name
    tel = sl.Telemetry.unpack(sl.decode(v["TELEMETRY"]).payload)
    assert sl.cdeg_to_rad(tel.position_cdeg[0]) == pytest.approx(np.radians(15.0))
    assert np.isnan(sl.cdeg_to_rad(tel.position_cdeg[1]))


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 255), st.integers(0, 255), st.binary(max_size=255), st.binary(max_size=20), st.integers(1, 7))
def test_decoder_resyncs_through_noise_and_chunking(seq, mtype, payload, noise, chunk):
    frame = sl.Frame(seq, mtype, payload)
    raw = sl.encode(frame)
    noise = noise.replace(b"\xa5", b"\x00")  # noise that cannot fake a sync pair
    stream = noise + raw + raw
    dec = sl.FrameDecoder()
    got = []
    for i in range(0, len(stream), chunk):
        got += dec.feed(stream[i : i + chunk])
    assert got == [frame, frame]
    assert dec.pending == 0


def test_decoder_drops_a_damaged_frame_and_keeps_the_next():
    good = sl.encode(sl.Frame(7, sl.MsgType.HEARTBEAT, b""))
    bad = bytearray(sl.encode(sl.Frame(6, sl.MsgType.TARGETS, sl.Targets(0, (100,)).pack())))
    bad[6] ^= 0xFF
    dec = sl.FrameDecoder()
    assert dec.feed(bytes(bad) + good) == [sl.Frame(7, sl.MsgType.HEARTBEAT, b"")]
    assert dec.crc_errors >= 1


def test_angle_conversion_and_range():
    assert sl.rad_to_cdeg(np.pi / 2) == 9000
    assert sl.rad_to_cdeg(-np.pi / 4) == -4500
    assert sl.cdeg_to_rad(sl.rad_to_cdeg(1.2345)) == pytest.approx(1.2345, abs=np.pi / 36000)
    with pytest.raises(ConfigError, match="wire range"):
        sl.rad_to_cdeg(6.0)
    with pytest.raises(ConfigError, match="TARGETS payload"):
        sl.Targets.unpack(bytes((0, 3, 1, 2)))


# ----------------------------------------------------------------------------- transport


def make_bus(n=4, lower=-1.0, upper=1.0, first=0):
    servos = [
        {
            "id": first + i,
            "joint": f"j{i}",
            "limits": [lower, upper],
            "direction": -1 if i % 2 else 1,
            "zero_offset": 0.1 * i,
        }
        for i in range(n)
    ]
    cfg = parse_config(
        {
            "robot": "t",
            "buses": [
                {"name": "link", "port": "/dev/null", "baud": 1000000, "protocol": "serial-link", "servos": servos}
            ],
        }
    )
    return cfg.buses[0]


def link(bus, port, **kw):
    """A transport whose board watchdog (tested on its own) cannot trip on a slow test machine."""
    kw.setdefault("watchdog_ms", 2000)
    return SerialLinkTransport(bus, port=port, **kw)


def wait_until(pred, timeout=3.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.005)
    return False


def test_transport_implements_interface_and_maps_direction_and_offset():
    bus = make_bus()
    # servo side = direction * joint + offset, so joint = direction * (servo - offset)
    start_servo = [0.3, 0.2, -0.1, 0.5]
    with SerialMcuEmulator(4, initial_positions=start_servo) as mcu:
        t = link(bus, mcu.port)
        assert isinstance(t, Transport)
        with t:
            assert t.board.n_channels == 4 and t.board.name == "dfsl-emu"
            s = t.read_state()
            expect = [d * (p - o) for d, p, o in zip([1, -1, 1, -1], start_servo, [0, 0.1, 0.2, 0.3])]
            np.testing.assert_allclose(s.position, expect, atol=2e-4)
            assert not s.torque_enabled.any()
            assert np.all(np.isnan(s.velocity)) and np.all(np.isnan(s.effort))
            np.testing.assert_allclose(s.voltage, 11.1)
            # torque on without a goal: the transport first sends goal = present
            t.set_torque(True)
            assert all(mcu.enabled())
            first_targets = {c: v for _, c, v in mcu.target_log[:4]}
            np.testing.assert_allclose([first_targets[c] for c in range(4)], start_servo, atol=2e-4)
            goal = np.array([0.5, -0.5, 0.25, 0.0])
            t.write_goal(goal)
            assert wait_until(lambda: np.allclose(t.read_state().position, goal, atol=1e-3))
            # board limits = config limits mapped to the servo side, rounded inwards
            for (lo, hi), s_cfg in zip(mcu.limits_rad(), bus.servos):
                clo, chi = s_cfg.servo_limits()
                assert clo <= lo < clo + 2e-4 and chi - 2e-4 < hi <= chi


def test_close_holds_or_goes_limp_by_policy_and_is_idempotent():
    bus = make_bus()
    for policy, expect_enabled in (("hold", True), ("limp", False)):
        with SerialMcuEmulator(4) as mcu:
            t = link(bus, mcu.port, stop_policy=policy)
            t.open()
            t.set_torque(True)
            t.close()
            t.close()
            assert all(mcu.enabled()) is expect_enabled


def test_out_of_limit_goal_never_reaches_the_board():
    bus = make_bus(lower=-0.5, upper=0.5)
    with SerialMcuEmulator(4) as mcu, link(bus, mcu.port) as t:
        t.set_torque(True)
        n = len(mcu.target_log)
        with pytest.raises(BridgeError, match=r"j2 \(channel 2\).*outside its limits"):
            t.write_goal(np.array([0.0, 0.0, 0.7, 0.0]))
        with pytest.raises(BridgeError, match="outside its limits"):
            t.write_goal(np.array([0.0, np.nan, 0.0, 0.0]))
        time.sleep(0.02)
        assert len(mcu.target_log) == n
        for _, c, v in mcu.target_log:
            lo, hi = bus.servos[c].servo_limits()
            assert lo - 1e-9 <= v <= hi + 1e-9


def test_board_rejects_a_target_outside_its_limits_and_the_host_hears_it():
    """Defence in depth: a target that bypasses the host check is refused by the board."""
    bus = make_bus(lower=-0.5, upper=0.5)
    with SerialMcuEmulator(4) as mcu, link(bus, mcu.port) as t:
        t._send(sl.MsgType.TARGETS, sl.Targets(1, (sl.rad_to_cdeg(1.0),)).pack())
        with pytest.raises(BridgeError, match="outside the channel's limits.*channel 1, joint j1"):
            t.read_state()
        assert mcu.rejected_log and not any(c == 1 for _, c, _ in mcu.target_log)


def test_dropped_and_corrupted_replies_are_retried_then_reported():
    bus = make_bus()
    with SerialMcuEmulator(4) as mcu, link(bus, mcu.port, retries=2) as t:
        mcu.drop_replies(1)
        mcu.corrupt_replies(1)
        t.read_state()  # third try succeeds
        mcu.drop_replies(3)
        with pytest.raises(BridgeError, match="no valid reply to TELEMETRY_REQ after 3 tries"):
            t.read_state()


def test_stall_and_overheat_show_as_joint_errors_and_outputs_off():
    bus = make_bus()
    with SerialMcuEmulator(4) as mcu, link(bus, mcu.port) as t:
        t.set_torque(True)
        mcu.stall(0)
        mcu.overheat(3)
        t.write_goal(np.array([0.8, 0.0, 0.0, 0.0]))
        assert wait_until(lambda: "j0" in t.read_state().errors)
        s = t.read_state()
        assert set(s.errors) == {"j0", "j3"} and "fault" in s.errors["j0"]
        assert not s.torque_enabled[0] and not s.torque_enabled[3] and s.torque_enabled[1]
        assert s.temperature[3] == 85.0


def test_watchdog_switches_outputs_off_when_the_host_goes_quiet():
    bus = make_bus()
    with SerialMcuEmulator(4) as mcu:
        t = SerialLinkTransport(bus, port=mcu.port, watchdog_ms=60)
        t.open()
        t.set_torque(True)
        assert wait_until(lambda: mcu.watchdog_trips == 1)
        assert not any(mcu.enabled())
        with pytest.raises(BridgeError, match="watchdog expired"):
            t.read_state()
        t.close()


def test_vanished_port_becomes_bridge_error_and_close_still_succeeds():
    bus = make_bus()
    mcu = SerialMcuEmulator(4).start()
    t = link(bus, mcu.port, reply_timeout=0.02, retries=0)
    t.open()
    mcu.vanish()
    with pytest.raises(BridgeError, match="serial link"):
        for _ in range(5):
            t.read_state()
    t.close()  # must not raise
    assert t._ser is None


def test_port_is_exclusive_and_missing_port_is_a_clear_error():
    bus = make_bus()
    with SerialMcuEmulator(4) as mcu, link(bus, mcu.port):
        with pytest.raises(BridgeError, match="cannot open"):
            link(bus, mcu.port).open()
    with pytest.raises(BridgeError, match="cannot open.*check the cable"):
        SerialLinkTransport(bus, port="/dev/does-not-exist").open()


def test_config_channel_beyond_board_is_refused():
    bus = make_bus(n=2, first=10)
    with SerialMcuEmulator(4) as mcu:
        with pytest.raises(BridgeError, match="has 4 channels but the config uses channel 11"):
            link(bus, mcu.port).open()
