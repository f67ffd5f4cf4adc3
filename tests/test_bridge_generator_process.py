"""The partner generator in its own process, and the catch-up policy of the partner core.

Real parts: a real (tiny, untrained) DualFlow checkpoint on disk, run by a real child
process (``python -m ros_free_bridge.partner.child``) over pipes; the bundled op3
model's CasADi retargeter; the op3 hardware config's limits; the record-only transport.
"""

import os
import signal
import threading
import time

import numpy as np
import pytest

from dualflow.streaming import StreamConfig
from dualflow.synthetic import make_leader
from ros_free_bridge.control.loop import ControlLoop, LoopConfig
from ros_free_bridge.control.targets import TargetBuffer
from ros_free_bridge.errors import BridgeError
from ros_free_bridge.partner.core import PartnerCore, PartnerTarget
from ros_free_bridge.partner.pipeline import PartnerPipeline
from ros_free_bridge.partner.process import GeneratorConfig, GeneratorProcess
from ros_free_bridge.partner.reactor import ReactorStage
from ros_free_bridge.partner.retarget_stage import RetargetStage
from ros_free_bridge.partner.wire import Channel, decode_actor, decode_target, encode_actor, encode_target
from ros_free_bridge.robots import bridge_limits, resolve_robot
from ros_free_bridge.sources.replay import MotionReplaySource
from ros_free_bridge.sources.udp import ActorFrame
from ros_free_bridge.transports.record import RecordTransport


@pytest.fixture(scope="module")
def limits():
    return bridge_limits(resolve_robot("op3").hardware_config())


def _generator(tiny_checkpoint, limits, **kw):
    cfg = dict(robot="op3", joint_names=list(limits.names), checkpoint=str(tiny_checkpoint), window=16, steps=2, hop=3)
    cfg.update(kw)
    return GeneratorProcess(GeneratorConfig(**cfg))


def _loop(limits, buf, stop_policy="hold"):
    tr = RecordTransport(limits.names, initial=limits.clip(np.zeros(limits.n)))
    loop = ControlLoop(
        tr, limits, buf, LoopConfig(handle_signals=False, min_ramp=0.3, rest_after=30.0, stop_policy=stop_policy)
    )
    return tr, loop


def _assert_in_limits(tr, limits):
    cmds = np.asarray(tr.commands)
    assert np.all(cmds >= limits.lower - 1e-9) and np.all(cmds <= limits.upper + 1e-9)
    assert np.all(np.abs(np.diff(cmds, axis=0)) <= limits.max_velocity * 0.01 + 1e-9)


# -- the wire format -----------------------------------------------------------------------


def test_messages_round_trip_through_a_pipe_in_pieces():
    r, w = os.pipe()
    rx = Channel(r, os.open(os.devnull, os.O_WRONLY))
    pos = np.arange(66, dtype=float).reshape(22, 3) / 7
    target = PartnerTarget(12, np.linspace(-1, 1, 20), pos, 3.25, 23, 0.125, 0.004, True)
    data = b"".join(
        [
            _framed(b"A", encode_actor(7, 1.5, pos)),
            _framed(b"T", encode_target(target)),
            _framed(b"D", b""),
        ]
    )
    got = []
    for k in range(0, len(data), 37):  # a reader sees arbitrary pieces of the byte stream
        os.write(w, data[k : k + 37])
        got += rx.receive(1.0)
    os.close(w)
    assert [k for k, _ in got] == [b"A", b"T", b"D"]
    frame = decode_actor(got[0][1])
    assert (frame.index, frame.arrival) == (7, 1.5) and np.array_equal(frame.positions, pos)
    back = decode_target(got[1][1], 20)
    assert (back.index, back.actor_frame, back.arrival, back.gen_latency, back.held) == (12, 23, 3.25, 0.125, True)
    assert np.array_equal(back.q, target.q) and np.array_equal(back.positions, pos)
    with pytest.raises(BridgeError, match="expected"):
        decode_target(got[1][1], 19)  # a joint count mismatch is caught, not misread
    settle = decode_target(encode_target(PartnerTarget(13, target.q, pos, float("nan"), 24, 0.0, 0.0, settle=True)), 20)
    assert (settle.held, settle.settle) == (False, True) and np.isnan(settle.arrival)
    assert back.contacts is None and settle.contacts is None  # none given, none invented
    for contacts in ([True, False, False, True], [False, True, True, False], [False] * 4):
        t = PartnerTarget(14, target.q, pos, 1.0, 25, 0.0, 0.0, contacts=np.array(contacts))
        assert decode_target(encode_target(t), 20).contacts.tolist() == contacts
    assert rx.receive(0.1) == [] and rx.eof
    rx.close()


