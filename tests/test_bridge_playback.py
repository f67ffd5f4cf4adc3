"""The loop's playback clock (ros_free_bridge.control.playback) and the buffer's interpolation and extrapolation."""

from __future__ import annotations

import numpy as np
import pytest

from ros_free_bridge.control.playback import PlaybackClock, PlaybackPolicy
from ros_free_bridge.control.targets import TargetBuffer, TargetFrame

FPS = 30.0


def _drive(clock, arrival_of, t_end, dt=0.01, first=0):
    """Run the loop's calls at 100 Hz; frames arrive at ``arrival_of(k)``. Returns [(now, motion time)]."""
    out, k, now = [], first, arrival_of(first)
    while now < t_end:
        while arrival_of(k + 1) <= now:
            k += 1
        clock.arrived(k, now)
        out.append((now, clock.motion_time(now)))
        now += dt
    return np.array(out)


def test_the_fixed_clock_keeps_where_the_first_frame_put_it():
    clock = PlaybackClock(FPS, 3, now=10.0, policy=PlaybackPolicy(margin=0.05, fixed=True))
    track = _drive(clock, lambda k: 10.0 + (k - 3) / FPS + 0.2, 12.0, first=3)  # later frames come 200 ms late
    np.testing.assert_allclose(track[:, 1], track[:, 0] - (10.0 + 0.05 - 3 / FPS))


def test_the_adaptive_clock_settles_at_the_delay_the_frames_actually_have():
    delay = 0.120  # frame k arrives 120 ms after its ideal time k / fps (a steady generator)
    first_late = 0.400  # the first frame was 400 ms late (a slow first window)

    def arrival(k):
        return k / FPS + delay + (first_late - delay if k == 0 else 0.0)

    clock = PlaybackClock(FPS, 0, now=arrival(0), policy=PlaybackPolicy(margin=0.02, lead_frames=1.0, window_s=1.0))
    track = _drive(clock, arrival, 8.0)
    speed = np.diff(track[:, 1]) / np.diff(track[:, 0])
    assert np.all(speed >= 0.5 - 1e-9) and np.all(speed <= 1.2 + 1e-9)  # bounded, never backwards
    # settled: frame k plays lead + margin after it arrives (as the loop sees it: at its next
    # 10 ms tick), not 400 ms + margin after
    assert delay + 1 / FPS + 0.02 - 1e-9 <= clock.t0 <= delay + 1 / FPS + 0.02 + 0.01
    # and every frame was there when the clock reached the frame before it (interpolation)
    for now, motion in track[track[:, 0] > 3.0]:
        k_played = int(np.floor(motion * FPS))
        assert arrival(k_played + 1) <= now + 1e-9


def test_a_burst_of_frames_no_actor_paced_does_not_speed_playback_up():
    """Frames 0-89 arrive 150 ms after their time; then frames 90-209 arrive all at once (the
    robot's return to its stance, made in one go after the stream): counted as arrivals they
    would pull the clock earlier at 1.2x real time; untimed, playback stays at real time."""

    def run(timed: bool):
        clock = PlaybackClock(FPS, 0, now=0.15, policy=PlaybackPolicy(margin=0.02, lead_frames=1.0, window_s=1.0))
        track = []
        for now in np.arange(0.15, 5.0, 0.01):
            burst = now >= 89 / FPS + 0.15
            clock.arrived(209 if burst else min(int((now - 0.15) * FPS), 89), now, timed=timed or not burst)
            track.append((now, clock.motion_time(now), burst))
        track = np.array(track)
        after = track[track[:, 2] == 1]
        return after[-1, 1] - after[0, 1], after[-1, 0] - after[0, 0]  # motion time played, wall time

    played, elapsed = run(timed=True)
    assert played > elapsed + 0.08  # counted as arrivals, the burst sped playback up (0.1 s here)
    played, elapsed = run(timed=False)
    assert abs(played - elapsed) < 1 / FPS  # real time (the old arrivals' quantile drifts by under a frame)


