"""`dualflow-bridge eval` and `eval train-evaluator` end to end on the synthetic dataset (tiny
settings), the ablation switches' row labels, the JSON output and one-line user errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from dualflow.checkpoint import save_checkpoint
from dualflow.datasets import load_dataset
from dualflow.model import DualFlow, DualFlowConfig
from dualflow.motion.normalization import NormStats
from dualflow.text import TEXT_ENCODER_ID
from ros_free_bridge.cli import main

DATA = ["--dataset", "synthetic", "--frames", "20", "--clips", "12"]


@pytest.fixture(scope="module")
def tiny_ckpt(tmp_path_factory):
    root = tmp_path_factory.mktemp("ckpt")
    feats = np.stack([s.features() for s in load_dataset("synthetic", split="train", n_clips=8, frames=20)])
    torch.manual_seed(0)
    model = DualFlow(DualFlowConfig.preset("tiny", music_dim=4, text_dim=384))
    return save_checkpoint(
        root / "final",
        model=model,
        stats=NormStats.from_features(feats),
        meta={"text_encoder": TEXT_ENCODER_ID, "music": "beats"},
    )


@pytest.mark.slow
def test_train_evaluator_then_eval_prints_table(tmp_path, tiny_ckpt, capsys):
    torch.set_num_threads(1)
    ev = tmp_path / "ev"
    assert (
        main(
            [
                "eval",
                "train-evaluator",
                *DATA,
                "--out",
                str(ev),
                "--steps",
                "3",
                "--width",
                "32",
                "--layers",
                "1",
                "--batch-size",
                "8",
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "evaluator written to" in out and (ev / "evaluator.safetensors").is_file()
    js = tmp_path / "res.json"
    assert (
        main(
            [
                "eval",
                *DATA,
                "--evaluator",
                str(ev),
                "--full",
                str(tiny_ckpt),
                "--no-sync",
                str(tiny_ckpt),
                "--look-ahead",
                f"0={tiny_ckpt}",
                "--steps",
                "1",
                "--quick",
                "--replications",
                "1",
                "--mm-repeats",
                "2",
                "--mm-samples",
                "2",
                "--json",
                str(js),
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    lines = out.splitlines()
    head = next(i for i, ln in enumerate(lines) if ln.startswith("Method"))
    assert "R@1" in lines[head] and "BAS" in lines[head]
    labels = [ln.split("  ")[0] for ln in lines[head + 2 :]]
    assert labels == [
        "Ground Truth",
        "[Interactive Task]",
        "DualFlow",
        "DualFlow (w/o L_sync)",
        "DualFlow (L=0)",
        "[Reactive Task]",
        "DualFlow",
        "DualFlow (w/o L_sync)",
        "DualFlow (L=0)",
    ]
    res = json.loads(js.read_text())
    assert abs(res["rows"]["Ground Truth"]["fid"]["mean"]) < 1e-6
    assert set(res["rows"]) == {
        "Ground Truth",
        "interactive/DualFlow",
        "interactive/DualFlow (w/o L_sync)",
        "interactive/DualFlow (L=0)",
        "reactive/DualFlow",
        "reactive/DualFlow (w/o L_sync)",
        "reactive/DualFlow (L=0)",
    }


def test_eval_user_errors(tmp_path, capsys):
    assert main(["eval", *DATA]) == 2
    assert "--evaluator" in capsys.readouterr().err
    assert main(["eval", *DATA, "--evaluator", str(tmp_path), "--look-ahead", "x=y"]) == 2
    assert "N=PATH" in capsys.readouterr().err
    assert main(["eval", *DATA, "--evaluator", str(tmp_path), "--full", str(tmp_path / "nope")]) == 2
    assert "checkpoint folder not found" in capsys.readouterr().err
    assert main(["eval", *DATA, "--evaluator", str(tmp_path)]) == 2
    assert "evaluator.safetensors" in capsys.readouterr().err
    assert main(["eval", "--dataset", "dd100", "--evaluator", str(tmp_path)]) == 2


def test_print_ablation_recipes(capsys):
    assert main(["eval", "--print-ablation-recipes"]) == 0
    out = capsys.readouterr().out
    assert "--no-triplet" in out and "--set loss_weights.triplet=0" in out and "--set model.look_ahead=N" in out
    assert "{v}" not in out and "--set retrieval.enabled=false" in out and "--set retrieval.k=N" in out
    # every recipe is the trainer's own ablation switch (one table, dualflow.evaluation.ablations)
    from dualflow.evaluation.ablations import ABLATION_SWITCHES

    for label, sets in ABLATION_SWITCHES.values():
        assert repr(label.format(v="N")) in out and " ".join(f"--set {s.format(v='N')}" for s in sets) in out
