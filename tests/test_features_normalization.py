"""NormStats: statistics over both persons, normalise/denormalise, npz round trip, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from dualflow.errors import DualFlowError
from dualflow.motion import REST_POSE, Motion, TwoPersonMotion
from dualflow.motion.features import FEATURE_SLICES, encode_pair
from dualflow.motion.normalization import STD_FLOOR, NormStats


def pair_features(seed: int, T: int = 40) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = np.arange(T)[:, None, None] / 30.0
    base = np.repeat(REST_POSE[None], T, axis=0)
    a = base + 0.1 * np.sin(2 * np.pi * t + rng.uniform(0, 6, size=(1, 22, 3))) + [0.5 * t[:, 0, 0].mean(), 0, 0]
    b = base + 0.1 * np.sin(3 * np.pi * t + rng.uniform(0, 6, size=(1, 22, 3))) + [1.5, 0.3, 0.0]
    feats, _ = encode_pair(TwoPersonMotion(Motion(a), Motion(b)))
    return feats


def test_stats_pool_both_persons_and_normalize_to_zero_mean_unit_std():
    feats = pair_features(0)
    stats = NormStats.from_features(feats)
    rows = feats.reshape(-1, 262).astype(np.float64)
    np.testing.assert_allclose(stats.mean, rows.mean(axis=0), atol=1e-9)
    z = stats.normalize(feats)
    assert z.shape == feats.shape and z.dtype == np.float32
    varying = rows.std(axis=0) > STD_FLOOR
    assert varying[FEATURE_SLICES["positions"]].all()
    flat = z.reshape(-1, 262).astype(np.float64)
    np.testing.assert_allclose(flat.mean(axis=0), 0.0, atol=1e-4)
    np.testing.assert_allclose(flat[:, varying].std(axis=0), 1.0, atol=1e-3)
    # constant columns (the leaf joints' identity rotation) are floored, not divided by zero
    assert (~varying).any() and np.all(stats.std[~varying] == STD_FLOOR)
    assert np.isfinite(z).all()
    np.testing.assert_allclose(stats.denormalize(z), feats, atol=1e-5)


def test_from_a_list_equals_from_the_concatenation():
    f1, f2 = pair_features(1), pair_features(2, T=25)
    s_list = NormStats.from_features([f1, f2[:, 1]])
    s_cat = NormStats.from_features(np.concatenate([f1.reshape(-1, 262), f2[:, 1]], axis=0))
    np.testing.assert_allclose(s_list.mean, s_cat.mean, atol=1e-12)
    np.testing.assert_allclose(s_list.std, s_cat.std, atol=1e-12)


def test_npz_round_trip(tmp_path):
    stats = NormStats.from_features(pair_features(3))
    path = stats.save(tmp_path / "stats.npz")
    assert sorted(np.load(path, allow_pickle=False).files) == ["mean", "std"]
    assert not list(tmp_path.glob("*.partial*"))
    loaded = NormStats.load(path)
    np.testing.assert_array_equal(loaded.mean, stats.mean)
    np.testing.assert_array_equal(loaded.std, stats.std)


def test_bad_stats_and_inputs_raise_naming_the_field_or_file(tmp_path):
    ones = np.ones(262)
    with pytest.raises(DualFlowError, match="mean must have shape"):
        NormStats(np.zeros(261), ones)
    with pytest.raises(DualFlowError, match="std must be > 0, column 5"):
        NormStats(np.zeros(262), np.where(np.arange(262) == 5, 0.0, 1.0))
    with pytest.raises(DualFlowError, match="std contains NaN"):
        NormStats(np.zeros(262), np.full(262, np.nan))
    stats = NormStats(np.zeros(262), ones)
    with pytest.raises(DualFlowError, match="last axis must be 262"):
        stats.normalize(np.zeros((3, 2, 263)))
    with pytest.raises(DualFlowError, match="last axis must be 262"):
        stats.denormalize(np.zeros(10))
    with pytest.raises(DualFlowError, match="NaN"):
        NormStats.from_features(np.full((4, 262), np.nan))
    with pytest.raises(DualFlowError, match="empty list"):
        NormStats.from_features([])
    with pytest.raises(DualFlowError, match=r"\.npz"):
        stats.save(tmp_path / "stats.json")
    with pytest.raises(DualFlowError, match="does not exist"):
        stats.save(tmp_path / "no_such_dir" / "stats.npz")

    missing = tmp_path / "missing_std.npz"
    np.savez(missing, mean=np.zeros(262))
    with pytest.raises(DualFlowError, match=r"missing_std\.npz.*lacks std"):
        NormStats.load(missing)
    wrong = tmp_path / "wrong.npz"
    np.savez(wrong, mean=np.zeros(100), std=np.ones(100))
    with pytest.raises(DualFlowError, match=r"wrong\.npz.*mean must have shape"):
        NormStats.load(wrong)
    pickled = tmp_path / "pickled.npz"
    np.savez(pickled, mean=np.array([{"a": 1}], dtype=object), std=np.ones(262))
    with pytest.raises(DualFlowError, match=r"pickled\.npz"):
        NormStats.load(pickled)
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"not a zip file")
    with pytest.raises(DualFlowError, match=r"garbage\.npz"):
        NormStats.load(garbage)
    with pytest.raises(DualFlowError, match=r"absent\.npz"):
        NormStats.load(tmp_path / "absent.npz")