def test_the_adaptive_clock_slows_down_for_late_frames_and_catches_up_after():
    def arrival(k):
        return k / FPS + (0.3 if 60 <= k < 70 else 0.05)  # a stall of 250 ms around 2 s

    clock = PlaybackClock(FPS, 0, now=arrival(0), policy=PlaybackPolicy(margin=0.02, lead_frames=0.0, window_s=1.0))
    track = _drive(clock, arrival, 8.0)

    def delay_at(t):
        return t - track[np.searchsorted(track[:, 0], t), 1]  # now - motion time

    assert max(delay_at(t) for t in np.arange(2.3, 3.5, 0.05)) > 0.2  # it waited for the late frames
    assert 0.05 + 0.02 <= delay_at(7.9) <= 0.05 + 0.02 + 0.01  # and came back down (to the tick)


def _buffer(extrapolate):
    buf = TargetBuffer(FPS, interpolation="cubic", extrapolate=extrapolate)
    for k in range(4):
        buf.push(TargetFrame(k, np.array([0.1 * k, -0.2 * k]), 0.0))
    return buf


def test_the_buffer_continues_the_newest_frame_with_its_speed_fading_over_extrapolate_frames():
    buf = _buffer(2.0)  # velocity (0.1, -0.2) per frame; q_n + m (s - s^2 / 2E) for s <= E = 2
    s = buf.sample(3.5 / FPS)
    assert s.extrapolated and not s.starved and s.newest.index == 3
    np.testing.assert_allclose(s.q, np.array([0.3, -0.6]) + (0.5 - 0.25 / 4) * np.array([0.1, -0.2]))
    eps = 1e-6  # the fade ends at rest: no jump in velocity where the hold begins
    np.testing.assert_allclose((buf.sample((5.0 + eps) / FPS).q - buf.sample(5.0 / FPS).q) / eps, 0.0, atol=1e-9)
    np.testing.assert_allclose((buf.sample(5.0 / FPS).q - buf.sample((5.0 - eps) / FPS).q) / eps, 0.0, atol=1e-5)
    s = buf.sample(6.5 / FPS)  # beyond E: held where the fade ended (no jump back), and starved
    assert s.starved and not s.extrapolated
    np.testing.assert_allclose(s.q, [0.3 + 0.1, -0.6 - 0.2])
    buf.close()
    s = buf.sample(3.5 / FPS)  # the stream ended: never extrapolate past the last frame
    assert s.finished and not s.extrapolated


def test_without_extrapolation_the_buffer_holds():
    s = _buffer(0.0).sample(3.5 / FPS)
    assert s.starved and not s.extrapolated
    np.testing.assert_allclose(s.q, [0.3, -0.6])
    with pytest.raises(ValueError, match="extrapolate"):
        TargetBuffer(FPS, extrapolate=-1.0)


def test_one_late_frame_does_not_hold_the_clock_back_but_a_late_run_does():
    # frame 60 is 50 ms late (the next one, in order behind it, 17 ms)
    def arrival(k):
        return k / FPS + (0.10 if k == 60 else 0.05)

    robust = PlaybackClock(FPS, 0, now=arrival(0), policy=PlaybackPolicy(margin=0.02, lead_frames=0.0))  # q = 0.9
    strict = PlaybackClock(FPS, 0, now=arrival(0), policy=PlaybackPolicy(margin=0.02, lead_frames=0.0, quantile=1.0))
    a, b = _drive(robust, arrival, 2.6), _drive(strict, arrival, 2.6)

    def lag(track):
        return np.max(track[:, 0] - track[:, 1])

    assert lag(a[a[:, 0] > 1.5]) < 0.05 + 0.02 + 0.011
    assert lag(b[b[:, 0] > 1.5]) > 0.1 + 0.02


@pytest.mark.parametrize("quantile", [0.5, 0.9, 1.0])
def test_the_clock_target_is_the_quantile_of_the_recent_arrival_offsets(quantile):
    """t0* = q-quantile (numpy's default, linear) of the last second's offsets + lead + margin,
    whatever the order frames arrive in and however often the loop asks."""
    rng = np.random.default_rng(3)
    clock = PlaybackClock(FPS, 0, 0.0, PlaybackPolicy(margin=0.02, lead_frames=1.0, quantile=quantile))
    t = 0.0
    for _ in range(600):
        t += 0.01 + rng.uniform(0.0, 0.004)
        clock.arrived(int(t * FPS - rng.uniform(0.0, 2.0)), t)
        clock.motion_time(t)
        offsets = [a for arrival, a in clock._offsets]
        assert all(t - arrival <= 1.0 for arrival, _ in clock._offsets)
        expected = np.quantile(offsets, quantile) + 1.0 / FPS + 0.02
        assert clock.target_t0() == pytest.approx(expected, abs=1e-12)


