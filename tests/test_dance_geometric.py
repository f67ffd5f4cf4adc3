"""DD100's FID_g: boolean geometric (relational) pose features and their known properties —
ground truth against itself gives FID_g ≈ 0, the features do not depend on the world frame or
body size, named relations fire on poses built to show them, and static followers are far."""

from __future__ import annotations

import numpy as np
import pytest

from dualflow.errors import DualFlowError
from dualflow.evaluation.dance import GEOMETRIC_FEATURES, dd100_metrics, geometric_feature
from dualflow.motion.skeleton import REST_POSE
from dualflow.synthetic import make_duet

RULES = ["mirror", "follow", "orbit", "hand_hold"]


def pairs(n: int = 8, seconds: float = 2.0, offset: int = 0):
    duets = [make_duet(RULES[i % 4], seconds=seconds, seed=offset + i) for i in range(n)]
    return [(d.actor.positions, d.reactor.positions) for d in duets]


def named(f: np.ndarray) -> dict[str, float]:
    return dict(zip(GEOMETRIC_FEATURES, f))


def test_ground_truth_against_itself_is_zero_and_static_followers_are_far():
    gt = pairs(16)
    m = dd100_metrics(gt, gt)
    assert abs(m["fid_g"]) < 1e-6 and m["div_g"] > 0
    still = [(ld, np.repeat(f[:1], len(f), axis=0)) for ld, f in gt]
    assert dd100_metrics(still, gt)["fid_g"] > 10.0
    # other clips of the same rules are much nearer than static followers
    assert dd100_metrics(pairs(16, offset=100), gt)["fid_g"] < 0.5 * dd100_metrics(still, gt)["fid_g"]


def test_invariant_to_world_frame_and_body_size():
    p = make_duet("orbit", seconds=2.0, seed=3).reactor.positions
    a = np.radians(70.0)
    rot = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    yup = np.array([[0, 1, 0], [0, 0, 1], [1, 0, 0]])  # Z-up -> Y-up, a proper rotation
    moved = 1.3 * (p @ rot.T @ yup.T) + np.array([2.0, -1.0, 0.5])
    np.testing.assert_allclose(geometric_feature(moved), geometric_feature(p), atol=1e-12)


def test_named_relations_on_built_poses():
    rest = np.asarray(REST_POSE, dtype=np.float64)
    t_pose = named(geometric_feature(np.repeat(rest[None], 10, axis=0)))
    assert t_pose["l_wrist_out_sideways"] == t_pose["r_wrist_out_sideways"] == 1.0
    assert t_pose["hands_apart"] == 1.0 and t_pose["l_arm_stretched"] == 1.0
    assert t_pose["l_wrist_above_neck"] == 0.0 and t_pose["l_knee_bent"] == 0.0
    assert all(t_pose[k] == 0.0 for k in GEOMETRIC_FEATURES if k.endswith(("_fast", "turning")))
    # right arm straight up, above the head: only the right side says so
    up = rest.copy()
    up[19] = up[17] + [0, 0, 0.26]
    up[21] = up[17] + [0, 0, 0.51]
    f = named(geometric_feature(np.repeat(up[None], 10, axis=0)))
    assert f["r_wrist_above_neck"] == 1.0 and f["l_wrist_above_neck"] == 0.0 and f["r_wrist_out_sideways"] == 0.0
    # walking forward at 1 m/s: the pelvis is fast, the person is not turning
    walk = np.repeat(rest[None], 30, axis=0) + np.arange(30)[:, None, None] / 30.0 * np.array([1.0, 0, 0])
    w = named(geometric_feature(walk))
    assert w["pelvis_fast"] == 1.0 and w["turning"] == 0.0
    # the left knee bent 90 degrees, the foot back: left knee bent, right not
    bent = rest.copy()
    bent[7] = bent[4] + [-0.4, 0, 0]
    b = named(geometric_feature(np.repeat(bent[None], 10, axis=0)))
    assert b["l_knee_bent"] == 1.0 and b["r_knee_bent"] == 0.0


def test_rejects_bad_shapes():
    with pytest.raises(DualFlowError, match="geometric feature"):
        geometric_feature(np.zeros((2, 22, 3)))
