"""The safety filter: whatever comes in, what goes out is inside every limit."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ros_free_bridge.control.safety import Intervention, JointLimits, SafetyFilter, min_jerk, min_jerk_duration
from ros_free_bridge.errors import BridgeError

DT = 0.01
LIMITS = JointLimits(("a", "b", "c"), [-1.0, -0.5, 0.0], [1.0, 0.5, 2.0], [2.0, 4.0, 1.0], [20.0, 40.0, 10.0])


def _check_invariants(cmds, limits=LIMITS, dt=DT):
    cmds = np.asarray(cmds)
    assert np.all(np.isfinite(cmds))
    assert np.all(cmds >= limits.lower - 1e-12) and np.all(cmds <= limits.upper + 1e-12)
    steps = np.diff(cmds, axis=0)
    assert np.all(np.abs(steps) <= limits.max_velocity * dt + 1e-12)


targets = st.lists(
    st.lists(st.one_of(st.floats(-10, 10), st.just(float("nan")), st.just(float("inf"))), min_size=3, max_size=3),
    min_size=1,
    max_size=60,
)


@settings(max_examples=200, deadline=None)
@given(targets)
def test_no_command_ever_leaves_the_limits(seq):
    f = SafetyFilter(LIMITS, DT)
    cmds = [f.reset([0.0, 0.0, 1.0])]
    for target in seq:
        cmds.append(f.step(np.array(target))[0])
    _check_invariants(cmds)


def test_smooth_in_limit_targets_pass_unchanged():
    f = SafetyFilter(LIMITS, DT)
    f.reset([0.0, 0.0, 1.0])
    t = np.arange(1, 200) * DT
    for ti in t:
        target = np.array([0.3 * (1 - np.cos(ti)), -0.1 * (1 - np.cos(2 * ti)), 1.0 + 0.2 * (1 - np.cos(ti))])
        cmd, flags = f.step(target)
        np.testing.assert_allclose(cmd, target, atol=1e-12)
        assert not flags.any()


def test_nan_target_is_rejected_and_the_last_command_held():
    f = SafetyFilter(LIMITS, DT)
    f.reset([0.2, 0.1, 1.0])
    cmd, flags = f.step(np.array([np.nan, 0.1, 1.0]))
    np.testing.assert_allclose(cmd, [0.2, 0.1, 1.0])  # whole pose rejected, not just the NaN joint
    assert np.all(flags & Intervention.NONFINITE)


def test_a_jump_is_spread_over_ticks_and_flagged():
    f = SafetyFilter(LIMITS, DT)
    f.reset([0.0, 0.0, 1.0])
    cmds = [f.step(np.array([0.9, 0.0, 1.0]))[0] for _ in range(300)]
    _check_invariants(cmds)
    accel = np.diff(np.asarray(cmds)[:, 0], 2)
    assert np.max(np.abs(accel)) <= LIMITS.max_acceleration[0] * DT * DT + 1e-12
    assert cmds[-1][0] == pytest.approx(0.9)


def test_target_beyond_limit_is_clamped_and_braked():
    f = SafetyFilter(LIMITS, DT)
    f.reset([0.0, 0.0, 1.0])
    flags_seen = 0
    cmds = []
    for _ in range(200):
        cmd, flags = f.step(np.array([5.0, 0.0, 1.0]))
        cmds.append(cmd)
        flags_seen |= int(flags[0])
    assert cmds[-1][0] == pytest.approx(1.0)
    assert flags_seen & Intervention.POSITION
    # braking keeps the deceleration into the limit within the acceleration limit
    accel = np.diff(np.asarray(cmds)[:, 0], 2)
    assert np.max(np.abs(accel)) <= LIMITS.max_acceleration[0] * DT * DT * 1.0001


def test_limits_intersection_takes_the_tighter_side():
    other = JointLimits(("c", "b", "a"), [0.5, -1.0, -2.0], [1.5, 0.2, 2.0], [3.0, 1.0, 1.0], [5.0, 50.0, 30.0])
    both = LIMITS.intersect(other)
    np.testing.assert_allclose(both.lower, [-1.0, -0.5, 0.5])
    np.testing.assert_allclose(both.upper, [1.0, 0.2, 1.5])
    np.testing.assert_allclose(both.max_velocity, [1.0, 1.0, 1.0])


def test_bad_limits_and_bad_reset_are_user_errors():
    with pytest.raises(BridgeError, match="'b'"):
        JointLimits(("a", "b"), [0, 1], [1, 1], 1, 1)
    f = SafetyFilter(LIMITS, DT)
    with pytest.raises(BridgeError, match="reset"):
        f.step(np.zeros(3))
    with pytest.raises(BridgeError, match="finite"):
        f.reset([0.0, np.nan, 1.0])


def test_min_jerk_ramp_respects_limits_when_timed_by_min_jerk_duration():
    q0, q1 = np.array([-0.9, 0.4, 0.1]), np.array([0.8, -0.4, 1.9])
    T = min_jerk_duration(q0, q1, LIMITS)
    path = np.vstack([q0, min_jerk(q0, q1, T, DT)])
    np.testing.assert_allclose(path[-1], q1)
    vel = np.diff(path, axis=0) / DT
    assert np.all(np.abs(vel) <= LIMITS.max_velocity * 1.001)
    acc = np.diff(path, 2, axis=0) / DT**2
    assert np.all(np.abs(acc) <= LIMITS.max_acceleration * 1.05)
