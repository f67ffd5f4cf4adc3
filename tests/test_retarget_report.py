"""The retarget report's figures on hand-made trajectories (no solver): jerk ratio edge cases."""

import json

import numpy as np
from retarget_toy import toy_robot

from dualflow.motion import REST_POSE, Motion
from retarget.report import evaluate, jerk_ratio
from retarget.streaming import trajectory_from_x
from retarget.targets import make_targets


def _standing(rb, T=12):
    return trajectory_from_x(rb, np.tile(rb.x_stand, (T, 1)), 30.0, {"mode": "test"})


def test_jerk_ratio_of_a_motionless_source_is_undefined_not_nan(tmp_path):
    rb = toy_robot()
    still = Motion(np.repeat(REST_POSE[None], 12, axis=0), fps=30.0, name="still")
    rep = evaluate(rb, _standing(rb), make_targets(rb, still))
    assert rep.jerk_source == 0.0 and rep.jerk_robot == 0.0
    assert rep.jerk_ratio is None
    assert rep.to_dict()["jerk_ratio"] is None
    assert "ratio n/a" in rep.to_markdown() and "nan" not in rep.to_markdown().lower()
    paths = rep.save(tmp_path, "still")
    text = paths["json"].read_text()
    data = json.loads(text, parse_constant=lambda c: (_ for _ in ()).throw(ValueError(c)))  # no NaN/Infinity
    assert data["jerk_ratio"] is None


def test_jerk_ratio_of_a_moving_source_is_robot_over_source():
    rb = toy_robot()
    t = np.arange(12) / 30.0
    pos = np.repeat(REST_POSE[None], 12, axis=0).copy()
    pos[:, 20:, 2] += 0.2 * np.sin(2 * np.pi * 1.5 * t)[:, None] ** 3  # wrists move with non-zero jerk
    rep = evaluate(rb, _standing(rb), make_targets(rb, Motion(pos, fps=30.0, name="wave")))
    assert rep.jerk_source > 0 and rep.jerk_robot == 0.0
    assert rep.jerk_ratio == 0.0
    assert "ratio 0.00" in rep.to_markdown()
    assert jerk_ratio(3.0, 2.0) == 1.5 and jerk_ratio(1.0, 0.0) is None


def test_first_failure_is_the_earliest_failing_frame_and_none_when_passing():
    rb = toy_robot()
    still = Motion(np.repeat(REST_POSE[None], 12, axis=0), fps=30.0, name="still")
    targets = make_targets(rb, still)
    assert evaluate(rb, _standing(rb), targets).first_failure_s is None
    X = np.tile(rb.x_stand, (12, 1))
    j = rb.n_root  # the first joint: beyond its upper limit from frame 7 on, which is also a speed jump
    X[7:, j] = rb.x_upper[j] + 0.05
    rep = evaluate(rb, trajectory_from_x(rb, X, 30.0, {"mode": "test"}), targets)
    assert not rep.passed and rep.limit_violations == 5
    assert rep.first_failure_s == round(7 / 30.0, 3)
    assert "first failure at 0.233 s" in rep.to_markdown()


def test_error_where_the_robot_follows_leaves_out_the_reported_changes():
    """A person who raises the wrists in frames 6-11 only, a robot that stands: the whole-clip
    error includes the raised wrists; with frames 6-11 reported as a change, the error where the
    robot follows the person is that of the still frames alone."""
    rb = toy_robot()
    pos = np.repeat(REST_POSE[None], 12, axis=0).copy()
    pos[6:, 20:, 2] += 0.3
    targets = make_targets(rb, Motion(pos, fps=30.0, name="raise"))
    plain = evaluate(rb, _standing(rb), targets)
    kp = rb.evaluate(np.tile(rb.x_stand, (12, 1)))["keypoints"]
    still_mm = 1000 * np.linalg.norm(kp[:6] - targets.keypoints[:6], axis=-1).mean()
    change = {"start_s": 6 / 30.0, "end_s": 12 / 30.0, "what": "test", "why": "hand-made"}
    traj = trajectory_from_x(rb, np.tile(rb.x_stand, (12, 1)), 30.0, {"mode": "test", "changes": [change]})
    rep = evaluate(rb, traj, targets)
    assert plain.keypoint_error_followed_mm == plain.keypoint_error_mean_mm  # no change: the same frames
    assert rep.keypoint_error_followed_mm < rep.keypoint_error_mean_mm
    assert abs(rep.keypoint_error_followed_mm - still_mm) < 1e-6
    assert rep.changes[0]["keypoint_error_mm"] > rep.keypoint_error_mean_mm
    assert "where it follows the person" in rep.to_markdown()
