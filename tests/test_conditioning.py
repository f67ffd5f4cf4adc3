"""The generator accepts any subset of (actor motion, text, music file): every subset builds the
right Conditions / mode / length and generates a decoded duet; mismatches fail clearly."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch

from dualflow.conditioning import ConditionBuilder, text_encoder_for
from dualflow.duet_generator import DuetGenerator
from dualflow.errors import DualFlowError
from dualflow.model import Conditions, DualFlow, DualFlowConfig
from dualflow.motion.features import encode_pair
from dualflow.motion.normalization import NormStats
from dualflow.synthetic import make_duet

FPS = 30.0


@pytest.fixture(scope="module")
def setup():
    from dualflow.text import MiniLMEncoder

    pairs = [make_duet(r, seconds=41 / FPS, fps=FPS, seed=7 + i) for i, r in enumerate(("mirror", "follow", "orbit"))]
    feats = np.stack([encode_pair(p)[0] for p in pairs])
    stats = NormStats.from_features(feats)
    torch.manual_seed(0)
    cfg = DualFlowConfig.preset("tiny", text_dim=384, music_dim=4)
    model = DualFlow(cfg).eval()
    for p in model.parameters():  # zero-initialised layers (outputs, adaLN) would hide the conditions
        if p.dim() > 1 and not p.detach().abs().sum():
            torch.nn.init.normal_(p, std=0.02)
    builder = ConditionBuilder(cfg, stats, text_encoder=MiniLMEncoder(), music_kind="beats4", fps=FPS)
    music60 = make_duet("mirror", seconds=61 / FPS, fps=FPS, seed=99).meta["beats"][:60]
    return {
        "music60": music60,
        "pairs": pairs,
        "feats": feats,
        "stats": stats,
        "cfg": cfg,
        "model": model,
        "builder": builder,
    }


SUBSETS = [s for n in range(4) for s in itertools.combinations(("actor", "text", "music"), n)]


@pytest.mark.parametrize("subset", SUBSETS, ids=lambda s: "+".join(s) or "nothing")
def test_every_subset_builds_and_generates(setup, subset):
    pair = setup["pairs"][0]
    given = {
        "actor": pair.actor if "actor" in subset else None,
        "text": pair.text if "text" in subset else None,
        "music": setup["music60"] if "music" in subset else None,
    }
    inputs = setup["builder"].build(**given)
    assert inputs.used == subset
    assert inputs.mode == ("reactive" if "actor" in subset else "interactive")
    expected_t = 40 if "actor" in subset else (60 if "music" in subset else 120)
    assert inputs.n_frames == expected_t
    assert (inputs.cond.text is None) == ("text" not in subset)
    assert (inputs.cond.music is None) == ("music" not in subset)
    if "text" in subset:
        assert inputs.cond.text.shape == (1, 384)
    if "music" in subset:
        assert inputs.cond.music.shape == (1, expected_t, 4)
        np.testing.assert_array_equal(inputs.cond.music[0].numpy(), setup["music60"][:expected_t])
    if "actor" in subset:
        np.testing.assert_allclose(
            inputs.actor[0].numpy(), setup["stats"].normalize(setup["feats"][0][:, 0]), atol=1e-5
        )

    duet, _ = DuetGenerator(setup["model"], setup["builder"]).generate(**given, steps=2, seed=1)
    assert duet.n_frames == expected_t + 1
    assert np.all(np.isfinite(duet.reactor.positions)) and np.all(np.isfinite(duet.actor.positions))
    if "actor" in subset:
        np.testing.assert_array_equal(duet.actor.positions, pair.actor.positions)


def test_absent_inputs_are_the_learned_null(setup):
    model, builder = setup["model"], setup["builder"]
    x = torch.randn(1, 120, 262)
    empty = builder.build()
    assert empty.cond.text is None and empty.cond.music is None and empty.cond.retrieval is None
    v_none = model(x, x, 0.3, Conditions())[1]
    torch.testing.assert_close(model(x, x, 0.3, empty.cond)[1], v_none)
    with_text = builder.build(text="the partner mirrors the leader")
    assert not torch.allclose(model(x, x, 0.3, with_text.cond)[1], v_none)


def test_the_reactor_lands_in_the_actors_world(setup):
    pair = setup["pairs"][1]
    moved = pair.actor.translated([3.0, -2.0, 0.0])
    gen = DuetGenerator(setup["model"], setup["builder"])
    a, _ = gen.generate(actor=pair.actor, steps=2, seed=4)
    b, _ = gen.generate(actor=moved, steps=2, seed=4)
    np.testing.assert_allclose(
        b.reactor.positions - a.reactor.positions,
        np.broadcast_to([3.0, -2.0, 0.0], a.reactor.positions.shape),
        atol=1e-6,
    )


@pytest.mark.slow  # librosa's beat tracker compiles (numba) on first use: ~10-20 s per process
def test_music_file_and_resampled_actor(setup, tmp_path):
    import librosa
    import soundfile as sf

    from dualflow.music import analysis_rate

    sr = analysis_rate(FPS)
    path = tmp_path / "clicks.wav"
    sf.write(path, librosa.clicks(times=np.arange(0.25, 3.0, 0.5), sr=sr, length=3 * sr), sr)
    actor60 = setup["pairs"][2].actor.resample(60.0)
    inputs = setup["builder"].build(actor=actor60, music=path)
    assert inputs.n_frames == setup["pairs"][2].actor.n_frames - 1  # resampled to the model's 30 fps
    beats = inputs.cond.music[0].numpy()
    assert beats.shape == (inputs.n_frames, 4) and beats[:, 0].sum() >= 2


def test_mismatches_fail_clearly(setup):
    from dualflow.text import MiniLMEncoder

    cfg, stats = setup["cfg"], setup["stats"]
    with pytest.raises(DualFlowError, match="text_dim is 32"):
        ConditionBuilder(
            DualFlowConfig.preset("tiny", text_dim=32, music_dim=4),
            stats,
            text_encoder=MiniLMEncoder(),
            music_kind="beats4",
        )
    with pytest.raises(DualFlowError, match="music_dim is 4"):
        ConditionBuilder(cfg, stats, music_kind="edge35")
    with pytest.raises(DualFlowError, match="leave n_frames out"):
        setup["builder"].build(actor=setup["pairs"][0].actor, n_frames=10)
    with pytest.raises(DualFlowError, match="non-empty"):
        setup["builder"].build(text="  ")
    with pytest.raises(DualFlowError, match=r"\(T, 4\)"):
        setup["builder"].build(music=np.zeros((50, 35)))
    with pytest.raises(DualFlowError, match="Motion"):
        setup["builder"].build(actor=np.zeros((10, 22, 3)))
    deaf = ConditionBuilder(cfg, stats, text_encoder=None, music_kind=None)
    inputs = deaf.build(text="hello", music=np.zeros((50, 4)))
    assert inputs.used == () and len(inputs.notes) == 2 and inputs.cond.text is None and inputs.cond.music is None
    with pytest.raises(DualFlowError, match="ClipTextEncoder"):
        text_encoder_for("open_clip/ViT-L-14/x.pt", 768)
    with pytest.raises(DualFlowError, match="both retrieval_db and retrieval_encoder"):
        ConditionBuilder(cfg, stats, music_kind=None, retrieval_db=object())


def test_retrieval_tokens_from_text_and_music(setup):
    from dualflow.retrieval import RetrievalDatabase, RetrievalEncoder

    pairs, feats, cfg = setup["pairs"], setup["feats"], setup["cfg"]
    text_encoder = setup["builder"].text_encoder
    db = RetrievalDatabase.build(
        feats, [40] * 3, [p.text for p in pairs], [p.meta["beats"] for p in pairs], text_encoder=text_encoder
    )
    enc = RetrievalEncoder(cfg.width, n_layers=1, n_heads=2, dropout=0.0).eval()
    builder = ConditionBuilder(
        cfg, setup["stats"], text_encoder=text_encoder, music_kind="beats4", retrieval_db=db, retrieval_encoder=enc
    )
    inter = builder.build(text=pairs[0].text, music=pairs[0].meta["beats"][:40])
    # 4 cues x min(k=5, 3 entries) clips x 2 persons
    assert inter.cond.retrieval.shape == (1, 4 * 3 * 2, cfg.width) and len(inter.retrieved) == 12
    react = builder.build(actor=pairs[1].actor, text=pairs[1].text)
    assert react.cond.retrieval.shape == (1, 3 * 3 * 2, cfg.width)  # text cues only, k = 3
    assert builder.build(actor=pairs[1].actor).cond.retrieval is None  # nothing to query with
    duet, _ = DuetGenerator(setup["model"], builder).generate(actor=pairs[1].actor, text=pairs[1].text, steps=2)
    assert np.all(np.isfinite(duet.reactor.positions))


def test_builder_from_a_checkpoint(setup, tmp_path):
    ckpt_mod = pytest.importorskip("dualflow.checkpoint", reason="dualflow.checkpoint not in this tree yet")
    path = ckpt_mod.save_checkpoint(
        tmp_path / "ck",
        model=setup["model"],
        stats=setup["stats"],
        meta={"text_encoder": "all-MiniLM-L6-v2/meanpool-l2", "music": "beats", "data": {"fps": 30.0}},
    )
    gen = DuetGenerator.from_checkpoint(path)
    assert gen.builder.music_kind == "beats4" and gen.builder.text_encoder.dim == 384
    duet, inputs = gen.generate(text="they hold hands", n_frames=20, steps=2)
    assert duet.n_frames == 21 and inputs.used == ("text",)
