"""The trainer: config files, warm-up, checkpoints without pickle, resume, EMA, CSV log, CLI."""

from __future__ import annotations

import csv
import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from dualflow import DualFlowError
from dualflow.checkpoint import load_checkpoint, load_model, save_checkpoint
from dualflow.datasets.config import TrainingDataConfig
from dualflow.datasets.synthetic import build_split
from dualflow.datasets.training import make_datasets
from dualflow.model import DualFlow, DualFlowConfig
from dualflow.text import TEXT_ENCODER_ID, template_text_embedding
from dualflow.train import TrainConfig, Trainer, load_train_config, train, warmup_lr

FAST = [
    "preset=tiny",
    "data.n_clips=8",
    "data.val_clips=2",
    "data.frames=16",
    "batch_size=4",
    "threads=1",
    "progress=false",
    "log_every=1",
    "ckpt_every=3",
    "lr=1e-3",
    "warmup_steps=4",
    "ema_decay=0.9",
]


def fast_config(tmp_path: Path, *extra: str) -> TrainConfig:
    return load_train_config(None, FAST + [f"out_dir={tmp_path}"] + list(extra))


def state_of(model: torch.nn.Module) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in model.state_dict().items()}


# -- configuration ------------------------------------------------------------------------


def test_config_file_and_overrides(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text(
        "preset: tiny\nlr: 3e-4\nsteps: 7\nmodel: {width: 48}\ndata: {n_clips: 5, rules: [mirror, orbit]}\n"
    )
    cfg = load_train_config(path, ["steps=9", "data.frames=20", "model.n_heads=4"])
    assert cfg.lr == pytest.approx(3e-4) and isinstance(cfg.lr, float)  # YAML reads 3e-4 as a string
    assert cfg.steps == 9 and cfg.model == {"width": 48, "n_heads": 4}
    assert cfg.model_config().width == 48 and cfg.model_config().n_blocks == DualFlowConfig.preset("tiny").n_blocks
    assert cfg.data_config() == TrainingDataConfig(n_clips=5, frames=20, rules=("mirror", "orbit"))
    # the paper's optimiser settings are the defaults
    d = TrainConfig()
    assert (d.lr, d.weight_decay, d.warmup_steps) == (2e-4, 2e-5, 1000)


@pytest.mark.parametrize(
    "text,match",
    [
        ("stepz: 3\n", r"c\.yaml: unknown training field\(s\) \['stepz'\]"),
        ("lr: fast\n", r"c\.yaml: field 'lr' must be float"),
        ("steps: 2.5\n", r"field 'steps' must be int"),
        ("warmup_steps: -1\n", "warmup_steps must be >= 0"),
        ("data_workers: -2\n", "data_workers must be >= 0"),
        ("data: {rules: [tango]}\n", "unknown or empty rules"),
        ("model: {widht: 3}\n", "bad 'model' overrides"),
        ("uncued_rules: orbit\n", r"uncued_rules must be a list of rules"),
        ("data: {rules: [mirror]}\nuncued_rules: [orbit]\n", r"uncued_rules \['orbit'\] are not among data.rules"),
        ("data: {dataset: dd100, root: .}\nuncued_rules: [orbit]\n", "uncued_rules picks synthetic follower rules"),
        ("- a\n- b\n", "must be a mapping"),
    ],
)
def test_bad_config_names_the_file_and_field(tmp_path, text, match):
    path = tmp_path / "c.yaml"
    path.write_text(text)
    with pytest.raises(DualFlowError, match=match):
        load_train_config(path)


def test_uncued_rules_keep_the_other_rules_text_in_every_drop(tmp_path):
    """With uncued_rules, only those rules' duets lose their text cue; the draw of the drops
    is unchanged, so the same samples lose their music, and without the setting every rule's
    duets lose text (the paper's drop)."""
    batch_rules = torch.arange(64) % 4  # data.rules: mirror, follow, hand_hold, orbit
    drops = {}
    for extra in ([], ["uncued_rules=[hand_hold, orbit]"]):
        music = ["music=beats", "model.music_dim=4"]
        trainer = Trainer(fast_config(tmp_path / str(len(extra)), "steps=1", *music, *extra))
        batch = trainer.train_set.batch(torch.zeros(64, dtype=torch.long))
        batch["rule"] = batch_rules
        cond = trainer._conditions(batch, torch.Generator().manual_seed(3))
        drops[len(extra)] = (cond.drop_text, cond.drop_music)
    (text_all, music_all), (text_some, music_some) = drops[0], drops[1]
    assert torch.equal(music_all, music_some)
    assert set(batch_rules[text_all].tolist()) == {0, 1, 2, 3}  # every rule loses text somewhere
    assert set(batch_rules[text_some].tolist()) == {2, 3}
    assert torch.equal(text_some, text_all & (batch_rules >= 2))


def test_missing_config_file(tmp_path):
    with pytest.raises(DualFlowError, match="training config file not found"):
        load_train_config(tmp_path / "nope.yaml")


def test_warmup_is_linear_then_constant():
    assert warmup_lr(2e-4, 0, 1000) == pytest.approx(2e-7)
    assert warmup_lr(2e-4, 499, 1000) == pytest.approx(1e-4)
    assert warmup_lr(2e-4, 999, 1000) == pytest.approx(2e-4)
    assert warmup_lr(2e-4, 5000, 1000) == pytest.approx(2e-4)
    assert warmup_lr(2e-4, 0, 0) == pytest.approx(2e-4)


# -- data -----------------------------------------------------------------------------------


def test_text_embedding_is_deterministic_and_reflects_words():
    texts = [
        "the partner mirrors the leader",
        "the partner mirrors the leader",
        "the partner circles around the leader",
        "",
    ]
    e = template_text_embedding(texts, 64)
    assert e.shape == (4, 64) and e.dtype == np.float32
    np.testing.assert_array_equal(e[0], e[1])
    np.testing.assert_allclose(np.linalg.norm(e[:3], axis=1), 1.0, rtol=1e-5)
    assert np.all(e[3] == 0)
    # shared words -> correlated, but not identical
    assert 0.3 < float(e[0] @ e[2]) < 0.99
    np.testing.assert_array_equal(template_text_embedding(texts[:1], 64), e[:1])
    with pytest.raises(DualFlowError, match="list of strings"):
        template_text_embedding("one string", 8)


def test_dataset_is_normalised_with_training_stats():
    cfg = TrainingDataConfig(n_clips=8, val_clips=4, frames=16)
    train_ds, val_ds, stats = make_datasets(cfg, text_dim=32)
    raw = build_split(cfg, "train").features
    assert train_ds.actor.shape == (8, 16, 262) and train_ds.text.shape == (8, 32)
    np.testing.assert_allclose(stats.denormalize(train_ds.reactor.numpy()), raw[:, :, 1], atol=1e-4)
    pooled = np.concatenate([train_ds.actor.numpy(), train_ds.reactor.numpy()]).reshape(-1, 262)
    assert np.abs(pooled.mean(axis=0)).max() < 1e-3  # training stats centre the training set
    assert val_ds is not None and len(val_ds) == 4
    assert not np.array_equal(val_ds.actor.numpy()[0], train_ds.actor.numpy()[0])  # disjoint seeds
    assert [int(r) for r in train_ds.rule] == [0, 1, 2, 3, 0, 1, 2, 3]


def test_split_cache_round_trips_without_pickle(tmp_path):
    cfg = TrainingDataConfig(n_clips=5, frames=12)
    fresh = build_split(cfg, "train", tmp_path)
    (cache,) = tmp_path.glob("synthetic_train_*.npz")
    with np.load(cache, allow_pickle=False) as z:
        assert z["texts"].dtype.kind == "U"
    again = build_split(cfg, "train", tmp_path)
    np.testing.assert_array_equal(fresh.features, again.features)
    np.testing.assert_array_equal(fresh.beats, again.beats)
    assert fresh.texts == again.texts and list(fresh.seeds) == list(again.seeds)
    build_split(TrainingDataConfig(n_clips=5, frames=12, seed=1), "train", tmp_path)
    assert len(list(tmp_path.glob("synthetic_train_*.npz"))) == 2  # another config, another file


# -- checkpoints ----------------------------------------------------------------------------


def _tiny_model_and_stats():
    torch.manual_seed(0)
    model = DualFlow(DualFlowConfig.preset("tiny"))
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.01 * torch.randn_like(p))
    _, _, stats = make_datasets(TrainingDataConfig(n_clips=4, val_clips=0, frames=8), text_dim=384)
    return model, stats


