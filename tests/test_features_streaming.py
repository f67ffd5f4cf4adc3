"""The 262-d encoding frame by frame (the bridge's streaming path) equals the whole-clip one,
and the level-batched inverse kinematics equals the joint-by-joint equations it replaced."""

from __future__ import annotations

import numpy as np
import pytest

from dualflow.motion import Motion
from dualflow.motion.features import REST_POSE_YUP, canonical_frame, encode_person
from dualflow.motion.kinematics import CHILDREN, inverse_kinematics, rest_offsets
from dualflow.motion.rotations import align_vector_sets, swing_rotation
from dualflow.motion.skeleton import N_JOINTS, PARENTS
from dualflow.synthetic import make_duet


def _reference_ik(positions: np.ndarray, rest: np.ndarray) -> np.ndarray:
    """Local rotations (T, 22, 3, 3), one joint at a time in index order (the docstring of
    ``inverse_kinematics``): Kabsch over the scaled rest child directions for several children,
    the swing onto G_parent^T (p_child - p_j) for one, identity for none."""
    off = rest_offsets(rest)
    T = positions.shape[0]
    local = np.broadcast_to(np.eye(3), (T, N_JOINTS, 3, 3)).copy()
    G = local.copy()
    for j in range(N_JOINTS):
        parent_G = G[:, PARENTS[j]] if j else np.broadcast_to(np.eye(3), (T, 3, 3))
        kids = list(CHILDREN[j])
        if kids:
            posed = np.einsum("tba,tkb->tka", parent_G, positions[:, kids] - positions[:, j : j + 1])
            rest_dirs = off[kids] / np.linalg.norm(off[kids], axis=-1, keepdims=True)
            if len(kids) == 1:
                local[:, j] = swing_rotation(rest_dirs[0], posed[:, 0])
            else:
                local[:, j] = align_vector_sets(rest_dirs[None] * np.linalg.norm(posed, axis=-1, keepdims=True), posed)
        G[:, j] = parent_G @ local[:, j]
    return local


def test_batched_ik_matches_joint_by_joint_equations_including_degenerate_bones():
    rng = np.random.default_rng(3)
    pos = REST_POSE_YUP[None] + 0.1 * rng.standard_normal((6, N_JOINTS, 3))
    pos[0] = REST_POSE_YUP  # every swing is the identity (parallel directions: the fallback axis)
    pos[1, 4] = pos[1, 1]  # a zero-length bone: identity swing
    pos[2, 18:] = pos[2, 16] + (pos[2, 16] - pos[2, 18])[None]  # an elbow folded straight back
    _, local = inverse_kinematics(pos, REST_POSE_YUP)
    want = _reference_ik(pos, REST_POSE_YUP)
    assert np.abs(local - want).max() < 1e-12
    assert np.allclose(local[0], np.eye(3), atol=1e-12)
    # proper rotations everywhere
    assert np.allclose(local @ np.swapaxes(local, -1, -2), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(local), 1.0, atol=1e-12)


def _frame_by_frame(positions: np.ndarray, fps: float) -> np.ndarray:
    """What ReactorStage does: each row encoded from a two-frame window [t, t+1] in the
    canonical frame of the first frame."""
    frame = canonical_frame(Motion(positions[:1], fps))
    return np.concatenate([encode_person(Motion(positions[t : t + 2], fps), frame) for t in range(len(positions) - 1)])


def test_frame_by_frame_encoding_equals_whole_clip_synthetic():
    actor = make_duet("mirror", seconds=2.0, seed=5).actor
    frame = canonical_frame(Motion(actor.positions[:1], actor.fps))
    whole = encode_person(actor, frame)
    streamed = _frame_by_frame(actor.positions, actor.fps)
    assert streamed.shape == whole.shape == (actor.n_frames - 1, 262)
    assert np.abs(streamed - whole).max() < 1e-6
    # the rotation part against the joint-by-joint IK, whole clip
    pos = frame.to_canonical(actor.positions)
    ref6 = _reference_ik(pos, REST_POSE_YUP)[:-1, 1:, :, :2].swapaxes(-1, -2).reshape(len(pos) - 1, -1)
    assert np.abs(whole[:, 132:258] - ref6).max() < 1e-6


def test_frame_by_frame_encoding_equals_whole_clip_cmu(cmu_pair_paths):
    from dualflow.motion.io import load_pair

    actor = load_pair(*cmu_pair_paths, fps=30.0).actor
    positions = actor.positions[:120]
    frame = canonical_frame(Motion(positions[:1], 30.0))
    whole = encode_person(Motion(positions, 30.0), frame)
    streamed = _frame_by_frame(positions, 30.0)
    assert np.abs(streamed - whole).max() < 1e-6
    assert whole[:, 258:].any()  # contacts exercised


@pytest.mark.parametrize("T", [2, 3])
def test_short_windows_keep_one_row_per_frame_pair(T):
    pos = REST_POSE_YUP[None].repeat(T, 0)
    rows = encode_person(Motion(pos[..., [2, 0, 1]], 30.0))
    assert rows.shape == (T - 1, 262)
    assert np.allclose(rows[:, 132:258].reshape(T - 1, 21, 6), [1, 0, 0, 0, 1, 0], atol=1e-7)
