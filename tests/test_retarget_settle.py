"""The end of a live stream (retarget.settle): the robot steps back to its own stance and comes
to rest before the bridge's joint-space stop ramp, on the bundled op3, in physics too."""

import numpy as np
import pytest

from bench.stepping_leaders import turning_leader
from dualflow.motion import REST_POSE, Motion
from retarget.robot import load_robot
from retarget.streaming import StreamingConfig, StreamingRetargeter, trajectory_from_x
from retarget.targets import make_targets

FPS = 30.0


@pytest.fixture(scope="module")
def op3():
    return load_robot("op3")


@pytest.fixture(scope="module")
def turned(op3):
    """A person who turns at 0.9 rad/s for 2 s and stops: the stream ends with the robot's feet
    behind the turn and its body twisted over them."""
    motion = turning_leader(2.0, -0.9)
    st = StreamingRetargeter(op3, FPS, StreamingConfig(balance=True, steps=True))
    tg = make_targets(op3, motion)
    X = [st.step(tg.keypoints[t], tg.contacts[t]) for t in range(motion.n_frames)]
    frames = st.settle()
    settle = list(frames)
    return st, np.stack(X), settle, frames.steps


def _hip_yaws(rb, x):
    return np.array([x[rb.n_root + rb.joint_names.index(j)] for j in rb.joint_names if "hip_yaw" in j])


def test_the_robot_steps_back_to_its_stand_pose_and_stance(op3, turned):
    st, X, settle, steps = turned
    assert np.abs(_hip_yaws(op3, X[-1])).max() > 0.2  # the stream left the body twisted over its feet
    assert steps >= 1 and len(settle) > steps * 10
    # at rest in the stand pose: both feet down, the joints at the stand pose's (the bridge's
    # rest pose: the feet in the stand stance under the hips) and the body no longer twisted
    assert st.planted.all()
    q = settle[-1][op3.n_root :]
    assert np.abs(q - op3.x_stand[op3.n_root :]).max() < 0.2
    assert np.abs(_hip_yaws(op3, settle[-1])).max() < 0.12
    # the last frames hold still (the joints slower than SettleConfig.rest_speed, 0.3 rad/s)
    assert np.abs(np.diff(np.stack(settle[-15:]), axis=0)[:, op3.n_root :]).max() <= 0.3 / FPS + 1e-12


def test_every_settle_frame_is_inside_the_joint_range_and_speed_limits(op3, turned):
    st, X, settle, _ = turned
    xs = np.concatenate([X[-1:], np.stack(settle)])
    assert np.all(xs >= op3.x_lower - 1e-9) and np.all(xs <= op3.x_upper + 1e-9)
    vmax = np.concatenate([op3.root_velocity_limits, op3.velocity_limits]) / FPS
    assert np.all(np.abs(np.diff(xs, axis=0)) <= vmax + 1e-9)


def _hip_heading(rb, x) -> float:
    """Where the robot's hips face (rad about the vertical) in configuration x."""
    kp = np.array(rb.f_keypoints(x)).T
    across = kp[rb.keypoint_names.index("left_hip"), 0:2] - kp[rb.keypoint_names.index("right_hip"), 0:2]
    return float(np.arctan2(-across[0], across[1]))


def test_the_settle_starts_from_where_the_robot_is_not_from_its_last_targets(op3):
    """The person's body snaps round 1.5 rad in the last three frames, faster than the robot may
    turn: the stream ends with the robot's body 1.1 rad short of its targets. The settle starts
    from the robot's own pose, so its stand pose faces where the robot faces; started from the
    last targets (as before) it turned the robot 1.1 rad further round over its planted feet
    (the demo's generated partner ended mid-lunge 0.1 m and 76 deg from its targets, and the
    settle swung the robot's body round at the servos' speed limit)."""
    T = 40
    turn = np.zeros(T)
    turn[-3:] = (0.5, 1.0, 1.5)
    pos = np.repeat(REST_POSE[None], T, axis=0)
    root = pos[:, :1, 0:2].copy()
    rel = pos[:, :, 0:2] - root
    c, s = np.cos(turn)[:, None], np.sin(turn)[:, None]
    pos[:, :, 0] = root[:, :, 0] + c * rel[:, :, 0] - s * rel[:, :, 1]
    pos[:, :, 1] = root[:, :, 1] + s * rel[:, :, 0] + c * rel[:, :, 1]
    st = StreamingRetargeter(op3, FPS, StreamingConfig(balance=True))
    tg = make_targets(op3, Motion(pos, FPS, name="snap"))
    X = [st.step(tg.keypoints[t], tg.contacts[t]) for t in range(T)]
    assert abs(_hip_heading(op3, X[-1]) - 1.5) > 0.8  # the robot could not follow the snap
    settle = list(st.settle())
    assert abs(_hip_heading(op3, settle[-1]) - _hip_heading(op3, X[-1])) < 0.15


