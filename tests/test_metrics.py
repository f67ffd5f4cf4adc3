"""Metrics' known properties: FID of a set with itself is 0 and of a shifted copy is ‖shift‖²;
R-precision of matched identical embeddings is 1 and of unrelated ones near chance; diversity
and multimodality of identical samples are 0; BAS is 1 when speed minima sit on the beats and
drops when they sit half a beat away; BED of a person with themselves is 1; DD100 features."""

from __future__ import annotations

import numpy as np
import pytest

from dualflow.errors import DualFlowError
from dualflow.evaluation import metrics as M
from dualflow.evaluation.dance import dd100_metrics, duet_feature, kinetic_feature
from dualflow.evaluation.rhythm import alignment_score, beat_alignment_score, beat_echo_degree, motion_beats
from dualflow.evaluation.table import format_table
from dualflow.synthetic import make_duet

RNG = np.random.default_rng(0)


def test_fid_properties():
    x = RNG.normal(size=(500, 8))
    assert abs(M.fid(x, x)) < 1e-6
    shift = np.arange(8) * 0.1
    assert M.fid(x + shift, x) == pytest.approx(float(shift @ shift), rel=1e-6)
    # Gaussians: FID(N(0, I), N(0, 4I)) = d (1 + 4 - 2·2) = d
    a, b = RNG.normal(size=(20000, 3)), 2.0 * RNG.normal(size=(20000, 3))
    assert M.fid(a, b) == pytest.approx(3.0, rel=0.05)
    with pytest.raises(DualFlowError):
        M.fid(np.zeros((1, 3)), x[:, :3])


def test_r_precision_matched_and_chance():
    t = RNG.normal(size=(192, 16))
    r, mm = M.r_precision(t, t, batch_size=96)
    np.testing.assert_allclose(r, [1.0, 1.0, 1.0])
    assert mm == pytest.approx(0.0, abs=1e-6)
    r, _ = M.r_precision(t, RNG.normal(size=(192, 16)), batch_size=96, rng=np.random.default_rng(1))
    assert np.all(r < 0.12) and r[0] <= r[1] <= r[2]  # chance: 1/96, 2/96, 3/96
    # a small batch: all pairs form one batch; the last incomplete batch is dropped otherwise
    r, _ = M.r_precision(t[:10], t[:10], batch_size=96)
    np.testing.assert_allclose(r, 1.0)
    # distances: MM distance is the mean matched distance
    _, mm = M.r_precision(t, t + 0.5, batch_size=96)
    assert mm == pytest.approx(0.5 * np.sqrt(16), rel=1e-6)


def test_diversity_and_multimodality():
    same = np.ones((300, 4))
    assert M.diversity(same) == 0.0
    spread = RNG.normal(size=(400, 32))
    assert M.diversity(spread) == pytest.approx(np.sqrt(2 * 32), rel=0.1)  # E‖a−b‖ ≈ √(2d)
    assert M.multimodality(np.ones((5, 30, 4))) == 0.0
    assert M.multimodality(RNG.normal(size=(50, 30, 32))) == pytest.approx(np.sqrt(2 * 32), rel=0.1)
    est = M.Estimate.of([1.0, 2.0, 3.0])
    assert est.mean == 2.0 and est.ci == pytest.approx(1.96 * np.std([1, 2, 3]) / np.sqrt(3))


def _motion_with_minima(n: int, period: float, phase: float) -> np.ndarray:
    """(n, 22, 3) positions moving along x with speed 1.05 − cos(2π(t − phase)/period) cm/frame:
    speed minima at t = phase + k·period."""
    t = np.arange(n - 1)
    speed = 0.01 * (1.05 - np.cos(2 * np.pi * (t - phase) / period))
    x = np.concatenate([[0.0], np.cumsum(speed)])
    pos = np.zeros((n, 22, 3))
    pos[:, :, 0] = x[:, None]
    pos[:, :, 1] = np.linspace(0, 1, 22)[None]
    return pos


def test_bas_is_one_on_the_beats_and_low_off_them():
    period = 16
    pos = _motion_with_minima(200, period, 5)
    beats = np.arange(5 + period, 180, period)
    found = motion_beats(pos)
    assert set(beats).issubset(set(found.tolist()))
    assert beat_alignment_score(pos, beats) == pytest.approx(1.0)
    off = beats + period // 2
    assert beat_alignment_score(pos, off) < 0.05  # exp(-64/18) ≈ 0.03
    assert alignment_score([10], [13]) == pytest.approx(np.exp(-9 / 18))  # σ² = 9 frames²
    assert alignment_score([10], []) == 0.0 and np.isnan(alignment_score([], [1]))


def test_bed_echo():
    pos = _motion_with_minima(200, 16, 5)
    assert beat_echo_degree(pos, pos) == pytest.approx(1.0)
    assert beat_echo_degree(pos, _motion_with_minima(200, 16, 13)) < 0.05


def test_dd100_features():
    d = [make_duet(rule, seconds=2.0, seed=s) for s, rule in enumerate(["mirror", "follow", "orbit", "hand_hold"] * 2)]
    pairs = [(x.actor.positions, x.reactor.positions) for x in d]
    f = duet_feature(pairs[0][1], pairs[0][0])
    assert f.shape == (100,)
    # the follower's pelvis-to-leader's-pelvis entry is their mean pelvis distance
    np.testing.assert_allclose(f[0], np.linalg.norm(pairs[0][1][:, 0] - pairs[0][0][:, 0], axis=-1).mean())
    assert kinetic_feature(pairs[0][1]).shape == (66,)
    m = dd100_metrics(pairs, pairs)
    assert abs(m["fid_k"]) < 1e-4 and abs(m["fid_cd"]) < 1e-4 and m["div_cd"] > 0
    # swapping in static followers moves both FIDs away from 0
    still = [(ld, np.repeat(f[:1], len(f), axis=0) + 1e-3 * RNG.normal(size=f.shape)) for ld, f in pairs]
    m2 = dd100_metrics(still, pairs)
    assert m2["fid_k"] > 1.0 and m2["fid_cd"] > 0.1


def test_table_layout():
    est = {k: M.Estimate.of([0.5, 0.6]) for k in ("r1", "r2", "r3", "fid", "mm_dist", "diversity", "bed", "bas")}
    text = format_table([("Ground Truth", est), ("Reactive Task", None), ("DualFlow", est)], title="T")
    lines = text.splitlines()
    assert lines[0] == "T" and "R@1" in lines[1] and "MModality" in lines[1]
    assert lines[3].startswith("Ground Truth") and "0.550±0.069" in lines[3] and lines[3].count("-") >= 1
    assert lines[4] == "[Reactive Task]"