def test_checkpoint_round_trip_without_pickle(tmp_path):
    model, stats = _tiny_model_and_stats()
    opt = torch.optim.AdamW(model.parameters(), lr=1e-3)
    model(torch.randn(1, 8, 262), torch.randn(1, 8, 262), 0.5)[1].sum().backward()
    opt.step()
    path = save_checkpoint(
        tmp_path / "ck",
        model=model,
        stats=stats,
        meta={"text_encoder": TEXT_ENCODER_ID},
        optimizer=opt,
        trainer_state={"step": 3},
    )
    names = sorted(p.name for p in path.iterdir())
    assert names == [
        "config.json",
        "model.safetensors",
        "norm_stats.npz",
        "optimizer.safetensors",
        "trainer_state.json",
    ]
    # no pickle anywhere: npz members are plain .npy arrays that load with allow_pickle=False
    with zipfile.ZipFile(path / "norm_stats.npz") as z:
        assert sorted(z.namelist()) == ["mean.npy", "std.npy"]
    with np.load(path / "norm_stats.npz", allow_pickle=False) as z:
        assert z["mean"].dtype == np.float64
    for f in path.iterdir():
        assert b"\x80\x04\x95" not in f.read_bytes() and b"\x80\x02" not in f.read_bytes()[:2]
    json.loads((path / "config.json").read_text())
    ck = load_checkpoint(path, resume=True)
    assert ck.config == model.config and ck.text_encoder == TEXT_ENCODER_ID
    rebuilt = ck.build_model()
    x = torch.randn(2, 8, 262)
    torch.testing.assert_close(rebuilt(x, x, 0.3)[1], model.eval()(x, x, 0.3)[1], rtol=0, atol=0)
    opt2 = torch.optim.AdamW(rebuilt.parameters(), lr=1e-3)
    opt2.load_state_dict(ck.optimizer_state)
    compared = 0
    for p1, p2 in zip(model.parameters(), rebuilt.parameters()):
        assert set(opt.state[p1]) == set(opt2.state[p2])
        for key in opt.state[p1]:
            torch.testing.assert_close(opt.state[p1][key], opt2.state[p2][key], rtol=0, atol=0)
            compared += 1
    assert compared > 30
    np.testing.assert_array_equal(ck.stats.std, stats.std)
    # half-size export loads back as float32 within fp16 precision
    half = save_checkpoint(tmp_path / "half", model=model, stats=stats, weights_dtype=torch.float16)
    assert (half / "model.safetensors").stat().st_size < 0.6 * (path / "model.safetensors").stat().st_size
    m16, _ = load_model(half)
    assert next(m16.parameters()).dtype == torch.float32
    torch.testing.assert_close(m16(x, x, 0.3)[1], rebuilt(x, x, 0.3)[1], rtol=0, atol=2e-2)


