"""The generator's catch-up passes run only in the gap before the next actor frame (ros_free_bridge.idle_slots)."""

import pytest

from ros_free_bridge.idle_slots import IdleSlots

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
    assert slots.pass_estimate == pytest.approx(0.011)
    slots.ran(0.004)
    slots.ran(0.004)
    slots.ran(0.004)  # the 11 ms pass has left the history
    assert slots.pass_estimate == pytest.approx(0.004)


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

