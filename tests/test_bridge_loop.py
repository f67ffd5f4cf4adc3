"""The control loop on the record-only transport: life cycle, limits, stops and faults.

These run in real time (a few seconds each) because the loop's clock is the real one.
"""

import threading
import time

import numpy as np
import pytest

from ros_free_bridge.control.loop import ControlLoop, Fault, LoopConfig, State
from ros_free_bridge.control.safety import JointLimits
from ros_free_bridge.control.targets import TargetBuffer, TargetFrame
from ros_free_bridge.errors import BridgeError
from ros_free_bridge.telemetry.log import TelemetryWriter, read_telemetry
from ros_free_bridge.transports.record import RecordTransport

NAMES = ("j0", "j1", "j2")
LIMITS = JointLimits(NAMES, [-1.0, -1.0, -0.5], [1.0, 1.0, 0.5], [3.0, 3.0, 3.0], [30.0, 30.0, 30.0])
FPS = 30.0


def _producer(buf, frames, stop_after=None, error=None, delay_first=0.0):
    """Push frames at the motion rate, as the generator thread would."""

    def run():
        time.sleep(delay_first)
        t0 = time.monotonic()
        for k, q in enumerate(frames):
            if stop_after is not None and k == stop_after:
                if error is not None:
                    buf.close(error)
                return  # go quiet without closing: a stall
            while time.monotonic() < t0 + k / FPS:
                time.sleep(0.001)
            buf.push(TargetFrame(k, np.asarray(q, float), time.monotonic(), actor_frame=k))
        buf.close()

    th = threading.Thread(target=run, daemon=True)
    th.start()
    return th


def _loop(tmp_path, transport=None, **cfg):
    transport = transport or RecordTransport(NAMES, initial=[0.3, -0.2, 0.1])
    buf = TargetBuffer(FPS)
    config = LoopConfig(rate_hz=100.0, rest_pose=np.zeros(3), min_ramp=0.2, handle_signals=False, **cfg)
    tel = TelemetryWriter(tmp_path / "run.tel", NAMES, 100.0)
    return ControlLoop(transport, LIMITS, buf, config, tel), transport, buf


def _sine(n, amp=(0.4, 0.8, 2.0)):
    t = np.arange(n) / FPS
    return np.stack([a * np.sin(2 * np.pi * 0.5 * t) for a in amp], axis=1)  # j2 asks beyond its limit


def _assert_commands_safe(tr):
    cmds = np.asarray(tr.commands)
    assert np.all(np.isfinite(cmds))
    assert np.all(cmds >= LIMITS.lower - 1e-9) and np.all(cmds <= LIMITS.upper + 1e-9)
    assert np.all(np.abs(np.diff(cmds, axis=0)) <= LIMITS.max_velocity * 0.01 + 1e-9)


def test_full_run_ramps_in_streams_and_ramps_out(tmp_path):
    loop, tr, buf = _loop(tmp_path)
    frames = _sine(45)
    _producer(buf, frames, delay_first=0.3)
    summary = loop.run()
    assert summary.end_state == "STOPPED" and summary.reason == "the motion ended"
    _assert_commands_safe(tr)
    cmds = np.asarray(tr.commands)
    np.testing.assert_allclose(cmds[0], [0.3, -0.2, 0.1])  # goal = present before torque on
    assert tr.torque_events[0][1] is True and tr.torque_events[0][0] >= tr.times[0]
    np.testing.assert_allclose(cmds[-1], 0.0, atol=1e-9)  # ended at the rest pose
    assert tr.stopped_with == "hold"
    # j0 tracked its (in-limit) sine; j2 was clamped at its limit
    assert np.max(cmds[:, 0]) == pytest.approx(0.4, abs=0.01)
    assert np.max(cmds[:, 2]) == pytest.approx(0.5)
    assert summary.frames_played >= 40 and summary.interventions > 0
    lat = summary.latency_percentiles()
    # measured for the played frames (its size depends on the machine's load: bench/bridge_loop.py times it)
    assert set(lat) == {"p50", "p99", "max"} and 0.0 < lat["p50"] <= lat["p99"] <= lat["max"] < np.inf
    tel = read_telemetry(tmp_path / "run.tel")
    assert len(tel.records) == summary.ticks
    np.testing.assert_allclose(tel.records["command"], cmds[1:].astype(np.float32))  # [0]: goal = present
    assert [e["kind"] for e in tel.events][-1] == "end"
    for field in ("imu_gyro", "imu_accel", "imu_quat"):  # a transport without an IMU: none recorded, not zeros
        assert np.isnan(tel.records[field]).all(), field


