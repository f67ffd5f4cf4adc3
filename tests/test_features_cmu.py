"""The 262-d feature on real two-person capture (CMU 18_01 / 19_01, resampled to 30 fps).

Skips where ../shared/data is absent (see tests/conftest.py).
"""

from __future__ import annotations

import numpy as np
import pytest

from dualflow.motion import FACE_JOINTS
from dualflow.motion.features import FEATURE_SLICES, decode_pair, encode_pair


@pytest.fixture
def cmu_pair(cmu_pair_paths):
    from dualflow.motion.io import load_pair

    return load_pair(*cmu_pair_paths, fps=30.0)


def test_cmu_pair_round_trip_and_rotation_fk(cmu_pair):
    feats, frame = encode_pair(cmu_pair)
    assert feats.shape == (cmu_pair.n_frames - 1, 2, 262)
    back = decode_pair(feats, 30.0, frame, append_last_frame=True)
    for got, want in ((back.actor, cmu_pair.actor), (back.reactor, cmu_pair.reactor)):
        assert np.abs(got.positions - want.positions).max() < 1e-3  # measured ~1e-7 m

    # FK of the rotation part vs the stored positions. The CMU -> SMPL-22 map makes
    # the pelvis triangle (hips, spine1) and the chest (neck, collars) slightly
    # non-rigid, which one rotation per joint cannot follow; measured: max 14 mm
    # (actor) / 17 mm (reactor), mean 3-4 mm.
    stored = decode_pair(feats, 30.0)
    via_fk = decode_pair(feats, 30.0, use_rotations=True)
    for got, want in ((via_fk.actor, stored.actor), (via_fk.reactor, stored.reactor)):
        err = np.linalg.norm(got.positions - want.positions, axis=-1)
        assert err.max() < 0.03 and err.mean() < 0.008


def test_cmu_pair_canonical_frame_faces_the_partner(cmu_pair):
    feats, _ = encode_pair(cmu_pair)
    pa = feats[:, 0, FEATURE_SLICES["positions"]].reshape(-1, 22, 3)
    pb = feats[:, 1, FEATURE_SLICES["positions"]].reshape(-1, 22, 3)
    np.testing.assert_allclose(pa[0, 0, [0, 2]], 0.0, atol=1e-6)
    assert abs(pa[..., 1].min()) < 1e-6
    assert 0.85 < pa[0, 0, 1] < 1.15  # pelvis height above A's floor
    # the partner starts in front of A (+Z), about 2 m away, facing back towards A (-Z)
    assert 1.0 < pb[0, 0, 2] < 3.0 and abs(pb[0, 0, 0]) < 0.6
    r_hip, l_hip, r_sho, l_sho = FACE_JOINTS
    across = pb[0, r_hip] - pb[0, l_hip] + pb[0, r_sho] - pb[0, l_sho]
    forward = np.cross([0.0, 1.0, 0.0], across)
    assert forward[2] / np.linalg.norm(forward) < -0.9
    # walking then standing to shake hands: feet are planted most of the time
    contacts = feats[..., FEATURE_SLICES["contacts"]]
    assert 0.4 < contacts.mean() < 1.0
