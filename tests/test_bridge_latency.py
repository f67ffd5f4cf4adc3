"""What sets the partner's delay in the bridge: which actor frame completes partner frame i,
the provisional newest feature row, incremental windows in the generator."""

from __future__ import annotations

import numpy as np
import pytest

from dualflow.motion import Motion
from dualflow.motion.features import canonical_frame, encode_person
from dualflow.streaming import StreamConfig
from dualflow.synthetic import make_leader
from ros_free_bridge.partner.reactor import ReactorStage


def _emitted_at(stage, leader):
    """{partner frame index: actor frame whose push emitted it}."""
    at = {}
    for k, p in enumerate(leader.positions):
        for f in stage.push(p, float(k), k):
            at[f.index] = k
    return at


@pytest.mark.parametrize("predict_next,ahead", [(True, 0), (False, 1)])
def test_partner_frame_i_is_emitted_when_actor_frame_i_plus_L_arrives(tiny_checkpoint, predict_next, ahead):
    stage = ReactorStage(30.0, tiny_checkpoint, StreamConfig(window=16, steps=2, hop=1), predict_next=predict_next)
    L = stage.look_ahead
    assert stage.frames_ahead == L + ahead and stage.delay_frames == L + ahead
    leader = make_leader(1.5, 30.0, seed=4)
    at = _emitted_at(stage, leader)
    assert at and all(k == i + L + ahead for i, k in at.items())
    n_left = leader.n_frames - len(at)
    rest = stage.flush(0.0, leader.n_frames - 1)
    # predicted: every actor frame gets a partner frame; exact: the last frame has no feature row
    assert len(rest) == n_left - ahead and rest[-1].index == leader.n_frames - 1 - ahead


def test_the_provisional_row_is_revised_with_the_true_next_frame(tiny_checkpoint):
    stage = ReactorStage(30.0, tiny_checkpoint, StreamConfig(window=16, steps=2, hop=1))
    leader = make_leader(1.0, 30.0, seed=5)
    for k in range(20):
        stage.push(leader.positions[k], float(k), k)
    exact = stage.stats.normalize(
        encode_person(Motion(leader.positions[:20], 30.0), canonical_frame(Motion(leader.positions[:1], 30.0)))
    )
    rows = stage.streamer._actor.numpy()
    assert rows.shape[0] == 20  # 19 exact rows and the newest frame's provisional one
    np.testing.assert_allclose(rows[:19], exact, atol=1e-5)
    # the provisional row: the newest frame at the velocity of the last step (constant-velocity guess)
    p = leader.positions
    guess = stage.stats.normalize(
        encode_person(Motion(np.stack([p[19], 2 * p[19] - p[18]]), 30.0), canonical_frame(Motion(p[:1], 30.0)))
    )
    np.testing.assert_allclose(rows[19], guess[0], atol=1e-5)


def test_incremental_generation_in_the_bridge_stage(tiny_checkpoint):
    """The generator's default streaming (incremental windows, idle-time catch-up) gives a
    whole partner timeline, finite, and idle work runs out."""
    stage = ReactorStage(30.0, tiny_checkpoint, StreamConfig(window=16, steps=2, hop=1, incremental=True))
    leader = make_leader(2.0, 30.0, seed=6)
    out = []
    for k, p in enumerate(leader.positions):
        out += stage.push(p, float(k), k)
        stage.prepare(1)
    out += stage.flush(0.0, leader.n_frames - 1)
    assert [f.index for f in out] == list(range(leader.n_frames))
    assert all(np.all(np.isfinite(f.positions)) for f in out)
    while stage.has_catch_up:
        stage.prepare(1)