def test_the_playback_quantile_is_checked_where_it_is_set():
    from ros_free_bridge.control.loop import LoopConfig
    from ros_free_bridge.errors import BridgeError

    assert LoopConfig(playback_quantile=0.5).playback_quantile == 0.5
    for bad in (0.0, 1.5, float("nan")):
        with pytest.raises(BridgeError, match="playback_quantile"):
            LoopConfig(playback_quantile=bad)
    with pytest.raises(BridgeError, match="playback_margin"):
        LoopConfig(playback_margin=-0.01)


def _filled(q, interpolation="cubic", extrapolate=0.0):
    buf = TargetBuffer(FPS, interpolation=interpolation, extrapolate=extrapolate)
    for k, row in enumerate(q):
        buf.push(TargetFrame(k, np.asarray(row, float), 0.0))
    return buf


def test_cubic_interpolation_is_exact_for_constant_acceleration():
    # the causal tangent (3 q_k - 4 q_k-1 + q_k-2) / 2 is exact on a parabola, and so is the
    # Hermite segment built on it (a backward difference alone would bend the curve)
    k = np.arange(8.0)
    q = np.stack([0.02 * k**2 - 0.1 * k + 0.3, -0.05 * k**2 + 0.4 * k], axis=1)
    buf = _filled(q)
    for pos in np.linspace(2.0, 6.99, 40):
        np.testing.assert_allclose(
            buf.sample(pos / FPS).q, [0.02 * pos**2 - 0.1 * pos + 0.3, -0.05 * pos**2 + 0.4 * pos], atol=1e-12
        )


def test_cubic_segments_never_change_when_later_frames_arrive_and_join_with_continuous_velocity():
    rng = np.random.default_rng(3)
    q = np.cumsum(np.cumsum(rng.normal(0.0, 0.01, (12, 3)), axis=0), axis=0)  # rough, like generated motion
    full = _filled(q)
    eps = 1e-6
    for k in range(1, 10):
        upto = _filled(q[: k + 2])  # frame k + 1 is the newest: segment [k, k + 1] is playable
        for w in (0.0, 0.3, 0.7, 0.999):
            np.testing.assert_allclose(upto.sample((k + w) / FPS).q, full.sample((k + w) / FPS).q, atol=1e-12)
        # velocity into and out of frame k: one-sided differences agree
        at = full.sample(k / FPS).q
        np.testing.assert_allclose(at, q[k], atol=1e-12)
        left = (at - full.sample((k - eps) / FPS).q) / eps
        right = (full.sample((k + eps) / FPS).q - at) / eps
        np.testing.assert_allclose(left, right, atol=1e-4)


def test_extrapolation_continues_the_last_segment_along_its_end_tangent():
    q = np.array([[0.0], [0.1], [0.3], [0.6]])  # accelerating: tangent at frame 3 is 1.5 * 0.6 - 2 * 0.3 + 0.5 * 0.1
    buf = _filled(q, extrapolate=1.0)
    s = buf.sample(3.5 / FPS)
    assert s.extrapolated
    np.testing.assert_allclose(s.q, [0.6 + (0.5 - 0.125) * 0.35])
    eps = 1e-6  # no kink where the last segment ends and the extrapolation begins
    left = (buf.sample(3.0 / FPS).q - buf.sample((3.0 - eps) / FPS).q) / eps
    right = (buf.sample((3.0 + eps) / FPS).q - buf.sample(3.0 / FPS).q) / eps
    np.testing.assert_allclose(left, right, atol=1e-4)


class _PushDuringSample(TargetBuffer):
    """A buffer whose producer thread pushes ``pending`` frames just after a ``sample`` call
    took its state, before the caller's next look at the buffer (the race of two threads)."""

    pending: list = []

    def sample(self, t):
        s = super().sample(t)
        pushing, self.pending = self.pending, []
        for frame in pushing:
            self.push(frame)
        return s


