"""dualflow.body: the per-frame cleanup that keeps a generated body together (issue 28)."""

from __future__ import annotations

import numpy as np
import pytest

from dualflow.body import BodyCleaner, CleanConfig, clean_positions
from dualflow.errors import DualFlowError
from dualflow.evaluation.plausibility import bone_cv, foot_contacts, jerk, skate
from dualflow.motion.skeleton import bone_lengths
from dualflow.synthetic import make_leader_clip


def _damaged(seed: int = 0, seconds: float = 4.0, jitter_m: float = 0.01):
    """A synthetic dancer (exact bones, planted feet) and a copy damaged the way generated
    bodies are: bones stretched by up to 5 % per frame, ``jitter_m`` white noise, feet sliding at up to 0.6 m/s."""
    clip = make_leader_clip(seconds, 30.0, seed)
    clean = clip.body.positions
    rng = np.random.default_rng(seed)
    parents = np.array([-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19])
    bones = clean[:, 1:] - clean[:, parents[1:]]
    bones *= 1.0 + 0.05 * rng.uniform(-1, 1, size=bones.shape[:2])[..., None]
    bad = np.empty_like(clean)
    bad[:, 0] = clean[:, 0]
    for j in range(1, 22):
        bad[:, j] = bad[:, parents[j]] + bones[:, j - 1]
    bad += rng.normal(0.0, jitter_m, size=bad.shape)
    sway = 0.15 * np.sin(2 * np.pi * np.arange(len(bad)) / 45.0)  # feet slide back and forth, up to 0.6 m/s
    bad[:, [7, 10, 8, 11], 0] += sway[:, None]
    return clean, bad


def test_bones_keep_one_length_per_bone_through_the_whole_clip():
    clean, bad = _damaged()
    assert bone_cv(bad) > 0.01
    out, _ = clean_positions(bad)
    lengths = bone_lengths(out)
    assert np.ptp(lengths, axis=0).max() < 1e-9
    assert bone_cv(out) < 1e-9
    # the skeleton is the first frame's, left and right averaged
    first = bone_lengths(bad[:1])[0]
    np.testing.assert_allclose(lengths[0, 6], 0.5 * (first[6] + first[7]), rtol=1e-9)  # left / right shins


def test_a_body_sunk_into_the_floor_keeps_its_bones_and_its_toes_above_it():
    _, bad = _damaged(seed=6)
    sunk = bad - np.array([0.0, 0.0, 0.06])
    out, _ = clean_positions(sunk)
    assert np.ptp(bone_lengths(out), axis=0).max() < 1e-9
    assert out[:, [10, 11], 2].min() >= -1e-9


def test_feet_in_contact_stay_put_and_skate_less_than_real_capture():
    clean, bad = _damaged(seed=3)
    assert skate(bad) > 0.3
    out, flags = clean_positions(bad)
    assert skate(out) < 0.05  # the real CMU partner 19_01: 0.2 by the same definition
    for side, ank in ((0, 7), (1, 8)):
        locked = flags[:, 2 * side]
        assert locked.sum() > 20
        runs = np.flatnonzero(np.diff(np.concatenate([[0], locked.astype(int), [0]])))
        for start, stop in zip(runs[::2], runs[1::2]):
            # from the frame it lands the ankle stays put: planted where it is (a foot planted
            # where the generated one was slid 8, 4, 2 cm over the next frames; under 1 mm is
            # the leg IK's reach while the pelvis settles)
            seg = out[start:stop, ank, :2]
            assert np.abs(seg - seg[0]).max() < 0.001
            if start > 0:  # ... and where it came down, not beside it
                assert np.linalg.norm(out[start, ank, :2] - out[start - 1, ank, :2]) < 0.01


def test_jitter_is_removed_to_within_the_undamaged_dancers_jerk():
    # 5 mm of white noise gives about the raw jerk of the bundled model's partners (1000-1300 m/s^3)
    clean, bad = _damaged(seed=5, jitter_m=0.005)
    assert jerk(bad) > 5 * jerk(clean)
    out, _ = clean_positions(bad)
    assert jerk(out) < 1.5 * jerk(clean)


def test_a_real_walking_partner_still_walks_after_cleanup(cmu_pair_paths):
    from dualflow.motion.io.formats import load_pair

    pair = load_pair(*cmu_pair_paths, fps=30.0)
    real = pair.reactor.positions
    out, _ = clean_positions(real)
    # the pelvis follows the capture (the filter lags a little), the feet end near the capture's
    assert np.linalg.norm(out[:, 0] - real[:, 0], axis=-1).mean() < 0.08
    assert np.linalg.norm(out[-1, [7, 8], :2] - real[-1, [7, 8], :2], axis=-1).max() < 0.25
    assert foot_contacts(out).any()


def test_output_frame_depends_on_past_input_frames_only():
    _, bad = _damaged(seed=1)
    changed = bad.copy()
    changed[50:] += np.array([0.3, -0.2, 0.1])
    a, fa = clean_positions(bad)
    b, fb = clean_positions(changed)
    np.testing.assert_array_equal(a[:50], b[:50])
    np.testing.assert_array_equal(fa[:50], fb[:50])
    assert not np.allclose(a[50:], b[50:])