def _framed(kind: bytes, payload: bytes) -> bytes:
    from ros_free_bridge.partner.wire import HEADER

    return HEADER.pack(len(payload), kind[0]) + payload


# -- the catch-up policy (deterministic: driven by frame indices, not by time) ------------


@pytest.mark.slow
def test_a_backlog_beyond_max_lag_is_dropped_held_and_reported(tiny_checkpoint):
    from retarget.robot import load_robot

    files = resolve_robot("op3")
    retarget = RetargetStage(load_robot(files.mjcf, files.profile), 30.0)
    reactor = ReactorStage(30.0, tiny_checkpoint, StreamConfig(window=16, steps=2, hop=3))
    core = PartnerCore(reactor, retarget, max_lag=6)
    leader = make_leader(3.0, 30.0, seed=1)
    frames = [ActorFrame(k, leader.positions[k], k / 30.0) for k in range(leader.n_frames)]
    out, events = [], []

    def feed(batch):
        t, e = core.feed(batch)
        out.extend(t)
        events.extend(e)
        while core.backlog:  # one window per call: drain what is due
            t, e = core.feed([])
            out.extend(t)
            events.extend(e)

    for f in frames[:30]:  # keeping up: one frame at a time
        feed([f])
    assert events == [] and core.frames_dropped == 0
    kept_up = len(out)
    last_q = out[-1].q
    feed(frames[30:60])  # the generator was away for a second: 30 frames at once
    L, hop = reactor.look_ahead, 3
    assert len(events) == 1 and events[0]["kind"] == "generator_behind"
    restart = 59 - L + 1 - hop  # newest - A + 1 - hop, A = L frames ahead (predict_next)
    assert events[0]["restart_frame"] == restart and events[0]["dropped_frames"] == restart - kept_up
    held = [t for t in out if t.held]
    assert [t.index for t in held] == list(range(kept_up, restart))
    assert all(np.array_equal(t.q, last_q) and np.isnan(t.gen_latency) for t in held)
    for f in frames[60:]:
        feed([f])
    out += core.finish()
    # the partner timeline stays whole: one target per actor frame, in order, then the robot's
    # return to its stance on the same timeline
    partner = [t for t in out if not t.settle]
    assert [t.index for t in partner] == list(range(leader.n_frames))
    assert [t.index for t in out] == list(range(len(out))) and len(out) > len(partner)
    assert core.frames_dropped == restart - kept_up and len(events) == 1
    # a generated frame is stamped with the last actor frame it depends on (i + L: the newest
    # row is encoded with a predicted next frame)
    gen = [t for t in out if not t.held and t.index + L < leader.n_frames]
    assert all(t.actor_frame == t.index + L and t.arrival == frames[t.index + L].arrival for t in gen)
    # the end-of-stream flush: the arrival actor frame i + L would have had on the actor's clock
    flush = [t for t in partner if t.index + L >= leader.n_frames]
    assert len(flush) == L and all(t.actor_frame == t.index + L for t in flush)
    np.testing.assert_allclose([t.arrival for t in flush], [(t.index + L) / 30.0 for t in flush])