def _late_frame_commands(omega, late=True, arrival="before"):
    """Commands at 100 Hz over a stream moving at 0.5 rad/s whose frame 11 stops it (q_11 = q_10):
    ``late`` frame 11 comes at frame time 10.5, while the loop extrapolates frame 10 (E = 3),
    else in time (before frame 10 plays). Motion time = wall time; returns (times, commands).
    ``arrival``: a tick's new frames are pushed "before" its sample, "during" it (after the
    buffer's state was read) or "after" it."""
    from ros_free_bridge.control.targets import RevisionSmoother

    v = 0.5 / FPS  # rad per frame
    q = [np.array([v * k]) for k in range(11)] + [np.array([v * 10])] + [np.array([v * 10])] * 20
    buf = _PushDuringSample(FPS, interpolation="cubic", extrapolate=3.0)
    curve = RevisionSmoother(buf, omega)
    times, out, pushed = np.arange(0.0, 1.0, 0.01), [], 0
    for t in times:
        due = t * FPS + (0.0 if late else 1.5)  # frames that have arrived by motion time t
        new = []
        while pushed < len(q) and pushed <= due + 1e-9:
            new.append(TargetFrame(pushed, q[pushed], 0.0))
            pushed += 1
        if arrival == "before" or pushed == len(new):  # the first frames start the stream
            for frame in new:
                buf.push(frame)
        elif arrival == "during":
            buf.pending = new
        out.append(curve.sample(t, t).q[0])
        if arrival == "after" and pushed != len(new):
            for frame in new:
                buf.push(frame)
    return times, np.array(out)


def test_a_frame_pushed_while_the_smoother_samples_counts_as_the_next_ticks_revision():
    # the producer thread may push between the buffer's read and anything the smoother reads
    # after it: the revision must then be noticed on the next tick, exactly as if the frame had
    # come after this tick, not lost (which would jump the command by the whole revision)
    _, during = _late_frame_commands(15.0, arrival="during")
    _, after = _late_frame_commands(15.0, arrival="after")
    _, before = _late_frame_commands(15.0)
    np.testing.assert_array_equal(during, after)
    assert np.abs(after - before).max() > 1e-4  # the arrival tick matters, so the test can tell


def test_a_late_frame_joins_the_command_to_the_new_curve_without_a_jump():
    t, smooth = _late_frame_commands(15.0)
    _, raw = _late_frame_commands(0.0)
    _, ideal = _late_frame_commands(0.0, late=False)

    def vel(c):
        return np.diff(c) / 0.01

    # without smoothing the late frame's curve replaces the extrapolated one at once: a step in
    # velocity far beyond any in the curve itself; with it the velocity changes no more than the
    # in-time curve's does
    assert np.abs(np.diff(vel(raw))).max() > 3 * np.abs(np.diff(vel(ideal))).max()
    assert np.abs(np.diff(vel(smooth))).max() <= 1.5 * np.abs(np.diff(vel(ideal))).max()
    # and it then joins the curve: within 1 % of the extrapolation error after 0.5 s
    err = np.abs(smooth - raw)
    assert err.max() > 1e-3 and err[t > 0.35 + 0.5].max() < 0.01 * err.max()


def test_without_revisions_the_smoother_is_the_curve_itself():
    from ros_free_bridge.control.targets import RevisionSmoother

    buf = _filled(np.array([[0.0], [0.1], [0.3], [0.6], [0.7]]), extrapolate=3.0)
    curve = RevisionSmoother(buf, 15.0)
    for t in np.arange(0.0, 6.0 / FPS, 0.01):
        np.testing.assert_array_equal(curve.sample(t, t).q, buf.sample(t).q)
    with pytest.raises(ValueError, match="omega"):
        RevisionSmoother(buf, -1.0)


def test_the_revision_smoothing_is_checked_where_it_is_set():
    from ros_free_bridge.control.loop import LoopConfig
    from ros_free_bridge.errors import BridgeError

    assert LoopConfig(revision_smoothing=0.0).revision_smoothing == 0.0
    for bad in (-1.0, float("inf"), float("nan")):
        with pytest.raises(BridgeError, match="revision_smoothing"):
            LoopConfig(revision_smoothing=bad)
