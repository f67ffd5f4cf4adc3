"""The synthetic duet generator: exact bones, planted feet, the follower rules, beats, text."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from dualflow import DualFlowError
from dualflow.motion import REST_POSE, Motion, TwoPersonMotion, bone_lengths
from dualflow.synthetic import (
    FOLLOW_LAG_S,
    FOLLOW_SIDE_M,
    HOLD_GAP_M,
    ORBIT_RADIUS_M,
    RULES,
    make_duet,
    make_leader,
)

REST_BONES = bone_lengths(REST_POSE)


def _facing(positions: np.ndarray) -> np.ndarray:
    """(T, 2) unit horizontal facing direction from the hips: (left - right) x up."""
    across = positions[:, 1] - positions[:, 2]
    f = np.cross(across, [0.0, 0.0, 1.0])[:, :2]
    return f / np.linalg.norm(f, axis=-1, keepdims=True)


@pytest.mark.parametrize("rule", RULES)
@pytest.mark.parametrize("seed", [0, 1, 2, 3, 4, 5])
def test_bodies_are_physical(rule, seed):
    pair = make_duet(rule, seconds=4.0, fps=30.0, seed=seed)
    assert isinstance(pair, TwoPersonMotion) and pair.n_frames == 120 and pair.fps == 30.0
    for m in (pair.actor, pair.reactor):
        # bones keep the rest-pose lengths exactly (forward kinematics)
        np.testing.assert_allclose(bone_lengths(m.positions), np.broadcast_to(REST_BONES, (120, 21)), atol=1e-9)
        # nothing below the ground; every frame has a planted foot
        assert m.positions[..., 2].min() > -1e-9
        c = m.contacts
        assert c is not None and (c[:, 0] | c[:, 2]).all()
        ankles = m.positions[:, [7, 8]]
        planted = c[:, [0, 2]]
        # a planted ankle sits at its rest height and does not slide
        np.testing.assert_allclose(ankles[..., 2][planted], REST_POSE[7, 2], atol=1e-6)
        still = planted[1:] & planted[:-1]
        step = np.linalg.norm(np.diff(ankles, axis=0), axis=-1)
        assert step[still].max() < 1e-6
        # a swinging foot really lifts
        if (~planted).any():
            assert ankles[..., 2][~planted].max() > REST_POSE[7, 2] + 0.03


def test_deterministic_by_seed_and_leader_shared_across_rules():
    a = make_duet("orbit", seed=7)
    b = make_duet("orbit", seed=7)
    np.testing.assert_array_equal(a.actor.positions, b.actor.positions)
    np.testing.assert_array_equal(a.reactor.positions, b.reactor.positions)
    np.testing.assert_array_equal(a.meta["beats"], b.meta["beats"])
    assert a.text == b.text
    c = make_duet("orbit", seed=8)
    assert np.abs(a.actor.positions - c.actor.positions).max() > 0.05
    for rule in RULES:
        np.testing.assert_array_equal(make_duet(rule, seed=7).actor.positions, a.actor.positions)
    np.testing.assert_array_equal(make_leader(seed=7).positions, a.actor.positions)


def test_mirror_is_a_reflection_in_a_fixed_plane():
    pair = make_duet("mirror", seconds=4.0, seed=3)
    lead, foll = pair.actor.positions, pair.reactor.positions
    from dualflow.motion import MIRROR_INDEX

    # each leader joint and its mirror-twin in the follower are symmetric about one plane:
    # midpoints lie on the plane and the connecting segments are parallel to its normal
    twin = foll[:, list(MIRROR_INDEX)]
    seg = twin - lead
    normal = seg[..., :2].reshape(-1, 2)
    normal = normal[np.linalg.norm(normal, axis=-1) > 0.2]
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    n0 = normal[0]
    assert np.abs(np.abs(normal @ n0) - 1.0).max() < 1e-9
    np.testing.assert_allclose(seg[..., 2], 0.0, atol=1e-12)
    mid = 0.5 * (twin + lead)
    offsets = mid[..., :2].reshape(-1, 2) @ n0
    assert np.ptp(offsets) < 1e-9
    # face to face (a leader that does not turn keeps facing its mirror image)
    assert pair.meta["slots"]["turn"] != "none"
    still = make_duet("mirror", seconds=4.0, seed=2)
    assert still.meta["slots"]["turn"] == "none"
    for p, frames in ((pair, slice(0, 1)), (still, slice(None))):
        to_leader = p.actor.positions[frames, 0, :2] - p.reactor.positions[frames, 0, :2]
        to_leader /= np.linalg.norm(to_leader, axis=-1, keepdims=True)
        assert (np.sum(_facing(p.reactor.positions[frames]) * to_leader, axis=-1) > 0.99).all()


def test_follow_copies_the_leader_with_a_lag_beside_them():
    pair = make_duet("follow", seconds=4.0, fps=30.0, seed=2)
    lag = int(round(FOLLOW_LAG_S * 30.0))
    lead, foll = pair.actor.positions, pair.reactor.positions
    shift = foll[lag:] - lead[:-lag]
    np.testing.assert_allclose(shift, np.broadcast_to(shift[0], shift.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(shift[0, 0]), FOLLOW_SIDE_M, atol=1e-12)
    assert np.abs(shift[0, 0, 2]) < 1e-12
    # before the lag has elapsed the follower holds the leader's first frame
    np.testing.assert_allclose(foll[:lag] - lead[0], np.broadcast_to(shift[0], foll[:lag].shape), atol=1e-12)
    np.testing.assert_array_equal(pair.reactor.contacts[lag:], pair.actor.contacts[:-lag])


@pytest.mark.parametrize("rule,radius", [("hand_hold", HOLD_GAP_M), ("orbit", ORBIT_RADIUS_M)])
def test_distance_rules_keep_their_distance_and_face_the_leader(rule, radius):
    for seed in range(4):
        pair = make_duet(rule, seconds=4.0, seed=seed)
        lead, foll = pair.actor.positions, pair.reactor.positions
        d = np.linalg.norm(foll[:, 0, :2] - lead[:, 0, :2], axis=-1)
        np.testing.assert_allclose(d, radius, atol=1e-9)
        to_leader = (lead[:, 0, :2] - foll[:, 0, :2]) / d[:, None]
        assert np.sum(_facing(foll) * to_leader, axis=-1).min() > 0.95


def test_orbit_goes_round_the_leader():
    pair = make_duet("orbit", seconds=8.0, seed=1)
    rel = pair.reactor.positions[:, 0, :2] - pair.actor.positions[:, 0, :2]
    angle = np.unwrap(np.arctan2(rel[:, 1], rel[:, 0]))
    turns_expected = 8.0 * pair.meta["bpm"] / 60.0 / 16.0 * (239 / 240)
    np.testing.assert_allclose((angle[-1] - angle[0]) / (2 * np.pi), turns_expected, rtol=1e-6)


def test_beat_track_matches_the_tempo_and_the_steps():
    pair = make_duet("mirror", seconds=6.0, fps=30.0, seed=4)
    beats, frames, bpm = pair.meta["beats"], pair.meta["beat_frames"], pair.meta["bpm"]
    assert beats.shape == (180, 4) and beats.dtype == np.float32
    assert 90.0 <= bpm <= 130.0
    np.testing.assert_array_equal(np.flatnonzero(beats[:, 0]), frames)
    spacing = np.diff(frames)
    assert np.abs(spacing - 30.0 * 60.0 / bpm).max() <= 1.0
    assert len(frames) >= int(6.0 * bpm / 60.0) - 1
    # phase columns are a unit circle, the downbeat is every 4th beat
    np.testing.assert_allclose(beats[:, 1] ** 2 + beats[:, 2] ** 2, 1.0, atol=1e-6)
    down = np.flatnonzero(beats[:, 3])
    assert set(down) <= set(frames) and len(down) >= 1
    assert np.all(np.diff(np.searchsorted(frames, down)) == 4)
    # the leader lands a foot on every beat: a contact starts within a frame of each beat
    c = pair.actor.contacts[:, [0, 2]]
    landings = np.flatnonzero((c[1:] & ~c[:-1]).any(axis=1)) + 1
    for f in frames[frames > 3]:
        assert np.abs(landings - f).min() <= 1


def test_text_and_meta_describe_the_clip():
    for rule, word in (("mirror", "mirrors"), ("follow", "later"), ("hand_hold", "hand-hold"), ("orbit", "circles")):
        pair = make_duet(rule, seed=5)
        assert word in pair.text and "leader" in pair.text
        assert pair.meta["synthetic"] is True and pair.meta["rule"] == rule and pair.meta["seed"] == 5
        assert set(pair.meta["slots"]) == {"step", "arms", "turn", "travel"}
    texts = {make_duet("mirror", seed=s).text for s in range(12)}
    assert len(texts) > 4


def test_make_leader_and_errors():
    m = make_leader(seconds=2.0, fps=50.0, seed=1)
    assert isinstance(m, Motion) and m.n_frames == 100 and m.fps == 50.0 and m.contacts.shape == (100, 4)
    with pytest.raises(DualFlowError, match="unknown rule 'tango'"):
        make_duet("tango")
    with pytest.raises(DualFlowError, match="fps must be > 0"):
        make_duet("mirror", fps=0)
    with pytest.raises(DualFlowError, match="seconds must be > 0"):
        make_leader(seconds=-1)
    with pytest.raises(DualFlowError, match="bpm"):
        make_leader(bpm=1000)


def test_importing_the_generator_does_not_import_torch():
    code = "import sys, dualflow.synthetic as s; s.make_duet('orbit'); assert 'torch' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)


# -- training windows cut at random offsets (issue 28) ----------------------------------------


def _crop_config(**kw):
    from dualflow.datasets.config import TrainingDataConfig

    return TrainingDataConfig(**{"n_clips": 24, "val_clips": 4, "frames": 30, "crop": 1.0, "crop_max_s": 4.0, **kw})


def test_crops_start_at_random_offsets_and_validation_clips_do_not():
    from dualflow.datasets.synthetic import build_split

    train = build_split(_crop_config(), "train")
    assert train.offsets.shape == (24,)
    assert (train.offsets >= 1).all() and (train.offsets <= 120).all()
    assert len(set(train.offsets.tolist())) >= 16 and train.offsets.std() > 15  # spread over 4 s, not one offset
    assert (build_split(_crop_config(), "val").offsets == 0).all()
    assert (build_split(_crop_config(), "val", crop_any_split=True).offsets > 0).all()  # --evaluate --mid-dance
    half = build_split(_crop_config(n_clips=64, crop=0.5), "train").offsets
    assert 16 <= int((half > 0).sum()) <= 48
    # no crop: the classic clips, byte for byte
    from dualflow.motion.features import encode_pair

    classic = build_split(_crop_config(crop=0.0), "train")
    assert (classic.offsets == 0).all()
    np.testing.assert_array_equal(classic.features[5], encode_pair(make_duet(RULES[1], 31 / 30.0, 30.0, 5))[0])


def test_a_crop_cuts_leader_follower_and_beats_at_the_same_frames():
    from dualflow.datasets.synthetic import build_split
    from dualflow.motion.features import encode_pair

    cfg = _crop_config(n_clips=8)
    split = build_split(cfg, "train")
    for i in range(8):
        o, seed, rule = int(split.offsets[i]), int(split.seeds[i]), RULES[i % 4]
        whole = make_duet(rule, (o + 31) / 30.0, 30.0, seed)
        want, _ = encode_pair(whole.slice(o, o + 31))
        assert whole.actor.n_frames == o + 31  # the source clip the crop was cut from, no longer
        np.testing.assert_allclose(split.features[i], want, atol=1e-6)
        np.testing.assert_array_equal(split.beats[i], whole.meta["beats"][o : o + 30])
        # the check would see a follower cut one frame off the leader
        off = TwoPersonMotion(whole.actor.slice(o - 1, o + 30), whole.reactor.slice(o, o + 31))
        assert np.abs(encode_pair(off)[0][:, 1] - want[:, 1]).max() > 1e-3


def test_a_cropped_follow_clip_still_follows_and_speed_and_mirror_keep_a_valid_duet():
    from dualflow.datasets.synthetic import CropDraw, cropped_duet

    lag = int(round(FOLLOW_LAG_S * 30.0))
    pair = cropped_duet("follow", 61, 30.0, 3, CropDraw(offset=47))
    lead, foll = pair.actor.positions, pair.reactor.positions
    shift = foll[lag:] - lead[:-lag]
    np.testing.assert_allclose(shift, np.broadcast_to(shift[0], shift.shape), atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(shift[0, 0]), FOLLOW_SIDE_M, atol=1e-9)
    # 1.25x as fast: the beats come 1.25x as often, bones stay exact, mirrored sides swap in the text
    slow = cropped_duet("mirror", 150, 30.0, 4, CropDraw(offset=20))
    fast = cropped_duet("mirror", 150, 30.0, 4, CropDraw(offset=20, speed=1.25, mirrored=True))
    gap = lambda p: np.diff(p.meta["beat_frames"]).mean()  # noqa: E731
    np.testing.assert_allclose(gap(slow) / gap(fast), 1.25, rtol=0.05)
    for person in (fast.actor, fast.reactor):
        np.testing.assert_allclose(bone_lengths(person.positions), np.broadcast_to(REST_BONES, (150, 21)), atol=1e-9)
    assert fast.actor.fps == 30.0 and len(fast.actor.positions) == 150
    if "left" in slow.text or "right" in slow.text:
        assert fast.text != slow.text


def test_a_split_built_in_worker_processes_is_the_split_built_in_this_one(tmp_path):
    from dualflow.datasets.synthetic import _CHUNK, build_split

    cfg = _crop_config(n_clips=_CHUNK + 40, crop=0.5, varied=0.4, crop_mirror=0.5)  # two tasks, every clip kind
    here = build_split(cfg, "train")
    there = build_split(cfg, "train", workers=2)
    np.testing.assert_array_equal(there.features, here.features)
    np.testing.assert_array_equal(there.beats, here.beats)
    assert there.texts == here.texts
    for name in ("rules", "seeds", "offsets"):
        np.testing.assert_array_equal(getattr(there, name), getattr(here, name))
    # the cache a parallel build writes is read back as the same split by a build in this process
    cached = build_split(cfg, "train", cache_dir=tmp_path, workers=2)
    np.testing.assert_array_equal(build_split(cfg, "train", cache_dir=tmp_path).features, cached.features)
    assert len(list(tmp_path.iterdir())) == 1
    assert build_split(_crop_config(n_clips=1), "train", workers=2).features.shape == (1, 30, 2, 262)
