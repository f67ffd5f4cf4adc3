"""ros_free_bridge.control.realtime: garbage collection in the loop's slack, the GIL switch interval
and SCHED_FIFO, each restored afterwards; and the control loop using them."""

from __future__ import annotations

import gc
import os
import sys
import weakref

import numpy as np

from ros_free_bridge.control.loop import ControlLoop, LoopConfig
from ros_free_bridge.control.realtime import LoopGc, realtime_priority, switch_interval
from ros_free_bridge.control.safety import JointLimits
from ros_free_bridge.control.targets import TargetBuffer
from ros_free_bridge.telemetry.log import TelemetryWriter, read_telemetry
from ros_free_bridge.transports.record import RecordTransport


class Node:
    pass


def _cycle() -> weakref.ref:
    """A reference cycle that only the cyclic collector can free; returns a weak ref to it."""
    a, b = Node(), Node()
    a.other, b.other = b, a
    return weakref.ref(a)


def test_loop_gc_collects_only_in_slack_or_past_the_hard_limit():
    was = gc.isenabled()
    survivor = Node()  # exists before the loop: frozen, never scanned while it runs
    with LoopGc(threshold=100, hard_limit=10**9) as lgc:
        assert not gc.isenabled() and gc.get_freeze_count() > 0
        ref = _cycle()
        junk = [[] for _ in range(300)]  # live container allocations push the young count past 100
        lgc.collect_in_slack(0.0)  # no slack: nothing runs
        assert ref() is not None and lgc.stats.in_slack == 0
        lgc.collect_in_slack(0.002)  # 2 ms left before the next tick: collect
        assert ref() is None and lgc.stats.in_slack == 1 and lgc.stats.longest_s > 0
        assert len(junk) == 300
    assert gc.isenabled() == was and gc.get_freeze_count() == 0
    assert survivor is not None

    with LoopGc(threshold=10, hard_limit=200) as lgc:
        ref = _cycle()
        junk = [[] for _ in range(500)]
        lgc.collect_in_slack(0.0)  # no slack, but past the hard limit: forced
        assert ref() is None and lgc.stats.forced == 1 and lgc.stats.in_slack == 0
    assert len(junk) == 500


def test_switch_interval_is_lowered_and_restored():
    old = sys.getswitchinterval()
    with switch_interval(0.0005):
        assert sys.getswitchinterval() == min(old, 0.0005)
    assert sys.getswitchinterval() == old


def test_realtime_priority_is_applied_or_explained_and_always_restored():
    policy = os.sched_getscheduler(0)
    with realtime_priority(0) as note:
        assert note == "normal scheduling"
    with realtime_priority(5) as note:
        if note.startswith("SCHED_FIFO priority 5"):
            assert os.sched_getscheduler(0) == os.SCHED_FIFO
        else:
            assert "not granted" in note and "CAP_SYS_NICE" in note
    assert os.sched_getscheduler(0) == policy


def test_control_loop_runs_with_gc_in_slack_and_restores_the_interpreter(tmp_path):
    names = ("a", "b")
    limits = JointLimits(names, [-1.0, -1.0], [1.0, 1.0], [3.0, 3.0], [30.0, 30.0])
    buf = TargetBuffer(30.0)
    buf.close()  # no motion: ramp in, wait, ramp out
    tel = TelemetryWriter(tmp_path / "rt.tel", names, 200.0)
    switch = sys.getswitchinterval()
    loop = ControlLoop(
        RecordTransport(names, initial=[0.2, -0.2]),
        limits,
        buf,
        LoopConfig(rate_hz=200.0, rest_pose=np.zeros(2), min_ramp=0.2, handle_signals=False),
        tel,
    )
    summary = loop.run()
    assert summary.end_state == "STOPPED"
    assert gc.isenabled() and gc.get_freeze_count() == 0 and sys.getswitchinterval() == switch
    events = {e["kind"]: e for e in read_telemetry(tmp_path / "rt.tel").events}
    assert events["realtime"]["gc_in_slack"] is True and events["realtime"]["scheduling"] == "normal scheduling"
    assert events["gc"]["forced"] == 0