# -- the process ---------------------------------------------------------------------------


@pytest.mark.slow
def test_the_process_pipeline_streams_every_frame_and_exits(tiny_checkpoint, limits):
    gen = _generator(tiny_checkpoint, limits).start()
    assert gen.delay_frames == gen.ready_info["look_ahead"] + 3 - 1  # L + hop - 1 (predict_next)
    assert gen.ready_info["frames_ahead"] == gen.ready_info["look_ahead"]
    assert gen.ready_info["pid"] == gen.pid != os.getpid()
    # the model's objects are out of the collector's way (a full pass over them: ~150 ms)
    assert gen.ready_info["gc_frozen_objects"] > 10_000
    buf = TargetBuffer(30.0)
    tr, loop = _loop(limits, buf)
    leader = make_leader(1.5, 30.0, seed=2)
    pipe = PartnerPipeline(MotionReplaySource(leader), None, None, buf, loop.ready, record=True, core=gen)
    pipe.start()
    summary = loop.run()
    pipe.join(10)
    assert summary.end_state == "STOPPED" and summary.reason == "the motion ended"
    assert pipe.frames_in == leader.n_frames
    assert pipe.frames_out == leader.n_frames == len(pipe.partner_positions)
    # how many the loop plays depends on the machine's load (late frames are skipped): not asserted
    assert 0 < summary.frames_played <= pipe.frames_out + pipe.settle_frames
    assert not pipe.alive
    assert gen.process.wait(10) == 0  # the pipeline closed its input: the child ended cleanly
    _assert_in_limits(tr, limits)


@pytest.mark.slow
def test_a_generator_process_that_dies_stops_the_robot_safely(tiny_checkpoint, limits):
    gen = _generator(tiny_checkpoint, limits).start()
    buf = TargetBuffer(30.0)
    tr, loop = _loop(limits, buf, stop_policy="limp")
    pipe = PartnerPipeline(MotionReplaySource(make_leader(30.0, 30.0, seed=3)), None, None, buf, loop.ready, core=gen)

    def kill_when_streaming():
        while loop.summary.frames_played < 5 and loop.state.name not in ("STOPPED", "ESTOP"):
            time.sleep(0.01)
        os.kill(gen.pid, signal.SIGKILL)

    killer = threading.Thread(target=kill_when_streaming, daemon=True)
    pipe.start()
    killer.start()
    summary = loop.run()
    pipe.join(10)
    killer.join(10)
    assert summary.frames_played >= 5
    assert summary.end_state == "STOPPED"
    assert "generator failed" in summary.reason and "ended unexpectedly" in summary.reason
    assert tr.stopped_with == "limp" and tr.torque_events[-1][1] is False  # torque off at the end
    assert not pipe.alive and gen.process.poll() == -signal.SIGKILL
    _assert_in_limits(tr, limits)


@pytest.mark.slow
def test_a_bad_checkpoint_fails_before_the_robot_moves(tmp_path, limits):
    gen = GeneratorProcess(
        GeneratorConfig(robot="op3", joint_names=list(limits.names), checkpoint=str(tmp_path / "nothing"))
    )
    with pytest.raises(BridgeError, match="nothing"):
        gen.start()
    assert gen.process.poll() is not None  # the child is gone, not left behind


@pytest.mark.slow
def test_close_ends_the_child_cleanly_while_a_forked_process_holds_our_pipe(tiny_checkpoint, limits):
    import multiprocessing as mp

    gen = _generator(tiny_checkpoint, limits).start()
    # like the bus emulator: forked after the generator started, so it holds a copy of our
    # write end and the child would never read EOF from it
    holder = mp.get_context("fork").Process(target=time.sleep, args=(60,), daemon=True)
    holder.start()
    try:
        gen.close(timeout=30)
        assert gen.process.returncode == 0  # it quit when told to (a kill would read -9)
    finally:
        holder.kill()
        holder.join()
