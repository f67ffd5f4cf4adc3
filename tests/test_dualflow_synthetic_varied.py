"""The wider synthetic repertoire (dualflow.synthetic_varied) and fine-tuning from a checkpoint (issue 28)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dualflow.datasets.config import TrainingDataConfig
from dualflow.datasets.synthetic import build_split, is_varied_clip
from dualflow.datasets.training import widen_stats
from dualflow.errors import DualFlowError
from dualflow.evaluation.plausibility import distance, facing_error
from dualflow.motion.normalization import NormStats
from dualflow.motion.skeleton import bone_lengths
from dualflow.synthetic import RULES, make_duet
from dualflow.synthetic_varied import make_varied_leader


@pytest.mark.parametrize("rule", RULES)
def test_varied_duets_are_rigid_deterministic_and_new(rule):
    for seed in range(6):
        pair = make_duet(rule, 3.0, 30.0, seed, varied=True)
        for person in (pair.actor, pair.reactor):
            lengths = bone_lengths(person.positions)
            assert np.ptp(lengths, axis=0).max() < 1e-9
            assert person.positions[..., 2].min() > -0.01  # nobody sinks into the floor
        again = make_duet(rule, 3.0, 30.0, seed, varied=True)
        np.testing.assert_array_equal(pair.reactor.positions, again.reactor.positions)
        classic = make_duet(rule, 3.0, 30.0, seed)
        assert not np.allclose(classic.actor.positions, pair.actor.positions)
        assert pair.meta["varied"] is True and "varied" not in classic.meta


def test_personal_distance_follower_walks_up_keeps_its_distance_and_faces_the_leader():
    far = 0
    for seed in range(40):
        pair = make_duet("hand_hold", 6.0, 30.0, seed, varied=True)
        a, b = pair.actor.positions, pair.reactor.positions
        d = distance(b, a)
        far += d[0] > 1.6
        settled = d[90:]  # after 3 s the follower has closed (or opened) the gap
        assert 0.5 < settled.min() and settled.max() < 1.55, (seed, settled.min(), settled.max())
        assert facing_error(b[90:], a[90:]) < 35.0
    assert far >= 5  # some followers start far away and walk up


def test_leaders_walk_up_turn_and_hold_a_hand_out():
    seen = set()
    for seed in range(60):
        clip = make_varied_leader(4.0, 30.0, seed)
        p, slots = clip.body.positions, clip.slots
        seen.update(slots.values())
        if slots["travel"] == "walk_up":
            heading = np.array([np.cos(clip.heading0), np.sin(clip.heading0)])
            assert (p[-1, 0, :2] - p[0, 0, :2]) @ heading > 0.2 or clip.plan.centre(np.array([-1.0]))[0] @ heading < 0
        if slots["arms"] in ("reach_left", "reach_right"):
            wrist = 20 if slots["arms"] == "reach_left" else 21
            ahead = [
                (p[t, wrist, :2] - p[t, 0, :2]) @ np.array([np.cos(h), np.sin(h)])
                for t, h in enumerate(clip.plan.heading(clip.times))
            ]
            assert max(ahead) > 0.35  # the hand held out in front, at least at some moment
    assert {"walk_up", "turn_to", "reach_left", "reach_right"} <= seen


def test_mirrored_duets_swap_the_sides_in_the_text():
    mirrored = [make_duet("mirror", 2.0, 30.0, s, varied=True) for s in range(30)]
    flags = [p.meta["mirrored"] for p in mirrored]
    assert 5 < sum(flags) < 25
    for pair in mirrored:
        slots = pair.meta["slots"]
        if slots["arms"] == "left":
            side = "right" if pair.meta["mirrored"] else "left"
            assert f"waving the {side} arm" in pair.text


def test_varied_share_of_a_split_and_the_classic_split_is_unchanged():
    cfg = TrainingDataConfig(n_clips=400, varied=0.6)
    share = np.mean([is_varied_clip(cfg, i) for i in range(400)])
    assert 0.5 < share < 0.7
    assert not any(is_varied_clip(TrainingDataConfig(), i) for i in range(64))
    small = TrainingDataConfig(n_clips=8, val_clips=0, frames=20)
    split = build_split(small)
    want = make_duet(RULES[1], seconds=21 / 30, fps=30.0, seed=1)
    assert split.texts[1] == want.text
    with pytest.raises(DualFlowError, match="data.varied"):
        TrainingDataConfig(varied=1.5)


def test_widen_stats_changes_only_the_columns_the_old_data_held_still():
    rng = np.random.default_rng(0)
    old = NormStats(rng.normal(size=262), np.full(262, 0.5))
    std = np.full(262, 0.6)
    std[[3, 200]] = 5.0
    new = NormStats(rng.normal(size=262), std)
    merged = widen_stats(old, new)
    changed = np.flatnonzero(np.asarray(merged.std) != np.asarray(old.std))
    assert changed.tolist() == [3, 200]
    assert np.asarray(merged.mean)[3] == np.asarray(new.mean)[3]


def test_fine_tuning_starts_from_the_checkpoint(tmp_path):
    from dualflow.train import Trainer, load_train_config, train

    fast = [
        "preset=tiny",
        "data.n_clips=8",
        "data.val_clips=0",
        "data.frames=16",
        "batch_size=4",
        "threads=1",
        "progress=false",
        "ckpt_every=0",
        "warmup_steps=1",
        "ema_decay=0.9",
        "steps=2",
    ]
    base = train(load_train_config(None, fast + [f"out_dir={tmp_path / 'base'}"]))
    base_ck = base.final_checkpoint
    tuned = Trainer(
        load_train_config(None, fast + [f"out_dir={tmp_path / 'tuned'}", "data.varied=0.5", f"init_from={base_ck}"])
    )
    from dualflow.checkpoint import load_checkpoint

    ck = load_checkpoint(base_ck)
    for name, value in tuned.model.state_dict().items():
        torch.testing.assert_close(value, ck.state_dict[name].to(value.dtype))
    kept = np.asarray(tuned.stats.std) == np.asarray(ck.stats.std)
    assert kept.mean() > 0.9  # the checkpoint's scale, but for columns the new clips spread much wider
    with pytest.raises(DualFlowError, match="init_from"):
        Trainer(
            load_train_config(None, fast + [f"out_dir={tmp_path / 'other'}", "model.width=48", f"init_from={base_ck}"])
        )