def test_estop_mid_run_goes_limp_at_once_and_telemetry_is_complete(tmp_path):
    loop, tr, buf = _loop(tmp_path)
    _producer(buf, _sine(300))
    threading.Timer(0.8, loop.estop, args=("test e-stop",)).start()
    summary = loop.run()
    assert summary.end_state == "ESTOP" and summary.reason == "test e-stop"
    assert tr.stopped_with == "limp" and tr.torque_events[-1][1] is False
    _assert_commands_safe(tr)
    tel = read_telemetry(tmp_path / "run.tel")
    assert len(tel.records) == summary.ticks and tel.truncated_bytes == 0
    assert any(e["kind"] == "estop" for e in tel.events)


def test_generator_stall_holds_then_ramps_to_rest(tmp_path):
    loop, tr, buf = _loop(tmp_path, actor_timeout=0.2, rest_after=0.6)
    _producer(buf, _sine(300), stop_after=20)
    summary = loop.run()
    assert summary.end_state == "STOPPED" and "no new frames" in summary.reason
    assert summary.faults & Fault.ACTOR_TIMEOUT
    tel = read_telemetry(tmp_path / "run.tel")
    assert (tel.records["state"] == State.HOLD).any()
    np.testing.assert_allclose(np.asarray(tr.commands)[-1], 0.0, atol=1e-9)
    _assert_commands_safe(tr)


def test_nan_from_the_generator_never_reaches_the_transport(tmp_path):
    loop, tr, buf = _loop(tmp_path)
    frames = _sine(40)
    frames[10:15, 1] = np.nan
    _producer(buf, frames)
    loop.run()
    _assert_commands_safe(tr)
    tel = read_telemetry(tmp_path / "run.tel")
    assert (tel.records["faults"] & Fault.NONFINITE).any()


def test_generator_failure_stops_with_its_reason(tmp_path):
    loop, tr, buf = _loop(tmp_path)
    _producer(buf, _sine(100), stop_after=15, error=RuntimeError("model exploded"))
    summary = loop.run()
    assert summary.end_state == "STOPPED" and "model exploded" in summary.reason
    _assert_commands_safe(tr)


class FailingTransport(RecordTransport):
    def write_goal(self, positions):
        if len(self.commands) > 50:
            raise BridgeError("servo 3: no status packet")
        super().write_goal(positions)


def test_a_bus_error_while_running_is_a_fault_that_applies_the_estop_policy(tmp_path):
    tr = FailingTransport(NAMES)
    loop, _, buf = _loop(tmp_path, transport=tr)
    _producer(buf, _sine(100))
    summary = loop.run()  # a bus failure is a fault to report, not an exception (exit code 1, not 2)
    assert summary.end_state == "ESTOP" and not summary.ok
    assert summary.reason.startswith("bus error") and "no status packet" in summary.reason
    assert summary.faults & Fault.BUS_ERROR
    assert tr.stopped_with == "limp" and not tr.is_open
    tel = read_telemetry(tmp_path / "run.tel")
    assert any(e["kind"] == "estop" and "no status packet" in e["reason"] for e in tel.events)


class BuggyTransport(RecordTransport):
    def write_goal(self, positions):
        if len(self.commands) > 50:
            raise ZeroDivisionError("a bug")
        super().write_goal(positions)


def test_a_bug_applies_the_estop_policy_before_propagating(tmp_path):
    tr = BuggyTransport(NAMES)
    loop, _, buf = _loop(tmp_path, transport=tr)
    _producer(buf, _sine(100))
    with pytest.raises(ZeroDivisionError):
        loop.run()
    assert tr.stopped_with == "limp" and not tr.is_open


def test_mismatched_joint_names_are_refused(tmp_path):
    with pytest.raises(BridgeError, match="same robot config"):
        ControlLoop(RecordTransport(("a", "b", "c")), LIMITS, TargetBuffer(FPS), LoopConfig(handle_signals=False))
