"""The contrastive evaluator and the whole evaluation on the synthetic duet dataset:
a small evaluator trained for a few hundred steps ranks matched (motion, text) pairs far
above chance on held-out clips; the ground-truth row has FID ~ 0; a tiny DualFlow
checkpoint runs through both modes; the evaluator saves and loads without pickle."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dualflow.checkpoint import save_checkpoint
from dualflow.datasets import load_dataset
from dualflow.errors import DualFlowError
from dualflow.evaluation.evaluator import (
    EvaluatorConfig,
    EvaluatorTraining,
    MotionTextEvaluator,
    train_evaluator,
    word_ids,
)
from dualflow.evaluation.protocol import CheckpointGenerator, EvalSet, ProtocolConfig, evaluate
from dualflow.model import DualFlow, DualFlowConfig
from dualflow.motion.normalization import NormStats
from dualflow.text import TEXT_ENCODER_ID

FRAMES = 30
TINY_EVAL = EvaluatorConfig(width=64, layers=2, heads=4, ff_dim=128, dim=64, vocab=1024)


@pytest.fixture(scope="module")
def synthetic_sets():
    train = EvalSet.from_duet_set(load_dataset("synthetic", split="train", n_clips=128, frames=FRAMES), FRAMES)
    test = EvalSet.from_duet_set(load_dataset("synthetic", split="test", n_clips=64, frames=FRAMES), FRAMES)
    return train, test


@pytest.fixture(scope="module")
def evaluator(synthetic_sets):
    torch.set_num_threads(1)  # the test machine is shared; one thread is the fastest there
    train, _ = synthetic_sets
    return train_evaluator(
        train.features, train.texts, config=TINY_EVAL, training=EvaluatorTraining(steps=150, batch_size=32, lr=1e-3)
    )


def test_word_ids_are_stable_and_padded():
    ids, mask = word_ids(["The leader waves", "waves"], 1024, 8)
    assert ids.shape == (2, 3) and mask.tolist() == [[True] * 3, [True, False, False]]
    assert ids[0, 2] == ids[1, 0] and ids[0, 0] != ids[0, 1]  # same word, same bucket
    assert word_ids([""], 1024, 8)[0].tolist() == [[0]]


@pytest.mark.slow
def test_trained_evaluator_r_precision_above_chance(synthetic_sets, evaluator):
    _, test = synthetic_sets
    cfg = ProtocolConfig(batch_size=32, diversity_times=32, mm_repeats=0, replications=2)
    gt = evaluate(None, test, evaluator, cfg)
    chance = np.array([1, 2, 3]) / 32
    r = np.array([gt["r1"].mean, gt["r2"].mean, gt["r3"].mean])
    assert np.all(r > 3 * chance), r  # matched pairs are found well above chance
    assert abs(gt["fid"].mean) < 1e-6  # ground truth vs itself
    assert gt["diversity"].mean > 0.1 and gt["multimodality"].n == 0
    assert 0.0 <= gt["bas"].mean <= 1.0 and 0.0 <= gt["bed"].mean <= 1.0
    # shuffled texts: R-precision falls to about chance, MM distance grows
    shuffled = EvalSet(
        test.features, list(np.random.default_rng(0).permutation(test.texts)), test.beat_frames, test.beats, test.fps
    )
    bad = evaluate(None, shuffled, evaluator, cfg)
    assert bad["r3"].mean < r[2] and bad["mm_dist"].mean > gt["mm_dist"].mean


@pytest.mark.slow
def test_whole_evaluation_with_a_tiny_checkpoint(tmp_path, synthetic_sets, evaluator):
    train, test = synthetic_sets
    torch.manual_seed(0)
    model = DualFlow(DualFlowConfig.preset("tiny", music_dim=4, text_dim=384))
    ckpt = save_checkpoint(
        tmp_path / "ckpt",
        model=model,
        stats=NormStats.from_features(train.features),
        meta={"text_encoder": TEXT_ENCODER_ID, "music": "beats"},
    )
    small = EvalSet(test.features[:12], test.texts[:12], test.beat_frames[:12], test.beats[:12], test.fps)
    cfg = ProtocolConfig(batch_size=12, diversity_times=12, mm_samples=3, mm_repeats=3, mm_times=2, replications=1)
    for mode in ("interactive", "reactive"):
        gen = CheckpointGenerator(ckpt, small, mode=mode, steps=2)
        out = gen(np.arange(3), seed=0)
        assert out.shape == (3, FRAMES, 2, 262) and np.isfinite(out).all()
        if mode == "reactive":
            np.testing.assert_allclose(out[:, :, 0], small.features[:3, :, 0], atol=1e-3)  # the actor is kept
        res = evaluate(gen, small, evaluator, ProtocolConfig(**{**cfg.__dict__, "mode": mode}))
        assert res["fid"].mean > 1.0  # an untrained model is far from the data
        assert res["multimodality"].n == 1 and res["multimodality"].mean > 0


def test_evaluator_save_load_roundtrip(tmp_path):
    train = EvalSet.from_duet_set(load_dataset("synthetic", split="val", n_clips=8, frames=20), 20)
    ev = train_evaluator(
        train.features[:8], train.texts[:8], config=TINY_EVAL, training=EvaluatorTraining(steps=2, batch_size=4)
    )
    ev.save(tmp_path / "ev")
    back = MotionTextEvaluator.load(tmp_path / "ev")
    m1, t1 = ev.embed(train.features[:4], train.texts[:4])
    m2, t2 = back.embed(train.features[:4], train.texts[:4])
    np.testing.assert_allclose(m1, m2, atol=1e-5)
    np.testing.assert_allclose(t1, t2, atol=1e-5)
    (tmp_path / "ev" / "norm_stats.npz").unlink()
    with pytest.raises(DualFlowError, match="norm_stats.npz"):
        MotionTextEvaluator.load(tmp_path / "ev")
    with pytest.raises(DualFlowError, match="features must be"):
        train_evaluator(np.zeros((4, 10, 262)), ["a"] * 4)
