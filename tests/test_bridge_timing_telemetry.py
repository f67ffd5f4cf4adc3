"""The fixed-rate clock (on a simulated clock) and crash-safe telemetry."""

import numpy as np
import pytest

from ros_free_bridge.control.clock import FixedRateClock
from ros_free_bridge.errors import BridgeError
from ros_free_bridge.telemetry.log import TelemetryWriter, read_telemetry


class FakeTime:
    """A simulated monotonic clock: sleeping advances it exactly."""

    def __init__(self):
        self.t = 100.0

    def now(self):
        return self.t

    def sleep(self, s):
        self.t += s


def test_deadlines_do_not_drift_when_work_takes_time():
    ft = FakeTime()
    clock = FixedRateClock(100.0, now=ft.now, sleep=ft.sleep, spin_s=0.0)
    dues = []
    for _k in range(500):
        tick = clock.wait()
        dues.append(tick.due)
        ft.t += 0.004  # 4 ms of work per 10 ms tick
    np.testing.assert_allclose(np.diff(dues), 0.01, atol=1e-9)
    assert dues[-1] - dues[0] == pytest.approx(4.99)
    assert clock.missed == 0


def test_a_long_stall_skips_ticks_instead_of_bursting():
    ft = FakeTime()
    clock = FixedRateClock(100.0, now=ft.now, sleep=ft.sleep, spin_s=0.0)
    clock.wait()
    ft.t += 0.055  # stall for 5.5 periods after tick 0
    tick = clock.wait()
    # ticks 1-4 are more than a period overdue and skipped; tick 5 runs, 5 ms late
    assert tick.skipped == 4 and clock.missed == 4
    assert tick.index == 5 and tick.lateness == pytest.approx(0.005)
    nxt = clock.wait()
    assert nxt.due - tick.due == pytest.approx(0.01)  # back on the original grid


def test_telemetry_round_trip_and_crash_truncation(tmp_path):
    path = tmp_path / "run.tel"
    names = ("a", "b")
    with TelemetryWriter(path, names, 100.0, meta={"robot": "toy"}) as w:
        for k in range(10):
            w.record(t=k / 100, tick=k, command=[k, -k], measured=[k, np.nan], intervention=[0, 2], faults=1)
        w.event("estop", reason="test")
    tel = read_telemetry(path)
    assert tel.joint_names == names and tel.rate_hz == 100.0 and tel.meta == {"robot": "toy"}
    assert len(tel.records) == 10 and tel.truncated_bytes == 0
    np.testing.assert_array_equal(tel.records["command"][:, 1], -np.arange(10))
    assert np.isnan(tel.records["measured"][3, 1])
    assert tel.events[0]["kind"] == "estop" and tel.events[0]["reason"] == "test"
    # a crash in the middle of a record: everything before it is still readable
    data = path.read_bytes()
    path.write_bytes(data[:-7])
    tel = read_telemetry(path)
    assert len(tel.records) == 9 and tel.truncated_bytes > 0


def test_telemetry_is_readable_while_the_writer_is_still_open(tmp_path):
    path = tmp_path / "live.tel"
    w = TelemetryWriter(path, ("a",), 100.0)
    for k in range(3):
        w.record(t=k, tick=k)
    assert len(read_telemetry(path).records) == 3  # flushed every tick: a crash now loses nothing
    w.close()
    w.close()  # idempotent


def test_reading_something_else_is_a_clear_error(tmp_path):
    p = tmp_path / "x.tel"
    p.write_bytes(b"hello\n")
    with pytest.raises(BridgeError, match="not a telemetry file"):
        read_telemetry(p)
