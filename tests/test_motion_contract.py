"""The human-motion contract: skeleton tables and the Motion / TwoPersonMotion containers."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dualflow.motion import (
    FACE_JOINTS,
    FOOT_JOINTS,
    JOINT_NAMES,
    KINEMATIC_CHAINS,
    MIRROR_INDEX,
    PARENTS,
    REST_POSE,
    DualFlowError,
    Motion,
    TwoPersonMotion,
    bone_lengths,
    joint_index,
)


def test_skeleton_tables_are_consistent():
    assert len(JOINT_NAMES) == len(PARENTS) == 22
    assert all(PARENTS[j] < j for j in range(1, 22)) and PARENTS[0] == -1
    # every chain walks parent -> child
    for chain in KINEMATIC_CHAINS:
        for parent, child in zip(chain[:-1], chain[1:]):
            assert PARENTS[child] == parent
    # mirror is an involution pairing left_* with right_*
    for j, m in enumerate(MIRROR_INDEX):
        assert MIRROR_INDEX[m] == j
        assert JOINT_NAMES[m] == JOINT_NAMES[j].replace("left", "#").replace("right", "left").replace("#", "right")
    assert [JOINT_NAMES[j] for j in FOOT_JOINTS] == ["left_ankle", "left_foot", "right_ankle", "right_foot"]
    assert [JOINT_NAMES[j] for j in FACE_JOINTS] == ["right_hip", "left_hip", "right_shoulder", "left_shoulder"]


def test_rest_pose_is_a_standing_adult_facing_plus_x():
    height = REST_POSE[:, 2].max() - REST_POSE[:, 2].min()
    assert 1.45 < height < 1.75  # head joint sits below the top of the skull
    assert REST_POSE[:, 2].min() >= 0.0
    for left, right in [(1, 2), (16, 17), (20, 21)]:
        assert REST_POSE[left, 1] > 0 > REST_POSE[right, 1]
    assert REST_POSE[joint_index("left_foot"), 0] > REST_POSE[joint_index("left_ankle"), 0]  # toes forward (+X)
    # symmetric bone lengths
    bones = bone_lengths(REST_POSE)
    for left, right in [(4, 5), (7, 8), (18, 19), (20, 21)]:
        assert bones[left - 1] == pytest.approx(bones[right - 1])
    assert 0.35 < bones[joint_index("left_knee") - 1] < 0.45  # thigh


def test_joint_index_unknown_name_names_the_valid_ones():
    with pytest.raises(DualFlowError, match="left_wrist"):
        joint_index("left_hand")


def _walk(n=40, fps=30.0):
    t = np.arange(n) / fps
    pos = np.repeat(REST_POSE[None], n, axis=0).copy()
    pos[:, :, 0] += 1.2 * t[:, None]  # walking forward at 1.2 m/s
    return Motion(pos, fps=fps, name="walk")


@pytest.mark.parametrize(
    "positions, fps, match",
    [
        (np.zeros((0, 22, 3)), 30, "zero frames"),
        (np.zeros((5, 21, 3)), 30, r"\(T, 22, 3\)"),
        (np.zeros((5, 22, 3)), 0, "fps must be > 0"),
        (np.zeros((5, 22, 3)), float("nan"), "fps must be > 0"),
    ],
)
def test_motion_validation(positions, fps, match):
    with pytest.raises(DualFlowError, match=match):
        Motion(positions, fps=fps)


def test_motion_rejects_nan_and_names_the_frame():
    pos = np.zeros((5, 22, 3))
    pos[3, 7, 2] = np.nan
    with pytest.raises(DualFlowError, match="frame 3, joint 7"):
        Motion(pos, name="clip.npz")


def test_contacts_shape_is_checked():
    with pytest.raises(DualFlowError, match="contacts"):
        Motion(np.zeros((5, 22, 3)), contacts=np.zeros((5, 2), bool))


@settings(max_examples=30, deadline=None)
@given(src=st.sampled_from([24.0, 30.0, 60.0, 120.0]), dst=st.sampled_from([20.0, 30.0, 50.0, 100.0]))
def test_resample_preserves_linear_motion_and_duration(src, dst):
    m = _walk(n=int(src) + 1, fps=src)  # exactly one second
    r = m.resample(dst)
    assert r.fps == dst
    assert r.duration == pytest.approx(1.0, abs=1.0 / dst)
    # a constant-velocity motion is reproduced exactly by linear interpolation
    expected = REST_POSE[None, :, 0] + 1.2 * r.times[:, None]
    np.testing.assert_allclose(r.positions[:, :, 0], expected, atol=1e-9)


def test_two_person_checks_fps_and_length():
    a = _walk(30)
    with pytest.raises(DualFlowError, match="fps"):
        TwoPersonMotion(a, _walk(30, fps=60))
    with pytest.raises(DualFlowError, match="frames"):
        TwoPersonMotion(a, _walk(20))
    pair = TwoPersonMotion.from_pair(a, _walk(61, fps=60))
    assert pair.n_frames == 30 and pair.reactor.fps == 30
