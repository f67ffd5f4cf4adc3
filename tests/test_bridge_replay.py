"""Real-time replay of an actor motion (on an injected clock)."""

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
