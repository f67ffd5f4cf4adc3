"""Real motion capture: the CMU pair 18_01 / 19_01 ("walk, shake hands").

What is physically true of two adults walking up to each other and shaking hands
checks the unit, the axes and the joint map in one go. Skips where
../shared/data is absent (see tests/conftest.py).
"""

from __future__ import annotations

import numpy as np
import pytest

from dualflow.motion import FOOT_JOINTS, joint_index
from dualflow.motion.io import load_pair, read_bvh, read_bvh_motion
from dualflow.motion.io.units import KNOWN_UNITS, Y_UP

PELVIS = joint_index("pelvis")
HEAD = joint_index("head")
R_WRIST = joint_index("right_wrist")
TOES = [joint_index("left_foot"), joint_index("right_foot")]


@pytest.fixture
def cmu_pair(cmu_pair_paths):
    return load_pair(*cmu_pair_paths, fps=30.0)


def test_raw_files_parse_with_mixed_line_endings(cmu_pair_paths):
    for path in cmu_pair_paths:
        raw = path.read_bytes()
        assert b"\r\n" in raw and raw.count(b"\n") > raw.count(b"\r\n")  # the mixed endings are really there
        clip = read_bvh(path)
        assert len(clip.joints) == 31 + 7 and clip.n_channels == 96
        assert clip.n_frames == 304 and clip.fps == pytest.approx(120.0, rel=1e-4)
        assert clip.joints[0].channels[3:] == ("Zrotation", "Yrotation", "Xrotation")


def test_detected_unit_axes_map_and_reference_frame(cmu_pair_paths):
    for path in cmu_pair_paths:
        r = read_bvh_motion(path)
        assert r.joint_map == "cmu"
        assert r.scale == pytest.approx(KNOWN_UNITS["cmu"]) == pytest.approx(0.05644, rel=1e-3)
        np.testing.assert_allclose(r.axes, Y_UP)
        assert r.dropped_first_frame and r.motion.n_frames == 303
        assert 1.45 < r.height < 1.75


def test_pair_is_physically_plausible_at_30_fps(cmu_pair):
    a, b = cmu_pair.actor.positions, cmu_pair.reactor.positions
    assert cmu_pair.fps == 30.0 and cmu_pair.n_frames == 76  # 2.525 s of capture
    for pos in (a, b):
        assert np.all(np.abs(pos[:, PELVIS, 2] - 1.0) < 0.1)  # pelvis about 1 m above the floor
        assert np.all((pos[:, HEAD, 2] > 1.3) & (pos[:, HEAD, 2] < 1.6))
        assert pos[:, TOES, 2].min() > -0.02  # toes never more than 2 cm below the floor
        assert pos[:, list(FOOT_JOINTS), 2].min() < 0.12  # and the feet do reach down to it
        # upright: the head is above the pelvis in every frame
        assert np.all(pos[:, HEAD, 2] - pos[:, PELVIS, 2] > 0.3)


def test_handshake(cmu_pair):
    a, b = cmu_pair.actor.positions, cmu_pair.reactor.positions
    t = np.arange(cmu_pair.n_frames) / cmu_pair.fps
    wrists = np.linalg.norm(a[:, R_WRIST] - b[:, R_WRIST], axis=-1)
    k = int(np.argmin(wrists))
    assert 0.7 < t[k] < 1.5  # about 1 s in
    assert wrists[k] < 0.45
    pelvis_gap = np.linalg.norm(a[:, PELVIS] - b[:, PELVIS], axis=-1)
    assert pelvis_gap[k] > 0.6 and pelvis_gap.min() > 0.6
    # they walk towards each other: far apart at the start, closest near the handshake
    assert pelvis_gap[0] > 1.5 and abs(t[np.argmin(pelvis_gap)] - t[k]) < 0.5
    # and face each other there: each one's forward (left x up) points at the other
    for me, other in ((a, b), (b, a)):
        left = me[k, joint_index("left_hip")] - me[k, joint_index("right_hip")]
        forward = np.cross(left, [0.0, 0.0, 1.0])
        to_other = other[k, PELVIS] - me[k, PELVIS]
        assert forward @ to_other / (np.linalg.norm(forward) * np.linalg.norm(to_other)) > 0.7


def test_world_frame_is_shared_not_recentred(cmu_pair_paths, cmu_pair):
    # the README of the data: root X/Z distance about 1.98 m at the first captured frame
    gap = np.linalg.norm(cmu_pair.actor.positions[0, PELVIS, :2] - cmu_pair.reactor.positions[0, PELVIS, :2])
    assert gap == pytest.approx(1.98, abs=0.03)
    # frame 2 of 18_01 has its root at X Y Z = 9.2465 17.8507 15.8856 CMU units (Y up)
    expected = KNOWN_UNITS["cmu"] * np.array([15.8856, 9.2465, 17.8507])
    np.testing.assert_allclose(cmu_pair.actor.positions[0, PELVIS], expected, atol=1e-4)
