"""Retrieval-augmented training (dualflow.retrieval + the Trainer): databases built from the training
windows, top-k per cue with the query's own clip excluded (eq. 1; k = 5 interactive, 3 reactive),
z_R fed as Conditions.retrieval with the CFG drop, gradients into the retrieval encoder, and the
retrieval parts travelling with checkpoints (resume, export, ConditionBuilder, evaluation)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_datasets import make_interhuman

from dualflow import DualFlowError
from dualflow.checkpoint import load_checkpoint
from dualflow.conditioning import ConditionBuilder
from dualflow.datasets import load_dataset
from dualflow.evaluation.protocol import CheckpointGenerator, EvalSet
from dualflow.model import Conditions, DualFlow, DualFlowConfig
from dualflow.retrieval import (
    CUES,
    DB_FILE,
    ENCODER_FILE,
    NeighbourTable,
    RagConfig,
    RetrievalDatabase,
    drop_retrieval_tokens,
    load_rag,
)
from dualflow.train import Trainer, load_train_config

FAST = [
    "preset=tiny",
    "data.n_clips=12",
    "data.val_clips=2",
    "data.frames=12",
    "batch_size=4",
    "threads=1",
    "progress=false",
    "log_every=1",
    "ckpt_every=2",
    "lr=1e-3",
    "warmup_steps=1",
    "ema_decay=0.9",
    "music=beats",
    "model.music_dim=4",
    "retrieval.enabled=true",
]


def rag_config(tmp_path, *extra: str):
    return load_train_config(None, FAST + [f"out_dir={tmp_path}"] + list(extra))


def test_config_section_and_depths():
    cfg = RagConfig()
    assert not cfg.enabled and (cfg.depth("interactive"), cfg.depth("reactive")) == (5, 3)
    assert RagConfig(k=7).depth("reactive") == 7
    with pytest.raises(DualFlowError, match=r"train config 'retrieval': unknown field\(s\) \['kk'\]"):
        load_train_config(None, ["retrieval.kk=3"])
    with pytest.raises(DualFlowError, match="retrieval.cues"):
        load_train_config(None, ["retrieval.cues=[smell]"])


def test_training_neighbours_never_include_the_query_window(tmp_path):
    trainer = Trainer(rag_config(tmp_path))
    table, db = trainer.retriever.table, trainer.retriever.db
    n = len(trainer.train_set)
    assert len(db) == n and set(db.cues) == set(CUES)  # spatial, body, rhythm texts + the beat-track music cue
    for cue, idx in table.indices.items():
        assert idx.shape == (n, 5), cue
        assert not (idx == np.arange(n)[:, None]).any(), cue
    # the spatial description names the follower rule (mirror, hand-hold, circling, beside), so the
    # spatial cue's best match mostly follows the query's rule (chance: 1 in 4)
    rule = trainer.train_set.rule.numpy()
    same = (rule[table.indices["spatial"][:, 0]] == rule).mean()
    assert same >= 0.75, same
    # depth by task: 5 per cue interactive, 3 reactive
    idx, cue_ids = trainer.retriever.retrieved(np.arange(3), "reactive")
    assert idx.shape == (3, 12) and list(cue_ids) == [c for c in range(4) for _ in range(3)]
    assert trainer.retriever.retrieved(np.arange(3), "interactive")[0].shape == (3, 20)


def test_windows_of_the_query_clip_are_all_excluded(tmp_path):
    """A windowed dataset: several windows per clip share its text, and none of them is retrieved."""
    make_interhuman(tmp_path / "ih", n=4)
    trainer = Trainer(
        load_train_config(
            None,
            FAST[:-4]
            + [
                "data.dataset=interhuman",
                f"data.root={tmp_path / 'ih'}",
                "data.frames=8",
                "data.stride=4",
                "retrieval.enabled=true",
                f"out_dir={tmp_path / 'r'}",
            ],
        )
    )
    groups = trainer.train_set.groups
    assert len(groups) > len(set(groups.tolist())) >= 2  # several windows per clip
    for cue, idx in trainer.retriever.table.indices.items():
        assert not (groups[idx] == groups[:, None]).any(), cue
    # with two training clips, each query sees only the other clip's windows
    assert trainer.retriever.table.depth == min(5, int(np.bincount(groups).min()))


def test_neighbour_table_scores_by_eq1_and_excludes_groups():
    rng = np.random.default_rng(0)
    emb = rng.normal(size=(6, 8)).astype(np.float32)
    emb[1] = emb[0]  # entry 1 duplicates entry 0 (same clip) ...
    emb[2] = emb[0] + 0.01  # ... entry 2 is a near copy from another clip
    db = RetrievalDatabase(
        np.zeros((6, 4, 2, 262), np.float32), np.full(6, 4), {"body": emb}, [f"c{i}" for i in range(6)]
    )
    groups = np.array([0, 0, 1, 2, 3, 4])
    t = NeighbourTable.compute(
        db, {"body": db.embeddings["body"]}, db.lengths, 3, query_groups=groups, db_groups=groups
    )
    assert t.indices["body"][0, 0] == 2 and 1 not in t.indices["body"][0]
    with pytest.raises(DualFlowError, match="one clip"):
        NeighbourTable.compute(
            db, {"body": db.embeddings["body"][:1]}, 4, 2, query_groups=np.zeros(1, int), db_groups=np.zeros(6, int)
        )


def test_gradients_reach_the_retrieval_encoder(tmp_path):
    trainer = Trainer(rag_config(tmp_path, "cfg_drop=false", "ema_decay=0"))
    start = {k: v.clone() for k, v in trainer.retrieval_encoder.state_dict().items()}
    for _ in range(3):  # the output linears start at zero, so the first step's upstream gradient is zero
        trainer.train_step()
    grads = {n: p.grad for n, p in trainer.retrieval_encoder.named_parameters()}
    assert all(g is not None for g in grads.values())
    assert sum(float(g.norm()) for g in grads.values()) > 0
    assert float(grads["proj.weight"].norm()) > 0  # through the transformer down to the motion projection
    moved = [k for k, v in trainer.retrieval_encoder.state_dict().items() if not torch.equal(v, start[k])]
    assert "proj.weight" in moved
    # the optimiser holds the encoder's parameters
    held = {id(p) for g in trainer.optimizer.param_groups for p in g["params"]}
    assert all(id(p) in held for p in trainer.retrieval_encoder.parameters())


def test_cfg_drop_of_all_cues_equals_absent_retrieval():
    torch.manual_seed(0)
    model = DualFlow(DualFlowConfig.preset("tiny", music_dim=4)).eval()
    with torch.no_grad():
        for p in model.parameters():  # leave zero-initialised outputs non-zero
            p.add_(0.02 * torch.randn_like(p))
    x = torch.randn(2, 6, 262)
    z = torch.randn(2, 8, model.config.width)
    cue_ids = np.array([0, 1, 2, 3])  # one retrieved clip per cue -> 8 tokens
    yes, no = torch.ones(2, dtype=torch.bool), torch.zeros(2, dtype=torch.bool)
    null = model.null_retrieval
    both = drop_retrieval_tokens(z, cue_ids, null, yes, yes)
    with torch.no_grad():
        v_drop = model(x, x, 0.5, Conditions(retrieval=both), mode="interactive")[1]
        v_none = model(x, x, 0.5, Conditions(), mode="interactive")[1]
        v_keep = model(x, x, 0.5, Conditions(retrieval=z), mode="interactive")[1]
    torch.testing.assert_close(v_drop, v_none, atol=1e-5, rtol=1e-5)
    assert not torch.allclose(v_keep, v_none, atol=1e-4)
    text_only = drop_retrieval_tokens(z, cue_ids, null, yes, no)
    assert torch.equal(text_only[:, 6:], z[:, 6:])  # the music-cue tokens stay
    assert torch.equal(text_only[:, :6], null.expand(2, 6, -1))
    assert drop_retrieval_tokens(z, cue_ids, null, no, no) is z


@pytest.mark.slow
def test_rag_checkpoint_resumes_exports_and_generates(tmp_path):
    straight = Trainer(rag_config(tmp_path / "a", "steps=4"))
    straight.run()
    first = Trainer(rag_config(tmp_path / "b", "steps=2"))
    first.run()
    resumed = Trainer(rag_config(tmp_path / "b", "steps=4"), resume=True)
    resumed.run()
    for k, v in straight.retrieval_encoder.state_dict().items():
        torch.testing.assert_close(v, resumed.retrieval_encoder.state_dict()[k], rtol=0, atol=0, msg=k)
    for k, v in straight.model.state_dict().items():
        torch.testing.assert_close(v, resumed.model.state_dict()[k], rtol=0, atol=0, msg=k)
    final = tmp_path / "a" / "final"
    assert (final / ENCODER_FILE).is_file() and (final / DB_FILE).is_file()
    ckpt = load_checkpoint(final)
    rag = load_rag(ckpt)
    assert rag.config.enabled and len(rag.db) == len(straight.train_set)
    ema = straight.retrieval_ema.module.state_dict()
    for k, v in rag.encoder.state_dict().items():  # the export holds the EMA encoder
        torch.testing.assert_close(v, ema[k], rtol=0, atol=0, msg=k)
    builder = ConditionBuilder.from_checkpoint(ckpt)
    inputs = builder.build(text="two people mirror each other, moving fast", n_frames=12)
    assert inputs.cond.retrieval.shape == (1, 2 * 3 * 5, ckpt.config.width) and len(inputs.retrieved) == 15
    assert set(inputs.retrieved) <= set(rag.db.ids)
    # the evaluation's generator retrieves for every test window too (depth by task)
    data = EvalSet.from_duet_set(load_dataset("synthetic", None, "test", n_clips=3, frames=12), 12)
    gen = CheckpointGenerator(final, data, mode="reactive", steps=2)
    assert gen.retriever.retrieved(np.arange(3), "reactive")[0].shape == (3, 4 * 3)
    out = gen(np.arange(3), 0)
    assert out.shape == (3, 12, 2, 262) and np.isfinite(out).all()
    # a checkpoint without retrieval has no RAG parts
    plain = Trainer(load_train_config(None, FAST[:-1] + ["steps=1", f"out_dir={tmp_path / 'c'}"]))
    plain.run()
    assert load_rag(load_checkpoint(tmp_path / "c" / "final")) is None
    (final / ENCODER_FILE).unlink()
    with pytest.raises(DualFlowError, match="lacks retrieval_encoder.safetensors"):
        load_rag(load_checkpoint(final))


def test_encoder_frame_stride_reads_every_sth_frame():
    torch.manual_seed(0)
    enc = RagConfig(frame_stride=4, dropout=0.0).encoder(32, 2).eval()
    motions = torch.randn(2, 3, 12, 2, 262)
    lengths = torch.tensor([[12, 5, 9], [1, 12, 8]])
    cue_ids = torch.tensor([0, 1, 3])
    z = enc(motions, lengths, cue_ids)
    off = motions.clone()
    off[:, :, 1::4] += 5.0  # frames the stride skips
    torch.testing.assert_close(enc(off, lengths, cue_ids), z)
    on = motions.clone()
    on[0, 0, 8] += 5.0  # a frame it reads (clip 0 of sample 0 is 12 frames long)
    assert not torch.allclose(enc(on, lengths, cue_ids)[0, :2], z[0, :2])
    late = motions.clone()
    late[0, 1, 8] += 5.0  # frame 8 of a 5-frame clip is padding, read or not
    torch.testing.assert_close(enc(late, lengths, cue_ids), z)
