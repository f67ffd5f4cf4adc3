"""Real-time replay of an actor motion (on an injected clock)."""

import time

import numpy as np

from dualflow.synthetic import make_leader
from ros_free_bridge.sources.replay import MotionReplaySource


def test_replay_releases_frames_on_their_due_time_only():
    leader = make_leader(seconds=1.0, fps=30.0, seed=3)
    now = [10.0]
    src = MotionReplaySource(leader, clock=lambda: now[0])
    assert src.poll() == []  # nothing before start
    src.start()
    first = src.poll()
    assert [f.index for f in first] == [0]
    now[0] += 0.1  # 3 more frame periods
    got = src.poll()
    assert [f.index for f in got] == [1, 2, 3]
    np.testing.assert_array_equal(got[-1].positions, leader.positions[3])
    assert got[-1].arrival == 10.0 + 3 / 30.0  # stamped at its due time
    now[0] += 5.0
    rest = src.poll()
    assert rest[-1].index == leader.n_frames - 1 and src.finished
    assert src.poll() == []


def test_looping_replay_wraps_and_never_finishes():
    leader = make_leader(seconds=0.5, fps=30.0, seed=1)
    now = [0.0]
    src = MotionReplaySource(leader, loop=True, clock=lambda: now[0])
    src.start()
    now[0] = 2.0
    frames = src.poll()
    assert len(frames) == 61 and not src.finished
    np.testing.assert_array_equal(frames[leader.n_frames].positions, leader.positions[0])


def test_next_due_says_when_the_next_frame_comes_and_the_pipeline_waits_no_longer():
    from ros_free_bridge.partner.pipeline import PartnerPipeline

    leader = make_leader(seconds=0.2, fps=30.0, seed=2)  # 6 frames
    now = [100.0]
    src = MotionReplaySource(leader, clock=lambda: now[0])
    assert src.next_due() is None  # not started
    src.start()
    assert src.next_due() == 100.0
    src.poll()
    assert src.next_due() == 100.0 + 1 / 30.0
    now[0] += 1.0
    src.poll()
    assert src.finished and src.next_due() is None

    class Soon:  # a source whose next frame is due in 0.5 ms
        def next_due(self):
            return time.monotonic() + 0.0005

    pipe = PartnerPipeline.__new__(PartnerPipeline)  # only the polling policy, no thread
    pipe.source = Soon()
    assert 0.0 <= pipe._poll_wait() <= 0.0005
    pipe.source = src  # finished: nothing due
    assert pipe._poll_wait() == PartnerPipeline.POLL_S
    pipe.source = object()  # a source that cannot say (a live UDP stream): the fixed poll interval
    assert pipe._poll_wait() == PartnerPipeline.POLL_S
