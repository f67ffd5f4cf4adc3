"""Training on any dataset by name (data.dataset / root / splits): a few real optimisation steps
through the real Trainer on the fake trees of each real layout (InterHuman, DD100, MDD, BVH
pairs), the windows it trains on, and one clear error naming the field for a wrong name or root."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from test_datasets import make_dd100, make_interhuman, make_mdd

from dualflow import DualFlowError
from dualflow.checkpoint import load_checkpoint
from dualflow.datasets import load_dataset
from dualflow.datasets.synthetic import click_track_music
from dualflow.datasets.windows import window_split
from dualflow.evaluation.protocol import CheckpointGenerator, EvalSet
from dualflow.motion.io import write_bvh_motion
from dualflow.synthetic import make_duet
from dualflow.train import Trainer, load_train_config

FRAMES = 12
FAST = [
    "preset=tiny",
    f"data.frames={FRAMES}",
    "batch_size=2",
    "threads=1",
    "progress=false",
    "log_every=1",
    "ckpt_every=0",
    "lr=1e-3",
    "warmup_steps=1",
    "ema_decay=0.9",
    "steps=2",
]


def make_bvh_pairs(root: Path) -> None:
    for i, rule in enumerate(("mirror", "follow")):
        d = make_duet(rule, seconds=1.0, fps=60.0, seed=40 + i)
        write_bvh_motion(d.actor, root / f"take{i}_actor.bvh")
        write_bvh_motion(d.reactor, root / f"take{i}_reactor.bvh")
        (root / f"take{i}.txt").write_text(f"two people dance, rule {rule}\n")


LAYOUTS = {
    "interhuman": (make_interhuman, ["data.splits=[train, test]"], ("train", "test")),
    "interhuman_as": (make_interhuman, [], ("train", None)),
    "dd100": (make_dd100, ["data.splits=[train, test]", "music=duolando54", "model.music_dim=54"], ("train", "test")),
    "mdd": (make_mdd, ["data.options={music: jukebox}", "music=jukebox", "model.music_dim=4800"], ("train", None)),
    "bvh_pairs": (make_bvh_pairs, [], ("all", None)),
}


@pytest.mark.slow
@pytest.mark.parametrize("name", list(LAYOUTS))
def test_trainer_trains_on_each_real_layout(tmp_path, name):
    make, extra, (train_split, val_split) = LAYOUTS[name]
    root = tmp_path / "data"
    root.mkdir()
    make(root)
    cfg = load_train_config(
        None, FAST + [f"data.dataset={name}", f"data.root={root}", f"out_dir={tmp_path / 'run'}"] + extra
    )
    trainer = Trainer(cfg)
    # the windows it trains on are the loader's clips cut into FRAMES-row windows
    options = {"music": "jukebox"} if name == "mdd" else {}
    expect = window_split(load_dataset(name, root, train_split, **options), FRAMES)
    assert len(trainer.train_set) == len(expect.features) >= 2
    want = trainer.stats.normalize(expect.features[:, :, 1].astype(np.float64)).astype(np.float32)
    torch.testing.assert_close(trainer.train_set.reactor, torch.from_numpy(want))
    assert trainer.train_set.texts == expect.texts
    assert (trainer.val_set is None) == (val_split is None)
    if "music=duolando54" in extra or "music=jukebox" in extra:
        kind = "duolando54" if name == "dd100" else "jukebox"
        assert trainer.train_set.music_kind == kind
        torch.testing.assert_close(trainer.train_set.music, torch.from_numpy(expect.music))
    before = {k: v.clone() for k, v in trainer.model.state_dict().items()}
    result = trainer.run()
    assert result.step == 2 and np.isfinite(result.loss)
    assert any(not torch.equal(before[k], v) for k, v in trainer.model.state_dict().items())
    meta = load_checkpoint(tmp_path / "run" / "final").meta
    assert meta["data"]["dataset"] == name and meta["data"]["root"] == str(root) and meta["synthetic"] is False


@pytest.mark.parametrize(
    "overrides,match",
    [
        (["data.dataset=interhumann", "data.root=ROOT"], r"data\.dataset: unknown dataset 'interhumann'"),
        (["data.dataset=dd100"], r"data\.root: dataset 'dd100' needs its folder"),
        (["data.dataset=dd100", "data.root=ROOT/nowhere"], r"data\.root: .*nowhere is not a folder"),
        (["data.root=ROOT"], r"data\.dataset 'synthetic' is generated"),
        (["data.dataset=dd100", "data.root=ROOT", "data.splits=[a, b, c]"], r"data\.splits must be"),
    ],
)
def test_wrong_dataset_or_root_names_the_field(tmp_path, overrides, match):
    overrides = [o.replace("ROOT", str(tmp_path)) for o in overrides]
    with pytest.raises(DualFlowError, match=match):
        load_train_config(None, FAST + overrides)


def test_a_root_in_the_wrong_layout_names_the_missing_folder(tmp_path):
    cfg = load_train_config(None, FAST + ["data.dataset=dd100", f"data.root={tmp_path}", f"out_dir={tmp_path / 'r'}"])
    with pytest.raises(DualFlowError, match=r"motion/pos3d/train"):
        Trainer(cfg)


def test_music_the_data_lacks_is_a_clear_error(tmp_path):
    make_interhuman(tmp_path)
    cfg = load_train_config(
        None,
        FAST
        + [
            "data.dataset=interhuman",
            f"data.root={tmp_path}",
            "music=edge35",
            "model.music_dim=35",
            f"out_dir={tmp_path / 'r'}",
        ],
    )
    with pytest.raises(DualFlowError, match="music 'edge35': this training data has only the beat track"):
        Trainer(cfg)
    with pytest.raises(DualFlowError, match=r"music 'duolando54' gives 54-d features; set model.music_dim: 54"):
        load_train_config(None, FAST + ["music=duolando54"])  # the presets' music_dim is 35
    jukebox = load_train_config(None, FAST + ["music=jukebox", "model.music_dim=4800", f"out_dir={tmp_path / 'j'}"])
    with pytest.raises(DualFlowError, match="synthetic duets have no audio to run Jukebox on"):
        Trainer(jukebox)


@pytest.mark.slow
def test_spectral_music_on_synthetic_duets_is_a_click_track(tmp_path):
    """music: edge35 on the synthetic duets: the EDGE features of a click track at the clip's beats."""
    cfg = load_train_config(
        None, FAST + ["data.n_clips=3", "data.val_clips=0", "music=edge35", "model.music_dim=35", f"out_dir={tmp_path}"]
    )
    trainer = Trainer(cfg)
    music = trainer.train_set.music.numpy()
    assert music.shape == (3, FRAMES, 35) and trainer.train_set.music_kind == "edge35"
    # the onset envelope (column 0) peaks within a frame or two of every beat impulse of the track
    for m, beats in zip(music, trainer.train_set.beats.numpy()):
        for b in np.flatnonzero(beats[:, 0] > 0.5):
            if 1 <= b < FRAMES - 2:
                assert m[b : b + 3, 0].max() > 2 * np.median(m[:, 0]) + 1e-6
    assert np.isfinite(trainer.run().loss)
    # the evaluation feeds such a checkpoint the same click-track features of the test windows
    data = EvalSet.from_duet_set(load_dataset("synthetic", None, "test", n_clips=2, frames=FRAMES), FRAMES)
    gen = CheckpointGenerator(tmp_path / "final", data, mode="interactive", steps=2)
    assert tuple(gen.music.shape) == (2, FRAMES, 35) and data.music_kind == "edge35"
    np.testing.assert_allclose(gen.music.numpy()[0], click_track_music(data.beats[0], "edge35"), atol=1e-6)
    assert np.isfinite(gen(np.arange(2), 0)).all()
    with pytest.raises(DualFlowError, match="trained with 'jukebox' music but this evaluation data has edge35"):
        data.music_for("jukebox")
