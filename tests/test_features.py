"""The InterGen 262-d feature: round trips, canonicalisation, contacts, rotations, pairs."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dualflow.errors import DualFlowError
from dualflow.motion import FACE_JOINTS, FOOT_JOINTS, REST_POSE, Motion, TwoPersonMotion, joint_index
from dualflow.motion.features import (
    CONTACT_HEIGHTS,
    FEATURE_DIM,
    FEATURE_SLICES,
    REST_POSE_YUP,
    CanonicalFrame,
    canonical_frame,
    decode_pair,
    decode_person,
    encode_pair,
    encode_person,
    foot_contacts,
    yup_to_zup,
    zup_to_yup,
)
from dualflow.motion.kinematics import LEAF_JOINTS, forward_kinematics, rest_offsets
from dualflow.motion.rotations import axis_angle_matrix, matrix_to_6d, rotvec_to_matrix

MULTI_CHILD_BONES = [1, 2, 3, 12, 13, 14]  # children of pelvis and spine3


def make_motion(
    seed: int, T: int = 30, yaw: float = 0.0, start=(0.0, 0.0), shape_noise: float = 0.0, fps: float = 30.0
) -> Motion:
    """A smooth FK-generated motion: swaying joints, a walking root, turning by ``yaw``.

    shape_noise (m) perturbs the pelvis and chest bones so the skeleton's shape
    differs from REST_POSE (a rigid skeleton of other proportions)."""
    rng = np.random.default_rng(seed)
    t = np.arange(T) / fps
    phase = rng.uniform(0, 2 * np.pi, size=(1, 22, 3))
    amp = rng.uniform(0.05, 0.5, size=(1, 22, 3))
    rots = rotvec_to_matrix(amp * np.sin(2 * np.pi * 0.9 * t[:, None, None] + phase))
    rots[:, 0] = axis_angle_matrix([0, 0, 1], yaw + 0.4 * t) @ rots[:, 0]
    root = np.stack([start[0] + 0.6 * t, start[1] + 0.1 * t, 0.95 + 0.03 * np.sin(5 * t)], axis=-1)
    off = rest_offsets().copy()
    off[MULTI_CHILD_BONES] += rng.normal(0.0, shape_noise, size=(len(MULTI_CHILD_BONES), 3))
    pos = forward_kinematics(root, rots, off)
    pos[..., 2] -= pos[..., 2].min() - rng.uniform(-0.5, 0.5)  # floor somewhere, not necessarily 0
    return Motion(pos, fps=fps, name=f"synthetic{seed}")


def make_pair(seed: int, T: int = 30) -> TwoPersonMotion:
    a = make_motion(seed, T, yaw=0.3 * seed, start=(1.0, -2.0))
    b = make_motion(seed + 100, T, yaw=0.3 * seed + 2.5, start=(2.2, -1.1), shape_noise=0.01)
    return TwoPersonMotion(a, b, "test pair")


def rows_to_positions(feats: np.ndarray) -> np.ndarray:
    return feats[..., FEATURE_SLICES["positions"]].reshape(feats.shape[:-1] + (22, 3)).astype(np.float64)


# -- layout and frame conventions ---------------------------------------------------
def test_slices_tile_the_262_columns():
    cols = np.concatenate([np.arange(FEATURE_DIM)[s] for s in FEATURE_SLICES.values()])
    np.testing.assert_array_equal(cols, np.arange(FEATURE_DIM))
    assert [s.stop - s.start for s in FEATURE_SLICES.values()] == [66, 66, 126, 4]


def test_axis_conversion_is_a_proper_rotation_and_inverts():
    M = zup_to_yup(np.eye(3))  # rows: images of x, y, z
    assert np.isclose(np.linalg.det(M), 1.0)
    x = np.random.default_rng(0).normal(size=(5, 4, 3))
    np.testing.assert_array_equal(yup_to_zup(zup_to_yup(x)), x)
    # Y-up rest pose: up is +Y, the left side is +X
    assert REST_POSE_YUP[joint_index("head"), 1] > 1.5
    assert REST_POSE_YUP[joint_index("left_hip"), 0] > 0 > REST_POSE_YUP[joint_index("right_hip"), 0]


def test_encode_shape_dtype_and_frame_count():
    m = make_motion(1, T=25)
    f = encode_person(m)
    assert f.shape == (24, FEATURE_DIM) and f.dtype == np.float32
    # velocity row t is p[t+1] - p[t] (metres per frame)
    vel = f[:, FEATURE_SLICES["velocities"]].reshape(24, 22, 3)
    np.testing.assert_allclose(vel[:-1], rows_to_positions(f[1:]) - rows_to_positions(f[:-1]), atol=1e-6)


# -- round trip -----------------------------------------------------------------------
@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    yaw=st.floats(-np.pi, np.pi),
    x=st.floats(-50, 50),
    y=st.floats(-50, 50),
    shape_noise=st.sampled_from([0.0, 0.01, 0.03]),
)
def test_round_trip_within_1mm_in_the_original_world(seed, yaw, x, y, shape_noise):
    m = make_motion(seed, T=20, yaw=yaw, start=(x, y), shape_noise=shape_noise)
    frame = canonical_frame(m)
    f = encode_person(m, frame)
    back = decode_person(f, m.fps, frame, append_last_frame=True)
    assert back.n_frames == m.n_frames and back.fps == m.fps
    assert np.abs(back.positions - m.positions).max() < 1e-3
    # one frame per row without append_last_frame
    np.testing.assert_allclose(decode_person(f, m.fps, frame).positions, m.positions[:-1], atol=1e-3)


def test_pair_round_trip_to_the_original_world():
    pair = make_pair(3)
    feats, frame = encode_pair(pair)
    assert feats.shape == (29, 2, FEATURE_DIM) and feats.dtype == np.float32
    back = decode_pair(feats, pair.fps, frame, append_last_frame=True, text=pair.text)
    assert np.abs(back.actor.positions - pair.actor.positions).max() < 1e-3
    assert np.abs(back.reactor.positions - pair.reactor.positions).max() < 1e-3
    assert back.text == "test pair"
    # the frame survives a JSON-style round trip
    again = decode_pair(feats, pair.fps, CanonicalFrame.from_dict(frame.to_dict()))
    np.testing.assert_allclose(again.reactor.positions, back.reactor.positions[:-1], atol=1e-12)


# -- rotations ------------------------------------------------------------------------
@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000), shape_noise=st.sampled_from([0.0, 0.01, 0.03]))
def test_fk_of_rotation_part_lands_on_stored_positions(seed, shape_noise):
    """Rigid skeleton (any proportions, any pelvis/chest shape): FK of the 6D part with
    the fitted offsets lands within 1e-4 m of the stored positions (measured: < 1e-6 m)."""
    m = make_motion(seed, T=20, shape_noise=shape_noise)
    f = encode_person(m)
    stored = decode_person(f, m.fps)
    via_fk = decode_person(f, m.fps, use_rotations=True)
    assert np.abs(via_fk.positions - stored.positions).max() < 1e-4


def test_rest_pose_rotations_are_identity_and_leaves_always_identity():
    still = Motion(np.repeat(REST_POSE[None], 3, axis=0))
    rot6 = encode_person(still)[:, FEATURE_SLICES["rotations"]].reshape(2, 21, 6)
    np.testing.assert_allclose(rot6, np.broadcast_to(matrix_to_6d(np.eye(3)), (2, 21, 6)), atol=1e-6)
    moving = encode_person(make_motion(5))[:, FEATURE_SLICES["rotations"]].reshape(-1, 21, 6)
    leaves = [j - 1 for j in LEAF_JOINTS]
    np.testing.assert_allclose(
        moving[:, leaves], np.broadcast_to(matrix_to_6d(np.eye(3)), moving[:, leaves].shape), atol=1e-6
    )
    assert np.abs(moving - matrix_to_6d(np.eye(3))).max() > 0.1  # non-leaf joints do rotate


def test_rotation_part_is_invariant_to_where_the_person_stands():
    a = make_motion(7, yaw=0.0, start=(0.0, 0.0))
    b = make_motion(7, yaw=2.0, start=(5.0, -3.0))
    rot = FEATURE_SLICES["rotations"]
    np.testing.assert_allclose(encode_person(a)[:, rot], encode_person(b)[:, rot], atol=1e-5)


# -- canonicalisation -------------------------------------------------------------------
@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000), yaw=st.floats(-np.pi, np.pi), x=st.floats(-20, 20))
def test_canonical_frame_properties(seed, yaw, x):
    m = make_motion(seed, yaw=yaw, start=(x, -x))
    f = encode_person(m)
    p = rows_to_positions(f)  # Y-up, frames 0..T-2
    np.testing.assert_allclose([p[0, 0, 0], p[0, 0, 2]], [0.0, 0.0], atol=1e-6)  # root over the origin
    assert abs(p[0, 0, 1] - (m.positions[0, 0, 2] - m.positions[..., 2].min())) < 1e-5  # height kept
    last = p[-1] + f[-1, FEATURE_SLICES["velocities"]].reshape(22, 3)
    assert abs(min(p[..., 1].min(), last[:, 1].min())) < 1e-6  # floor at the lowest joint
    r_hip, l_hip, r_sho, l_sho = FACE_JOINTS
    across = p[0, r_hip] - p[0, l_hip] + p[0, r_sho] - p[0, l_sho]
    forward = np.cross([0, 1, 0], across)
    assert abs(forward[0]) < 1e-5 and forward[2] > 0  # faces +Z
    # decoded without a frame: Z-up, facing +X, root over the origin, floor z = 0
    z = decode_person(f, m.fps, append_last_frame=True).positions
    np.testing.assert_allclose(z[0, 0, :2], [0.0, 0.0], atol=1e-6)
    assert abs(z[..., 2].min()) < 1e-6
    left = z[0, l_hip] + z[0, l_sho] - z[0, r_hip] - z[0, r_sho]
    assert left[1] > 0 and abs(np.cross([0, 0, 1], -left)[1]) < 1e-5  # forward = up x across is +X


def test_facing_is_undefined_for_a_vertical_across_vector():
    pos = np.repeat(REST_POSE[None], 2, axis=0).copy()
    r_hip, l_hip, r_sho, l_sho = FACE_JOINTS
    for right, left in ((r_hip, l_hip), (r_sho, l_sho)):
        pos[:, right, :2] = pos[:, left, :2]  # right exactly above/below left
    assert canonical_frame(Motion(pos)).yaw == 0.0


# -- two persons ------------------------------------------------------------------------
def test_person_b_placement_relative_to_a_is_preserved():
    pair = make_pair(11)
    feats, frame = encode_pair(pair)
    pa, pb = rows_to_positions(feats[:, 0]), rows_to_positions(feats[:, 1])
    # all A-B joint distances are kept (one rigid transform for both)
    d_world = np.linalg.norm(pair.actor.positions[:-1, :, None] - pair.reactor.positions[:-1, None], axis=-1)
    d_feat = np.linalg.norm(pa[:, :, None] - pb[:, None], axis=-1)
    np.testing.assert_allclose(d_feat, d_world, atol=1e-5)
    # B's height is measured from A's floor
    a_floor = pair.actor.positions[..., 2].min()
    np.testing.assert_allclose(pb[..., 1], pair.reactor.positions[:-1, :, 2] - a_floor, atol=1e-5)
    # A is canonical on its own, B is not moved to the origin
    np.testing.assert_allclose(feats[:, 0], encode_person(pair.actor), atol=1e-6)
    assert np.linalg.norm(pb[0, 0, [0, 2]]) > 0.5
    # B's offset from A, seen in A's facing frame: rotate the world offset by the same yaw
    off_world = zup_to_yup(pair.reactor.positions[0, 0] - pair.actor.positions[0, 0])
    np.testing.assert_allclose(pb[0, 0] - pa[0, 0], frame.rotation @ off_world, atol=1e-5)
    # without a frame the pair comes back in A's canonical frame (Z-up)
    canon = decode_pair(feats, pair.fps)
    np.testing.assert_allclose(canon.reactor.positions, yup_to_zup(pb), atol=1e-6)


# -- foot contacts ----------------------------------------------------------------------
def test_contacts_on_a_known_stance_phase():
    """Left foot planted (0-9), lifted 0.25 m and held (10-19), planted again (20-29);
    the right foot stays planted throughout."""
    T = 30
    pos = np.repeat(REST_POSE[None], T, axis=0).copy()
    left = [joint_index("left_ankle"), joint_index("left_foot")]
    pos[10:20, left, 2] += 0.25
    pos[:, :, 0] += 0.3  # the whole body stands off the origin; does not matter
    c = encode_person(Motion(pos))[:, FEATURE_SLICES["contacts"]]
    assert c.shape == (T - 1, 4)
    expected_left = np.zeros(T - 1, dtype=bool)
    expected_left[:9] = True  # frame 9 -> 10 moves 0.25 m; 10..18 are too high; 19 -> 20 moves
    expected_left[20:] = True
    np.testing.assert_array_equal(c[:, 0] > 0.5, expected_left)  # left ankle
    np.testing.assert_array_equal(c[:, 1] > 0.5, expected_left)  # left foot
    np.testing.assert_array_equal(c[:, 2:], np.ones((T - 1, 2)))  # right ankle, right foot
    back = decode_person(encode_person(Motion(pos)), 30.0, append_last_frame=True)
    np.testing.assert_array_equal(back.contacts[:-1, 0], expected_left)


@pytest.mark.parametrize("column", range(4))
def test_contact_thresholds_per_joint(column):
    """Squared per-frame displacement < 0.001 m^2 and height < 0.12 m (ankles) / 0.05 m (feet)."""
    joint = FOOT_JOINTS[column]
    h = CONTACT_HEIGHTS[column]
    pos = np.zeros((5, 22, 3))
    pos[:, :, 1] = 1.0  # every other joint high
    pos[:, joint, 1] = [h - 0.01, h - 0.01, h + 0.01, h - 0.01, h - 0.01]
    pos[:, joint, 0] = [0.0, 0.0, 0.0, 0.0, 0.04]  # 0.04^2 = 0.0016 > 0.001
    pos[1, joint, 0] = 0.03  # frame 0 -> 1: 0.03^2 + 0 = 0.0009 < 0.001
    pos[2, joint, 0] = 0.03
    c = foot_contacts(pos)[:, column]
    # t=0: slow + low -> 1; t=1: low, 0.03->0.03 x but height changes 0.02 -> 0.0004+0 -> 1;
    # t=2: high -> 0; t=3: moves 0.04 -> 0
    np.testing.assert_array_equal(c, [1, 1, 0, 0])
    others = [k for k in range(4) if k != column]
    assert not foot_contacts(pos)[:, others].any()


# -- bad input ----------------------------------------------------------------------------
def test_bad_inputs_raise_dualflow_error_naming_the_field():
    with pytest.raises(DualFlowError, match="at least 2"):
        encode_person(Motion(REST_POSE[None]))
    with pytest.raises(DualFlowError, match="features"):
        decode_person(np.zeros((5, 261)))
    with pytest.raises(DualFlowError, match="features"):
        decode_person(np.full((5, 262), np.nan))
    with pytest.raises(DualFlowError, match="pair features"):
        decode_pair(np.zeros((5, 262)))
    with pytest.raises(DualFlowError, match="canonical"):
        decode_person(np.zeros((2, 262)), canonical={"yaw": 0.0})
    with pytest.raises(DualFlowError, match="origin"):
        CanonicalFrame(0.0, [0.0, 1.0])
    with pytest.raises(DualFlowError, match="yaw"):
        CanonicalFrame.from_dict({"origin": [0, 0, 0]})
    with pytest.raises(DualFlowError, match="motion"):
        encode_person(np.zeros((4, 22, 3)))
    with pytest.raises(DualFlowError, match="pair"):
        encode_pair(make_motion(0))
    # a generated row whose 6D block is degenerate cannot be decoded through rotations
    f = encode_person(make_motion(0))
    f[3, FEATURE_SLICES["rotations"]] = 0.0
    with pytest.raises(DualFlowError, match="rotation 6D"):
        decode_person(f, use_rotations=True)
    decode_person(f)  # the position part alone still decodes
