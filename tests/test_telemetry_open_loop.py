"""The commands a run would have sent without its balance stabilizer, read back from its
telemetry (Telemetry.open_loop_commands): what the demo's physics check judges.

Where the safety filter clips a corrected command, ``command - correction`` is not what the
filter makes of the pre-stabilizer target; the open-loop commands must be exactly what the
same loop sends with the stabilizer off."""

import json
import time

import numpy as np
import pytest

from ros_free_bridge.control.safety import JointLimits, SafetyFilter
from ros_free_bridge.errors import BridgeError
from ros_free_bridge.telemetry.log import TelemetryWriter, read_telemetry

RUNNING, RAMP_OUT = 3, 5  # loop.State codes


def _run_op3(path, stabilizer: bool):
    """The real loop on the MuJoCo op3 (lockstep physics, IMU read), one frame per tick from
    a recorded stream whose first frame is far from the rest pose: the safety filter brakes
    the jump for many ticks while the stabilizer corrects the ankles."""
    from ros_free_bridge.control.loop import ControlLoop, LoopConfig
    from ros_free_bridge.control.targets import TargetBuffer, TargetFrame
    from ros_free_bridge.robots import bridge_limits, resolve_robot
    from ros_free_bridge.transports.sim import SimTransport
    from sim.stabilizer import balance_model

    limits = bridge_limits(resolve_robot("op3").hardware_config())
    names = list(limits.names)
    transport = SimTransport("op3", clock="lockstep")
    transport.open()
    rest = limits.clip(transport.read_state().position)
    transport.close()
    pose = rest.copy()
    for joint, move in (("r_ank_pitch", 0.12), ("l_ank_pitch", 0.12), ("r_sho_pitch", 0.5), ("l_sho_pitch", -0.5)):
        pose[names.index(joint)] += move
    buf = TargetBuffer(30.0)
    for k in range(30):
        buf.push(TargetFrame(k, limits.clip(pose), time.monotonic()))
    buf.close()
    loop = ControlLoop(
        SimTransport("op3", clock="lockstep"),
        limits,
        buf,
        # no blend onto the stream (stream_join_s=0): the jump to the first frame is what makes the
        # safety filter clip corrected commands here (a fast partner motion does it in a real run)
        LoopConfig(
            handle_signals=False,
            min_ramp=0.3,
            pace="ticks",
            rest_pose=rest,
            stabilizer=stabilizer,
            stream_join_s=0.0,
        ),
        TelemetryWriter(path, names, 100.0),
        balance=balance_model("op3", joint_names=tuple(names)),
    )
    assert loop.run().end_state == "STOPPED"
    return read_telemetry(path)


@pytest.fixture(scope="module")
def op3_runs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("open_loop")
    return _run_op3(folder / "on.dftl", True), _run_op3(folder / "off.dftl", False)


@pytest.mark.slow
def test_the_open_loop_commands_are_what_the_loop_sends_with_its_stabilizer_off(op3_runs):
    on, off = op3_runs
    # the same targets in both runs up to the stop ramp (which starts from different places)
    upto = int(np.flatnonzero(on.records["state"] == RAMP_OUT)[0])
    assert int(np.flatnonzero(off.records["state"] == RAMP_OUT)[0]) == upto
    np.testing.assert_array_equal(on.records["target"][:upto], off.records["target"][:upto])
    r = on.records[:upto]
    corrected = np.any(r["correction"] != 0, axis=1)
    clipped = np.any(r["intervention"] != 0, axis=1)
    assert np.any(corrected & clipped & (r["state"] == RUNNING))  # the case this is about is there
    sent_open_loop = off.records["command"][:upto].astype(float)
    old = (r["command"] - r["correction"]).astype(float)
    assert np.abs(old - sent_open_loop).max() > 1e-3  # command - correction is not it (100 x the tolerance below) ...
    q, how = on.open_loop_commands()
    assert "safety filter" in how
    np.testing.assert_allclose(q[:upto], sent_open_loop, atol=1e-5)  # ... this is
    traj = on.commands_trajectory("op3", without_correction=True)
    np.testing.assert_array_equal(traj.joint_pos, q)
    # what the check is given moves within the loop's velocity limits, as the sent commands do
    from ros_free_bridge.robots import bridge_limits, resolve_robot

    vmax = bridge_limits(resolve_robot("op3").hardware_config()).max_velocity
    assert np.all(np.abs(np.diff(q, axis=0)) <= vmax * 0.01 + 1e-4)


@pytest.mark.slow
def test_events_that_do_not_describe_the_run_are_refused(op3_runs, tmp_path):
    on, _ = op3_runs
    src = tmp_path / "t.dftl"
    _copy_with_events(on, src, lambda e: {**e, "max_velocity": [v * 0.5 for v in e["max_velocity"]]})
    with pytest.raises(BridgeError, match="does not belong to this run"):
        read_telemetry(src).open_loop_commands()
    _copy_with_events(on, src, lambda e: {**e, "start": e["start"][:3]})
    with pytest.raises(BridgeError, match="'start' must be 20 finite numbers"):
        read_telemetry(src).open_loop_commands()