def _stop_ramp(rb, last: np.ndarray) -> np.ndarray:
    """The bridge's stop ramp (ros_free_bridge.control.safety.min_jerk to the rest pose, the
    stand pose, over 1 s), then 1 s held: (60, nx) after ``last`` (nx,)."""
    from ros_free_bridge.control.safety import min_jerk

    rest = rb.x_stand[rb.n_root :]
    xs = np.repeat(last[None], 60, axis=0)
    xs[:30, rb.n_root :] = min_jerk(last[rb.n_root :], rest, 1.0, 1.0 / FPS)
    xs[30:, rb.n_root :] = rest
    return xs


def _physics(rb, xs, stabilizer: bool = True):
    from retarget.robot import robot_ref
    from sim.check import CheckConfig, check_trajectory

    traj = trajectory_from_x(rb, np.asarray(xs), FPS, {"mode": "streaming"})
    return check_trajectory(traj, CheckConfig(mode="free", stabilizer=stabilizer), robot=robot_ref("op3"))


@pytest.mark.slow
def test_the_stop_ramp_after_the_settle_keeps_op3_standing_in_physics(op3, turned):
    """The stop ramp played after the settle frames: the free-standing robot stays up
    throughout, and the ramp has little left to do."""
    _, X, settle, _ = turned
    assert np.abs(settle[-1][op3.n_root :] - op3.x_stand[op3.n_root :]).max() < 0.2
    result = _physics(op3, np.concatenate([X, np.stack(settle), _stop_ramp(op3, settle[-1])]))
    assert result.passed, (result.reason, result.first_failure_time)


@pytest.mark.slow
def test_the_real_partner_falls_in_the_bare_stop_ramp_and_stands_after_the_settle(op3, cmu_pair_paths):
    """CMU 19_01 streamed ends with the hips turned -0.22 / 0.40 rad over the feet: the stop ramp
    straight from there unwinds them on planted feet and the servos alone let the robot fall (at
    3.99 s; the stabilizer catches it since it stopped rolling the ankles on two feet, at 16 deg of
    tilt); stepping back to its stance first, it stands with the servos alone and stabilized."""
    from dualflow.motion.io import load_pair, put_on_ground

    motion = put_on_ground(load_pair(*cmu_pair_paths, fps=FPS)).reactor
    st = StreamingRetargeter(op3, FPS, StreamingConfig(balance=True))
    tg = make_targets(op3, motion)
    X = np.stack([st.step(tg.keypoints[t], tg.contacts[t]) for t in range(motion.n_frames)])
    bare = _physics(op3, np.concatenate([X, _stop_ramp(op3, X[-1])]), stabilizer=False)
    assert not bare.passed and bare.reason == "fall" and bare.first_failure_time > motion.n_frames / FPS
    frames = st.settle()
    settle = list(frames)
    assert frames.steps >= 1
    settled = np.concatenate([X, np.stack(settle), _stop_ramp(op3, settle[-1])])
    for stabilizer in (False, True):
        result = _physics(op3, settled, stabilizer)
        assert result.passed, (stabilizer, result.reason, result.first_failure_time)


def test_no_settle_without_balance_or_before_the_first_frame(op3):
    st = StreamingRetargeter(op3, FPS, StreamingConfig(balance=True))
    assert list(st.settle()) == []  # nothing streamed yet
    plain = StreamingRetargeter(op3, FPS, StreamingConfig(balance=False))
    tg = make_targets(op3, turning_leader(0.5, -0.9))
    plain.step(tg.keypoints[0], tg.contacts[0])
    assert list(plain.settle()) == []  # no planner, no steps: the stop ramp alone
