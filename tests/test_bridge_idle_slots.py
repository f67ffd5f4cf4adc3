"""The generator's catch-up passes run only in the gap before the next actor frame
(ros_free_bridge.partner.idle_slots)."""

import pytest

from ros_free_bridge.partner.idle_slots import IdleSlots

PERIOD = 1 / 30


def test_a_pass_starts_only_if_it_ends_before_the_next_frame():
    slots = IdleSlots(PERIOD, guard=0.002)
    slots.arrived(10.0)
    slots.ran(0.008)
    # the next frame is due at 10.0333: a pass of 8 ms (+ 2 ms guard) fits until 10.0233
    assert slots.fits(10.020)
    assert slots.fits(10.0233)
    assert not slots.fits(10.0240)
    assert not slots.fits(10.0333)


def test_the_longest_recent_pass_is_the_estimate():
    slots = IdleSlots(PERIOD, guard=0.0, history=3)
    for d in (0.004, 0.011, 0.005):
        slots.ran(d)
    assert slots.estimate() == pytest.approx(0.011)
    slots.ran(0.004)
    slots.ran(0.004)
    slots.ran(0.004)  # the 11 ms pass has left the history
    assert slots.estimate() == pytest.approx(0.004)


def test_each_kind_of_work_is_timed_on_its_own():
    """A cheap kind (the prefetch) still fits in a gap that the dearest kind (a feed) does not."""
    slots = IdleSlots(PERIOD, guard=0.002)
    slots.arrived(10.0)
    slots.ran(0.015, "feed")
    slots.ran(0.003, "prefetch")
    assert slots.estimate("feed") == pytest.approx(0.015) and slots.estimate("prefetch") == pytest.approx(0.003)
    assert slots.estimate("start") == 0.0  # never timed: it runs, and is timed then
    now = 10.020  # 13.3 ms before the next frame
    assert slots.fits(now, "prefetch") and not slots.fits(now, "feed")
    assert slots.wait(now, "prefetch") == 0.0 and slots.wait(now, "feed") > 0.0
    urgent = IdleSlots(PERIOD, guard=0.002, urgent=("takeover",))
    urgent.arrived(10.0)
    urgent.ran(0.015, "takeover")
    urgent.ran(0.015, "feed")
    assert urgent.fits(now, "takeover") and urgent.wait(now, "takeover") == 0.0  # any gap
    assert not urgent.fits(now, "feed")


def test_a_paused_source_does_not_starve_catch_up_work():
    slots = IdleSlots(PERIOD, guard=0.002, late=0.010)
    slots.arrived(5.0)
    slots.ran(0.040)  # a pass longer than the gap: never fits before the next frame
    assert not slots.fits(5.001)
    # the frame due at 5.0333 has not come 10 ms later: the source paused, work may run
    assert not slots.fits(5.043)
    assert slots.fits(5.0434)
    wait = slots.wait(5.001)
    assert 5.001 + wait > 5.0433 and wait < 0.043
    assert slots.fits(5.001 + wait)


def test_the_newest_arrival_counts_and_no_frame_means_no_gate():
    slots = IdleSlots(PERIOD)
    slots.ran(0.5)
    assert slots.fits(0.0) and slots.wait(0.0) == 0.0  # no frame yet: nothing to wait for
    slots.arrived(2.0)
    slots.arrived(1.9)  # an older frame reported late does not move the next due time back
    assert not slots.fits(2.0 + PERIOD + 0.001)
    assert slots.fits(2.0 + PERIOD + slots.late + 0.001)


def test_a_bad_period_is_refused():
    with pytest.raises(ValueError, match="period"):
        IdleSlots(0.0)


def test_urgent_catch_up_runs_in_any_gap_other_work_only_where_it_fits(tiny_checkpoint):
    """The generator's scheduler (PartnerCore) on a real incremental stream, every kind of
    piece timed far longer than a frame gap: only the pieces that a frame would otherwise do
    in full (the streamer's ``urgent_jobs``, dualflow.streaming.CatchUpWork: feeding the start
    about to take over, making the next start) still run; feeds of the background start and
    the prefetch wait."""
    from dualflow.streaming import StreamConfig
    from dualflow.synthetic import make_leader
    from retarget.robot import load_robot
    from ros_free_bridge.partner.core import PartnerCore
    from ros_free_bridge.partner.reactor import ReactorStage
    from ros_free_bridge.partner.retarget_stage import RetargetStage
    from ros_free_bridge.robots import resolve_robot
    from ros_free_bridge.sources.udp import ActorFrame

    files = resolve_robot("op3")
    reactor = ReactorStage(30.0, tiny_checkpoint, StreamConfig(window=40, steps=2, hop=1, incremental=True))
    core = PartnerCore(reactor, RetargetStage(load_robot(files.mjcf, files.profile), 30.0))
    assert reactor.urgent_jobs == ("takeover", "start")
    for kind in reactor.streamer.IDLE_JOBS:
        core.catch_up.slots.ran(1.0, kind)  # no piece fits a 33 ms gap
    leader = make_leader(3.0, 30.0, seed=2)
    ran, waited = set(), set()
    for k in range(leader.n_frames):
        arrival = k * PERIOD
        core.feed([ActorFrame(k, leader.positions[k], arrival)])
        while core.backlog:
            core.feed([])
        now = arrival + 0.001
        assert (core.idle_wait(now) == 0.0) == core.idle_ready(now)  # the child process waits on idle_wait
        while core.idle_ready(now):
            job = reactor.idle_jobs()[0] if reactor.idle_jobs()[0] in reactor.urgent_jobs else None
            assert job is not None, f"frame {k}: {reactor.idle_jobs()} ran without fitting"
            core.idle_step(now)
            ran.add(job)
        waited.update(reactor.idle_jobs())
    assert ran == {"takeover", "start"}
    assert {"feed", "prefetch"} <= waited