def test_checkpoint_errors_name_the_file(tmp_path):
    with pytest.raises(DualFlowError, match="checkpoint directory not found"):
        load_checkpoint(tmp_path / "none")
    model, stats = _tiny_model_and_stats()
    path = save_checkpoint(tmp_path / "ck", model=model, stats=stats)
    (path / "norm_stats.npz").unlink()
    with pytest.raises(DualFlowError, match="lacks norm_stats.npz"):
        load_checkpoint(path)
    path = save_checkpoint(tmp_path / "ck2", model=model, stats=stats)
    (path / "model.safetensors").write_bytes(b"garbage")
    with pytest.raises(DualFlowError, match="model.safetensors: not a readable safetensors file"):
        load_checkpoint(path)
    path = save_checkpoint(tmp_path / "ck3", model=model, stats=stats)
    (path / "config.json").write_text(json.dumps({"format": "other"}))
    with pytest.raises(DualFlowError, match="not a DualFlow checkpoint config"):
        load_checkpoint(path)
    with pytest.raises(DualFlowError, match="cannot be resumed"):
        load_checkpoint(save_checkpoint(tmp_path / "ck4", model=model, stats=stats), resume=True)


# -- the training loop ----------------------------------------------------------------------


def test_training_writes_log_checkpoints_and_ema_export(tmp_path):
    cfg = fast_config(tmp_path, "steps=6", "val_every=3")
    result = train(cfg)
    assert result.step == 6 and np.isfinite(result.loss)
    with open(tmp_path / "train_log.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [int(r["step"]) for r in rows] == [1, 2, 3, 4, 5, 6]
    assert float(rows[0]["lr"]) == pytest.approx(1e-3 / 4) and float(rows[5]["lr"]) == pytest.approx(1e-3)
    assert rows[2]["val_loss"] and not rows[1]["val_loss"]
    # the paper's loss terms are logged and add up to the loss (one process: no averaging)
    terms = ("flow", "triplet", "foot", "vel", "bone", "dm", "ro", "sync")
    for r in rows:
        assert float(r["loss"]) == pytest.approx(sum(float(r[k]) for k in terms), rel=1e-4)
        assert float(r["flow"]) > 0 and float(r["bone"]) >= 0
    assert {r["mode"] for r in rows} <= {"reactive", "interactive"}
    assert json.loads((tmp_path / "latest.json").read_text())["step"] == 6
    assert sorted(p.name for p in (tmp_path / "checkpoints").iterdir()) == ["step_0000003", "step_0000006"]
    final = load_checkpoint(tmp_path / "final")
    assert final.meta["weights"] == "ema" and final.meta["synthetic"] is True and final.meta["step"] == 6
    # the export holds the EMA weights, which differ from the raw weights of the last step
    last = load_checkpoint(tmp_path / "checkpoints" / "step_0000006")
    ema = {k[len("module.") :]: v for k, v in last.ema_state.items() if k.startswith("module.")}
    for k, v in final.state_dict.items():
        torch.testing.assert_close(v, ema[k], rtol=0, atol=0)
    assert any(not torch.equal(v, last.state_dict[k]) for k, v in final.state_dict.items())


def test_resume_equals_uninterrupted(tmp_path):
    straight = Trainer(fast_config(tmp_path / "a", "steps=6"))
    straight.run()
    first = Trainer(fast_config(tmp_path / "b", "steps=3"))
    first.run()
    resumed = Trainer(fast_config(tmp_path / "b", "steps=6"), resume=True)
    assert resumed.step == 3
    resumed.run()
    a, b = state_of(straight.model), state_of(resumed.model)
    assert a.keys() == b.keys()
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0, msg=k)
    for k, v in straight.ema.state_dict().items():
        torch.testing.assert_close(v, resumed.ema.state_dict()[k], rtol=0, atol=0, msg=k)
    # and the weights really moved from their initial values
    init = state_of(Trainer(fast_config(tmp_path / "c", "steps=1")).model)
    assert any(not torch.equal(init[k], a[k]) for k in a)
    with open(tmp_path / "b" / "train_log.csv", newline="") as fh:
        assert [int(r["step"]) for r in csv.DictReader(fh)] == [1, 2, 3, 4, 5, 6]


