"""The paper's ablation switches as training overrides: each one changes exactly its own field
of the full model's config, and the Jukebox switch says why it cannot run on the synthetic duets."""

from __future__ import annotations

import pytest

from dualflow import DualFlowError
from dualflow.evaluation.ablations import ABLATION_SWITCHES, ablation_overrides
from dualflow.train import Trainer, load_train_config

BASE = [
    "preset=tiny",
    "music=beats",
    "model.music_dim=4",
    "data.n_clips=4",
    "data.val_clips=0",
    "data.frames=12",
    "threads=1",
    "progress=false",
    "steps=1",
]

CHANGES = {
    "full": {},
    "no_rag": {("retrieval", "enabled"): False},
    "no_triplet": {("loss_weights", "triplet"): 0},
    "no_sync": {("loss_weights", "sync"): 0},
    "spectral": {("music",): "edge35", ("model", "music_dim"): 35},
    "jukebox": {("music",): "jukebox", ("model", "music_dim"): 4800},
    "look_ahead": {("model", "look_ahead"): 20},
    "retrieval_k": {("retrieval", "k"): 7},
}


def flat(d: dict, prefix=()) -> dict:
    out = {}
    for k, v in d.items():
        out.update(flat(v, prefix + (k,)) if isinstance(v, dict) else {prefix + (k,): v})
    return out


@pytest.mark.parametrize("switch", list(ABLATION_SWITCHES))
def test_each_switch_changes_only_its_field(switch):
    full = flat(load_train_config(None, BASE + ablation_overrides("full")[1]).to_dict())
    value = 20 if switch == "look_ahead" else 7 if switch == "retrieval_k" else None
    label, sets = ablation_overrides(switch, value)
    cfg = load_train_config(None, BASE + sets)
    got = flat(cfg.to_dict())
    diff = {k: got.get(k) for k in set(full) | set(got) if full.get(k) != got.get(k)}
    assert diff == CHANGES[switch]
    assert full[("retrieval", "enabled")] is True and label.startswith("DualFlow")
    if value is not None:
        assert str(value) in label


def test_switch_errors_and_jukebox_on_synthetic(tmp_path):
    with pytest.raises(DualFlowError, match="needs a value"):
        ablation_overrides("look_ahead")
    with pytest.raises(DualFlowError, match="unknown ablation switch"):
        ablation_overrides("no_music")
    cfg = load_train_config(None, BASE + ablation_overrides("jukebox")[1] + [f"out_dir={tmp_path}"])
    with pytest.raises(DualFlowError, match="synthetic duets have no audio to run Jukebox on"):
        Trainer(cfg)