def _copy_with_events(tel, path, edit):
    """A copy of ``tel``'s records at ``path`` with its safety_filter event changed by ``edit``."""
    with TelemetryWriter(path, tel.joint_names, tel.rate_hz) as w:
        for rec in tel.records:
            w.record(**{name: rec[name] for name in tel.records.dtype.names})
        for e in tel.events:
            w.event(**(edit(e) if e["kind"] == "safety_filter" else e))


# -- files written by hand (the reader on its own) ---------------------------------------
LIMITS = JointLimits(("a", "b"), [-1.0, -1.0], [1.0, 1.0], [2.0, 2.0], [40.0, 40.0])
DT = 0.01


def _file(path, degrade_at=None, log_degrade=True, safety_event=True):
    """Two joints stepped to 0.5 rad: joint a corrected by 0.05 rad from tick 3 on (its corrected
    command clipped by the filter), joint b never; the velocity limit halved from record
    ``degrade_at`` on, as the loop's degraded mode does. Returns the open-loop commands
    (a filter fed the targets alone)."""
    sent, open_loop = SafetyFilter(LIMITS, DT), SafetyFilter(LIMITS, DT)
    start = sent.reset(np.zeros(2))
    open_loop.reset(start)
    slow = JointLimits(LIMITS.names, LIMITS.lower, LIMITS.upper, LIMITS.max_velocity * 0.5, LIMITS.max_acceleration)
    expected = []
    with TelemetryWriter(path, LIMITS.names, 1 / DT) as w:
        if safety_event:
            w.event(
                "safety_filter",
                dt=DT,
                start=start,
                lower=LIMITS.lower,
                upper=LIMITS.upper,
                max_velocity=LIMITS.max_velocity,
                max_acceleration=LIMITS.max_acceleration,
            )
        for k in range(40):
            if k == degrade_at:
                sent.limits = open_loop.limits = slow
                if log_degrade:
                    w.event("degraded", factor=0.5, record=k, max_velocity=slow.max_velocity)
            target = np.array([0.5, 0.5]) if k else start
            correction = np.array([0.05 if k >= 3 else 0.0, 0.0])
            command, flags = sent.step(target + correction)
            expected.append(open_loop.step(target)[0])
            w.record(t=k * DT, tick=k, target=target, correction=correction, command=command, intervention=flags)
    return np.array(expected)


def test_a_clipped_corrected_command_gives_back_the_filtered_target(tmp_path):
    expected = _file(tmp_path / "t.dftl")
    tel = read_telemetry(tmp_path / "t.dftl")
    r = tel.records
    old = (r["command"] - r["correction"]).astype(float)
    assert np.abs(old[:, 0] - expected[:, 0]).max() > 0.01  # the old reading: wrong on joint a
    q, _ = tel.open_loop_commands()
    np.testing.assert_allclose(q, expected, atol=1e-6)


def test_a_degraded_run_is_filtered_with_the_slower_limits_from_its_record_on(tmp_path):
    expected = _file(tmp_path / "t.dftl", degrade_at=5)
    q, _ = read_telemetry(tmp_path / "t.dftl").open_loop_commands()
    np.testing.assert_allclose(q, expected, atol=1e-6)
    # without the degraded event the filtered targets leave the sent commands on joint b: refused
    _file(tmp_path / "u.dftl", degrade_at=5, log_degrade=False)
    with pytest.raises(BridgeError, match="joint 'b'"):
        read_telemetry(tmp_path / "u.dftl").open_loop_commands()


def test_an_older_file_without_the_filter_event_is_read_as_before_and_says_so(tmp_path):
    _file(tmp_path / "t.dftl", safety_event=False)
    tel = read_telemetry(tmp_path / "t.dftl")
    q, how = tel.open_loop_commands()
    r = tel.records
    np.testing.assert_allclose(q, (r["command"] - r["correction"]).astype(float))
    assert "inexact" in how
    traj = tel.commands_trajectory("x", without_correction=True)
    assert "inexact" in traj.meta["source"]


def test_a_run_without_corrections_gives_its_commands(tmp_path):
    with TelemetryWriter(tmp_path / "t.dftl", ["a"], 100.0) as w:
        for k in range(5):
            w.record(t=k / 100, tick=k, target=[0.3], command=[0.01 * k])
    q, _ = read_telemetry(tmp_path / "t.dftl").open_loop_commands()
    np.testing.assert_allclose(q[:, 0], 0.01 * np.arange(5), atol=1e-7)


def test_a_damaged_filter_event_names_its_field(tmp_path):
    _file(tmp_path / "t.dftl")
    events = tmp_path / "t.dftl.events.jsonl"
    lines = [json.loads(x) for x in events.read_text().splitlines()]
    lines[0]["dt"] = 0.02  # not the file's 100 Hz
    events.write_text("".join(json.dumps(e) + "\n" for e in lines))
    with pytest.raises(BridgeError, match="'dt'"):
        read_telemetry(tmp_path / "t.dftl").open_loop_commands()