def test_resume_without_checkpoint_is_a_user_error(tmp_path):
    with pytest.raises(DualFlowError, match="nothing to resume from"):
        Trainer(fast_config(tmp_path, "steps=2"), resume=True)


def test_bf16_autocast_path_trains(tmp_path):
    trainer = Trainer(fast_config(tmp_path, "steps=2", "amp=bf16", "ema_decay=0"))
    assert trainer.autocast_dtype == torch.bfloat16
    before = state_of(trainer.model)
    result = trainer.run()
    assert np.isfinite(result.loss)
    assert all(v.dtype == torch.float32 for v in trainer.model.state_dict().values())  # master weights stay fp32
    assert any(not torch.equal(before[k], v) for k, v in trainer.model.state_dict().items())
    assert Trainer(fast_config(tmp_path / "x", "steps=1")).autocast_dtype is None  # auto on CPU: no autocast


def test_cli_print_params_and_user_errors(capsys, tmp_path):
    from ros_free_bridge.cli import main

    assert main(["train", "--print-params"]) == 0
    out = capsys.readouterr().out
    for name in ("paper", "small", "tiny", "456M"):
        assert name in out
    assert main(["train", "--config", str(tmp_path / "missing.yaml")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "missing.yaml" in err and len(err.strip().splitlines()) == 1


def test_cli_trains(tmp_path, capsys):
    from ros_free_bridge.cli import main

    cfg = tmp_path / "c.yaml"
    cfg.write_text("\n".join(s.replace("=", ": ", 1) for s in FAST if "." not in s.split("=")[0]) + "\n")
    rc = main(
        [
            "train",
            "--config",
            str(cfg),
            "--set",
            "data.n_clips=4",
            "--set",
            "data.frames=12",
            "--set",
            "data.val_clips=0",
            "--steps",
            "2",
            "--out-dir",
            str(tmp_path / "out"),
        ]
    )
    assert rc == 0
    assert "trained to step 2" in capsys.readouterr().out
    model, ck = load_model(tmp_path / "out" / "final")
    assert ck.meta["train"]["steps"] == 2 and ck.meta["data"]["frames"] == 12
    assert isinstance(model, DualFlow) and not model.training
    assert load_file(str(tmp_path / "out" / "final" / "model.safetensors"))
    assert main(["train", "--evaluate", str(tmp_path / "out" / "final"), "--eval-clips", "2"]) == 0
    out = capsys.readouterr().out
    assert "reactor MPJPE over 2 clips" in out and "actor masked" in out and "static mean pose" in out


def test_wall_clock_budget_stops_and_still_exports(tmp_path):
    result = train(fast_config(tmp_path, "steps=1000", "max_minutes=1e-9"))
    assert result.step == 0
    assert load_checkpoint(tmp_path / "final").meta["step"] == 0
    assert json.loads((tmp_path / "latest.json").read_text())["step"] == 0


def test_x0_prediction_forms_the_straight_path_velocity():
    from dualflow.flow import RectifiedPath

    torch.manual_seed(0)
    model = DualFlow(DualFlowConfig.preset("tiny", prediction="x0")).eval()
    with torch.no_grad():
        model.out_b.bias.normal_()
    x_a, x_t = torch.randn(2, 6, 262), torch.randn(2, 6, 262)
    t = torch.tensor([0.25, 0.999])
    _, v = model(x_a, x_t, t, mode="reactive")
    x0_hat = model.out_b.bias.expand_as(x_t)  # zero-initialised weights: the output is the bias
    torch.testing.assert_close(v[0], (x0_hat[0] - x_t[0]) / 0.75)
    torch.testing.assert_close(v[1], (x0_hat[1] - x_t[1]) / 0.05)  # 1 - t floored at 0.05
    torch.testing.assert_close(RectifiedPath().x0_from_velocity(x_t[:1], t[:1], v[:1]), x0_hat[:1])
    with pytest.raises(DualFlowError, match="prediction must be one of"):
        DualFlowConfig.preset("tiny", prediction="eps")


@pytest.mark.parametrize("name", ["hashed", "minilm"])
def test_the_text_encoder_is_recorded_and_rebuilt_from_the_checkpoint(tmp_path, name):
    trainer = Trainer(fast_config(tmp_path, "steps=1", "model.text_dim=384", f"text_encoder={name}"))
    trainer.run()
    ck = load_checkpoint(tmp_path / "final")
    assert ck.meta["text_encoder_name"] == name and ck.text_encoder == trainer.text_encoder.encoder_id
    encoder = ck.make_text_encoder()
    assert encoder.encoder_id == ck.text_encoder
    # the training data was embedded by exactly this encoder
    np.testing.assert_allclose(
        encoder.encode(trainer.train_set.texts[:3]), trainer.train_set.text[:3].numpy(), atol=1e-5
    )