def test_streaming_frame_by_frame_equals_the_offline_clip_and_reset_restarts():
    _, bad = _damaged(seed=2, seconds=2.0)
    offline, _ = clean_positions(bad)
    cleaner = BodyCleaner(30.0)
    live = np.stack([cleaner.step(p)[0] for p in bad])
    np.testing.assert_array_equal(live, offline)
    cleaner.reset()
    np.testing.assert_array_equal(cleaner.step(bad[0])[0], offline[0])


def test_given_bone_lengths_are_used():
    _, bad = _damaged(seed=4, seconds=1.0)
    lengths = np.full(21, 0.2)
    out, _ = clean_positions(bad, lengths=lengths)
    np.testing.assert_allclose(bone_lengths(out), 0.2, atol=1e-9)


def test_bad_input_gets_one_clear_error():
    with pytest.raises(DualFlowError, match="22, 3"):
        BodyCleaner().step(np.zeros((21, 3)))
    with pytest.raises(DualFlowError, match="finite"):
        BodyCleaner().step(np.full((22, 3), np.nan))
    with pytest.raises(DualFlowError, match="lengths"):
        BodyCleaner(lengths=np.ones(5))
    with pytest.raises(DualFlowError, match="order"):
        CleanConfig(order=0)


def test_a_body_running_off_travels_at_a_persons_speed_and_a_walk_is_left_alone():
    """The generated pelvis (the whole body) runs off at 4 m/s from standing and stops dead
    (a partner chasing an actor that steps back): cleaned, it travels at most max_speed and
    changes speed at most max_accel, and comes to rest where the generated body stopped
    without running past it. A walk at 1 m/s (under both limits after its start) is left where
    it is."""
    cfg = CleanConfig(smooth=False, feet=False)
    still = make_leader_clip(3.0, 30.0, 0).body.positions[:1]
    T = 90
    x = np.clip(np.arange(T) - 20, 0, 20) * (4.0 / 30.0)  # 4 m/s for 20 frames (2.67 m), then still
    run = np.repeat(still, T, axis=0)
    run[:, :, 0] += x[:, None]
    out, _ = clean_positions(run, 30.0, config=cfg)
    v = np.diff(out[:, 0, :2], axis=0) * 30.0
    a = np.diff(v, axis=0) * 30.0
    assert np.linalg.norm(v, axis=1).max() <= cfg.max_speed + 1e-9
    assert np.linalg.norm(a, axis=1).max() <= cfg.max_accel + 1e-9
    moved = out[:, 0, 0] - out[0, 0, 0]
    assert moved.max() <= x[-1] + 2e-3  # no overshoot (the braking is frame by frame: about 1 mm)
    assert abs(moved[-1] - x[-1]) < 1e-3  # and it got there
    # the body moves as one: bones and posture relative to the pelvis untouched
    np.testing.assert_allclose(out - out[:, :1], run - run[:, :1], atol=1e-12)
    walk = np.repeat(still, T, axis=0)
    walk[:, :, 0] += (np.arange(T) * (1.0 / 30.0))[:, None]
    out, _ = clean_positions(walk, 30.0, config=cfg)
    assert np.abs(out[15:, 0, 0] - walk[15:, 0, 0]).max() < 1e-9  # caught up after the start, then exact
    with pytest.raises(DualFlowError, match="max_speed"):
        CleanConfig(max_speed=2.0, max_accel=0.0)


def test_a_body_that_bobs_up_keeps_a_foot_on_the_floor_and_a_step_still_lifts_one():
    """A generated partner whose whole body rises 12 cm for 0.4 s, twice, hops (both feet off the
    floor) unless the cleaner keeps a foot planted: the training duets never leave the floor.
    One foot stays down through each bob, and a dancer's steps still lift a foot at a time."""
    clean, _ = _damaged(seed=2)
    bob = clean.copy()
    for start in (30, 75):
        bob[start : start + 12, :, 2] += 0.12
    assert foot_contacts(bob)[[35, 80]].sum() == 0  # both feet off the floor in the bobs
    rule = CleanConfig(one_foot_down=True, drop_gain=0.12)
    out, flags = clean_positions(bob, config=rule)
    planted = flags[:, [0, 2]]
    first = int(np.argmax(planted.any(axis=1)))
    assert first <= 1 and planted[first:].any(axis=1).all()  # from the start on, a foot is always planted
    assert np.ptp(bone_lengths(out), axis=0).max() < 1e-9
    assert CleanConfig().one_foot_down and CleanConfig().drop_gain == rule.drop_gain  # the default
    _, hopping = clean_positions(bob, config=CleanConfig(one_foot_down=False, drop_gain=0.5))
    assert not hopping[:, [0, 2]].any(axis=1).all()  # without the rule the body hops
    # a dancer's own steps still lift the feet, one at a time (8 and 11 lift-offs without the rule)
    for seed in (0, 3):
        _, bad = _damaged(seed=seed)
        down = clean_positions(bad, config=rule)[1][:, [0, 2]]
        assert down[1:].any(axis=1).all() and np.sum(down[1:] < down[:-1]) >= 6
