"""Rotation utilities, forward kinematics and the inverse-kinematics step."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from dualflow.errors import DualFlowError
from dualflow.motion import REST_POSE, bone_lengths, joint_index
from dualflow.motion.kinematics import (
    LEAF_JOINTS,
    fit_offsets,
    forward_kinematics,
    global_rotations,
    inverse_kinematics,
    rest_offsets,
    root_orientation,
    scaled_offsets,
)
from dualflow.motion.rotations import (
    align_vector_sets,
    axis_angle_matrix,
    euler_to_matrix,
    is_rotation_matrix,
    matrix_to_6d,
    matrix_to_quat_wxyz,
    matrix_to_rotvec,
    quat_wxyz_to_matrix,
    rotvec_to_matrix,
    sixd_to_matrix,
    swing_rotation,
)


def random_rotations(n: int, seed: int) -> np.ndarray:
    return Rotation.random(n, random_state=seed).as_matrix()


# -- rotations ----------------------------------------------------------------
def test_6d_is_first_two_columns():
    Rz90 = axis_angle_matrix([0, 0, 1], np.pi / 2)  # x -> y, y -> -x
    np.testing.assert_allclose(matrix_to_6d(Rz90), [0, 1, 0, -1, 0, 0], atol=1e-12)


def test_6d_round_trip_batched():
    R = random_rotations(60, 0).reshape(3, 20, 3, 3)
    d6 = matrix_to_6d(R)
    assert d6.shape == (3, 20, 6)
    np.testing.assert_allclose(sixd_to_matrix(d6), R, atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(arrays(np.float64, (6,), elements=st.floats(-10, 10)))
def test_gram_schmidt_gives_a_rotation_keeping_the_first_column_direction(d6):
    a1, a2 = d6[:3], d6[3:]
    n1 = np.linalg.norm(a1)
    n2 = np.linalg.norm(a2)
    assume(n1 > 1e-3 and n2 > 1e-3 and np.linalg.norm(np.cross(a1, a2)) > 1e-3 * n1 * n2)
    R = sixd_to_matrix(d6)
    assert is_rotation_matrix(R, atol=1e-9)
    np.testing.assert_allclose(R[:, 0], a1 / n1, atol=1e-9)
    # the second column lies in the plane of a1 and a2, on a2's side
    normal = np.cross(a1, a2) / np.linalg.norm(np.cross(a1, a2))
    assert abs(np.dot(normal, R[:, 1])) < 1e-9
    assert np.dot(R[:, 1], a2) > 0


def test_6d_degenerate_raises_naming_the_field():
    with pytest.raises(DualFlowError, match="rotation 6D"):
        sixd_to_matrix(np.array([[1, 0, 0, 1, 0, 0], [1, 0, 0, 0, 1, 0]], dtype=float))
    with pytest.raises(DualFlowError, match="rotation 6D"):
        sixd_to_matrix(np.zeros((4, 5)))


def test_quaternion_is_wxyz_and_round_trips():
    Rz90 = axis_angle_matrix([0, 0, 1], np.pi / 2)
    np.testing.assert_allclose(matrix_to_quat_wxyz(Rz90), [np.sqrt(0.5), 0, 0, np.sqrt(0.5)], atol=1e-12)
    np.testing.assert_allclose(quat_wxyz_to_matrix([1.0, 0, 0, 0]), np.eye(3), atol=1e-15)
    R = random_rotations(12, 1).reshape(4, 3, 3, 3)
    q = matrix_to_quat_wxyz(R)
    assert q.shape == (4, 3, 4) and (q[..., 0] >= 0).all()
    np.testing.assert_allclose(quat_wxyz_to_matrix(q), R, atol=1e-12)
    np.testing.assert_allclose(rotvec_to_matrix(matrix_to_rotvec(R)), R, atol=1e-12)


def test_intrinsic_euler_order():
    # intrinsic ZX: first about Z by 90 deg, then about the new X (= old Y) by 90 deg
    R = euler_to_matrix([np.pi / 2, np.pi / 2, 0.0], "ZXY")
    np.testing.assert_allclose(R @ [0, 0, 1], [1, 0, 0], atol=1e-12)


def test_swing_maps_direction_without_twist():
    rng = np.random.default_rng(2)
    a, b = rng.normal(size=(50, 3)), rng.normal(size=(50, 3))
    R = swing_rotation(a, b)
    ua = a / np.linalg.norm(a, axis=-1, keepdims=True)
    ub = b / np.linalg.norm(b, axis=-1, keepdims=True)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", R, ua), ub, atol=1e-12)
    # no twist: the axis a x b is left unchanged
    axis = np.cross(ua, ub)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", R, axis), axis, atol=1e-12)
    # opposite directions: a half turn about an axis perpendicular to a
    Rop = swing_rotation([0.0, 0, 1], [0.0, 0, -2])
    np.testing.assert_allclose(Rop @ [0, 0, 1], [0, 0, -1], atol=1e-12)
    assert is_rotation_matrix(Rop)
    np.testing.assert_allclose(swing_rotation([1.0, 0, 0], [3.0, 0, 0]), np.eye(3), atol=1e-15)


@pytest.mark.parametrize("gap", [0.5, 2e-3, 9e-4, 1e-7, 1e-13])
def test_swing_matches_the_axis_angle_rotation_up_to_opposite_directions(gap):
    """1 + a.b = gap: the outer-product form on one side of its 1e-3 switch, the angle form on
    the other; both must be the rotation by angle(a, b) about a x b to full precision."""
    rng = np.random.default_rng(5)
    a = rng.normal(size=(20, 3))
    a /= np.linalg.norm(a, axis=-1, keepdims=True)
    perp = np.cross(a, rng.normal(size=(20, 3)))
    perp /= np.linalg.norm(perp, axis=-1, keepdims=True)
    angle = np.arccos(gap - 1.0)  # cos(angle) = gap - 1
    b = np.cos(angle) * a + np.sin(angle) * perp
    expected = Rotation.from_rotvec(np.cross(a, b) / np.sin(angle) * angle).as_matrix()
    R = swing_rotation(a, 2.5 * b)
    np.testing.assert_allclose(R, expected, atol=1e-12)
    assert is_rotation_matrix(R, atol=1e-12).all()


def test_ik_gives_a_zero_length_bone_the_identity():
    pos = REST_POSE[None].copy()
    elbow, wrist = joint_index("left_elbow"), joint_index("left_wrist")
    pos[0, wrist] = pos[0, elbow]  # the forearm has no direction
    _, rots = inverse_kinematics(pos)
    assert np.isfinite(rots).all()
    np.testing.assert_allclose(rots[0, elbow], np.eye(3), atol=1e-15)


def test_align_vector_sets_recovers_a_rotation():
    R = random_rotations(8, 3)
    src = np.random.default_rng(3).normal(size=(8, 3, 3))
    dst = np.einsum("nij,nkj->nki", R, src)
    np.testing.assert_allclose(align_vector_sets(src, dst), R, atol=1e-10)
    with pytest.raises(DualFlowError, match="same number of vectors"):
        align_vector_sets(np.zeros((3, 3)), np.zeros((2, 3)))


# -- forward kinematics ---------------------------------------------------------
def identity_rots(T: int) -> np.ndarray:
    return np.broadcast_to(np.eye(3), (T, 22, 3, 3)).copy()


def test_fk_identity_is_rest_pose():
    pos = forward_kinematics(np.tile(REST_POSE[0], (3, 1)), identity_rots(3))
    assert pos.shape == (3, 22, 3)
    np.testing.assert_allclose(pos, np.broadcast_to(REST_POSE, (3, 22, 3)), atol=1e-12)


def test_fk_root_yaw_turns_the_whole_body():
    rots = identity_rots(1)
    rots[0, 0] = axis_angle_matrix([0, 0, 1], np.pi / 2)  # face +Y instead of +X
    pos = forward_kinematics(REST_POSE[None, 0], rots)[0]
    toe = pos[joint_index("left_foot")] - pos[0]
    assert toe[1] > 0.1  # toes now point to +Y
    # the left hip, on +Y in the rest pose, is now on -X
    assert pos[joint_index("left_hip"), 0] < -0.05


def test_fk_knee_flexion_moves_only_the_shank_and_foot_backwards():
    knee, ankle = joint_index("left_knee"), joint_index("left_ankle")
    rots = identity_rots(1)
    rots[0, knee] = axis_angle_matrix([0, 1, 0], np.pi / 2)  # +90 deg about the left-right axis
    pos = forward_kinematics(REST_POSE[None, 0], rots)[0]
    moved = np.abs(pos - REST_POSE).max(axis=-1) > 1e-9
    assert set(np.flatnonzero(moved)) == {ankle, joint_index("left_foot")}
    shin = pos[ankle] - pos[knee]
    assert shin[0] < -0.35 and abs(shin[2]) < 0.05  # shank horizontal, pointing backwards


def test_fk_preserves_bone_lengths_and_accepts_per_frame_offsets():
    T = 16
    rots = random_rotations(T * 22, 4).reshape(T, 22, 3, 3)
    root = np.random.default_rng(4).normal(size=(T, 3))
    pos = forward_kinematics(root, rots)
    np.testing.assert_allclose(bone_lengths(pos), np.broadcast_to(bone_lengths(REST_POSE), (T, 21)), atol=1e-12)
    np.testing.assert_allclose(pos[:, 0], root)
    lengths = np.linspace(0.5, 1.5, T)[:, None] * bone_lengths(REST_POSE)
    pos2 = forward_kinematics(root, rots, scaled_offsets(lengths))
    np.testing.assert_allclose(bone_lengths(pos2), lengths, atol=1e-12)


def test_fk_bad_shapes_name_the_field():
    with pytest.raises(DualFlowError, match="root_pos"):
        forward_kinematics(np.zeros((4, 2)), identity_rots(4))
    with pytest.raises(DualFlowError, match="local_rot"):
        forward_kinematics(np.zeros((4, 3)), identity_rots(3))
    with pytest.raises(DualFlowError, match="offsets"):
        forward_kinematics(np.zeros((4, 3)), identity_rots(4), np.zeros((21, 3)))
    with pytest.raises(DualFlowError, match="positions"):
        inverse_kinematics(np.zeros((4, 21, 3)))


def test_global_rotations_compose_down_the_chain():
    rots = random_rotations(22, 5).reshape(1, 22, 3, 3)
    G = global_rotations(rots)
    wrist, elbow, shoulder = joint_index("left_wrist"), joint_index("left_elbow"), joint_index("left_shoulder")
    np.testing.assert_allclose(G[0, wrist], G[0, shoulder] @ rots[0, elbow] @ rots[0, wrist], atol=1e-12)


# -- inverse kinematics -----------------------------------------------------------
def test_ik_of_rest_pose_is_identity():
    root, rots = inverse_kinematics(REST_POSE[None] + [1.0, 2.0, 0.0])
    np.testing.assert_allclose(root, [REST_POSE[0] + [1.0, 2.0, 0.0]])
    np.testing.assert_allclose(rots, identity_rots(1), atol=1e-12)


def test_ik_then_fk_reproduces_positions_of_rest_proportioned_poses():
    T = 40
    rots = random_rotations(T * 22, 6).reshape(T, 22, 3, 3)
    root = np.random.default_rng(6).normal(size=(T, 3))
    pos = forward_kinematics(root, rots)
    root_ik, rots_ik = inverse_kinematics(pos)
    assert is_rotation_matrix(rots_ik, atol=1e-9).all()
    np.testing.assert_allclose(rots_ik[:, list(LEAF_JOINTS)], identity_rots(T)[:, list(LEAF_JOINTS)], atol=1e-12)
    np.testing.assert_allclose(forward_kinematics(root_ik, rots_ik), pos, atol=1e-9)
    # multi-child joints recover the full rotation (twist included)
    np.testing.assert_allclose(rots_ik[:, 0], rots[:, 0], atol=1e-9)


def test_ik_single_child_joint_is_swing_only():
    elbow = joint_index("left_elbow")
    rots = identity_rots(1)
    twist = axis_angle_matrix([0, 1, 0], 0.7)  # about the forearm's own rest axis (+Y)
    rots[0, elbow] = twist
    pos = forward_kinematics(REST_POSE[None, 0], rots)
    _, rots_ik = inverse_kinematics(pos)
    np.testing.assert_allclose(rots_ik[0, elbow], np.eye(3), atol=1e-12)  # twist is not observable


def test_ik_fk_with_measured_lengths_on_other_proportions():
    """Different proportions (scaled bones): FK with the measured lengths stays exact."""
    T = 10
    rots = random_rotations(T * 22, 7).reshape(T, 22, 3, 3)
    lengths = bone_lengths(REST_POSE) * np.random.default_rng(7).uniform(0.8, 1.2, size=21)
    pos = forward_kinematics(np.zeros((T, 3)), rots, scaled_offsets(lengths))
    root, rots_ik = inverse_kinematics(pos)
    np.testing.assert_allclose(forward_kinematics(root, rots_ik, scaled_offsets(bone_lengths(pos))), pos, atol=1e-9)
    assert rest_offsets().shape == (22, 3)


def test_fit_offsets_recovers_a_rigid_skeleton_of_another_shape():
    T = 12
    rots = random_rotations(T * 22, 8).reshape(T, 22, 3, 3)
    off = rest_offsets() + np.random.default_rng(8).normal(0.0, 0.02, size=(22, 3))
    off[0] = 0.0
    pos = forward_kinematics(np.zeros((T, 3)), rots, off)
    root, rots_ik = inverse_kinematics(pos)
    fitted = fit_offsets(pos, rots_ik)
    np.testing.assert_allclose(forward_kinematics(root, rots_ik, fitted), pos, atol=1e-9)
    # with the rest pose's own offsets the perturbed pelvis/chest shape is not reproduced
    assert np.abs(forward_kinematics(root, rots_ik, scaled_offsets(bone_lengths(pos[0]))) - pos).max() > 1e-3
    np.testing.assert_allclose(root_orientation(pos), rots_ik[:, 0], atol=1e-12)
