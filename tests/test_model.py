"""The DualFlow network: shapes, presets, conditioning, task switch, errors."""

from __future__ import annotations

import json

import pytest
import torch

from dualflow import DualFlowError
from dualflow.model import (
    PRESETS,
    Conditions,
    DualFlow,
    DualFlowConfig,
    count_parameters,
    look_ahead_mask,
    parameter_report,
    sample_condition_drop,
)

B, T = 3, 16


def randomise_zero_inits(m: DualFlow) -> DualFlow:
    """The output linears and adaLN modulations start at zero; give them weights for testing."""
    for name, p in m.named_parameters():
        if name.startswith(("out_a", "out_b")) or ".modulation." in name:
            torch.nn.init.normal_(p, std=0.1)
    return m


@pytest.fixture(scope="module")
def model() -> DualFlow:
    torch.manual_seed(0)
    return randomise_zero_inits(DualFlow(DualFlowConfig.preset("tiny")).eval())


def _x(seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(B, T, 262, generator=g), torch.randn(B, T, 262, generator=g)


def _cond(seed=0, **kw):
    g = torch.Generator().manual_seed(seed)
    base = dict(
        text=torch.randn(B, 384, generator=g),
        music=torch.randn(B, T, 35, generator=g),
        retrieval=torch.randn(B, 5, 32, generator=g),
    )
    base.update(kw)
    return Conditions(**base)


def test_presets_match_the_paper_and_scale_down():
    paper = DualFlowConfig.preset("paper")
    assert (paper.n_blocks, paper.width, paper.n_heads, paper.ff_dim, paper.dropout) == (20, 512, 8, 1024, 0.1)
    assert paper.conv_kernels == (7, 11, 21) and paper.look_ahead == 10
    assert count_parameters("tiny") < count_parameters("small") < count_parameters("paper")
    # The paper preset's block stack is hundreds of millions of parameters (456M in the paper).
    assert 300e6 < count_parameters("paper") < 500e6
    report = parameter_report()
    for name in PRESETS:
        assert name in report


def test_parameter_count_matches_a_built_model():
    cfg = DualFlowConfig.preset("tiny")
    assert count_parameters(cfg) == sum(p.numel() for p in DualFlow(cfg).parameters())


def test_config_round_trips_through_json_and_rejects_bad_values():
    cfg = DualFlowConfig.preset("small", look_ahead=5)
    assert DualFlowConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    with pytest.raises(DualFlowError, match="n_heads"):
        DualFlowConfig(width=30, n_heads=4)
    with pytest.raises(DualFlowError, match="unknown DualFlow preset"):
        DualFlowConfig.preset("huge")
    with pytest.raises(DualFlowError, match="unknown field"):
        DualFlowConfig.from_dict({"widht": 3})
    with pytest.raises(DualFlowError, match="odd"):
        DualFlowConfig(conv_kernels=(4,))


@pytest.mark.parametrize("mode", ["interactive", "reactive"])
def test_output_shapes_and_reactive_actor_velocity_is_zero(model, mode):
    x_a, x_b = _x()
    v_a, v_b = model(x_a, x_b, torch.rand(B), _cond(), mode=mode)
    assert v_a.shape == v_b.shape == (B, T, 262)
    assert torch.isfinite(v_b).all()
    if mode == "reactive":
        assert torch.all(v_a == 0)
    else:
        assert v_a.abs().sum() > 0


def test_one_set_of_weights_gives_different_fields_per_task(model):
    x_a, x_b = _x()
    _, v_int = model(x_a, x_b, 0.5, _cond(), mode="interactive")
    _, v_rea = model(x_a, x_b, 0.5, _cond(), mode="reactive")
    assert not torch.allclose(v_int, v_rea)


def test_reactive_actor_stream_does_not_depend_on_the_flow_time_of_the_reactor(model):
    """The clean actor is embedded at t = 1; only the reactor's state changes with t."""
    x_a, x_b = _x()
    xa = x_a.clone().requires_grad_(True)
    _, v_b = model(xa, x_b, 0.1, _cond(), mode="reactive")
    v_b.sum().backward()
    assert xa.grad.abs().sum() > 0  # the reactor is conditioned on the actor


def test_every_condition_can_be_absent_and_changes_the_output(model):
    x_a, x_b = _x()
    t = torch.full((B,), 0.4)
    full = model(x_a, x_b, t, _cond())[1]
    none = model(x_a, x_b, t, Conditions())[1]
    no_text = model(x_a, x_b, t, _cond(text=None))[1]
    no_music = model(x_a, x_b, t, _cond(music=None))[1]
    no_retr = model(x_a, x_b, t, _cond(retrieval=None))[1]
    for other in (none, no_text, no_music, no_retr):
        assert torch.isfinite(other).all()
        assert not torch.allclose(full, other)


def test_drop_masks_replace_conditions_by_the_learned_null(model):
    x_a, x_b = _x()
    t = torch.full((B,), 0.4)
    dropped = _cond(drop_text=torch.tensor([True, False, True]), drop_music=torch.tensor([True, False, False]))
    v = model(x_a, x_b, t, dropped)[1]
    v_full = model(x_a, x_b, t, _cond())[1]
    v_null = model(x_a, x_b, t, _cond(text=None, music=None))[1]
    torch.testing.assert_close(v[0], v_null[0])  # both dropped == both absent
    torch.testing.assert_close(v[1], v_full[1])  # nothing dropped
    assert not torch.allclose(v[2], v_full[2]) and not torch.allclose(v[2], v_null[2])


def test_condition_drop_schedule_frequencies():
    g = torch.Generator().manual_seed(0)
    n = 200_000
    drop_text, drop_music = sample_condition_drop(n, g)
    both = (drop_text & drop_music).float().mean().item()
    text_only = (drop_text & ~drop_music).float().mean().item()
    music_only = (~drop_text & drop_music).float().mean().item()
    assert abs(both - 0.10) < 0.005
    assert abs(text_only - 0.20) < 0.005
    assert abs(music_only - 0.20) < 0.005


def test_padding_frames_do_not_affect_real_frames_in_interactive_mode(model):
    x_a, x_b = _x()
    mask = torch.ones(B, T, dtype=torch.bool)
    mask[:, 12:] = False
    v_ref = model(x_a, x_b, 0.5, Conditions(), frame_mask=mask)[1]
    x_a2, x_b2 = x_a.clone(), x_b.clone()
    x_a2[:, 12:] = 9.0
    x_b2[:, 12:] = -9.0
    v_new = model(x_a2, x_b2, 0.5, Conditions(), frame_mask=mask)[1]
    torch.testing.assert_close(v_new[:, :12], v_ref[:, :12])


def test_look_ahead_mask_is_the_papers_upper_triangular_mask():
    m = look_ahead_mask(4, 4, 1)
    expected = torch.tensor([[1, 1, 0, 0], [1, 1, 1, 0], [1, 1, 1, 1], [1, 1, 1, 1]], dtype=torch.bool)
    assert torch.equal(m, expected)


def test_bad_shapes_raise_one_clear_error(model):
    x_a, x_b = _x()
    with pytest.raises(DualFlowError, match="x_a"):
        model(x_a[..., :100], x_b, 0.5)
    with pytest.raises(DualFlowError, match="music"):
        model(x_a, x_b, 0.5, Conditions(music=torch.randn(B, T + 1, 35)))
    with pytest.raises(DualFlowError, match="text"):
        model(x_a, x_b, 0.5, Conditions(text=torch.randn(B, 768)))
    with pytest.raises(DualFlowError, match="mode"):
        model(x_a, x_b, 0.5, mode="duet")


def test_a_few_training_steps_reduce_the_flow_loss():
    """All parts receive gradients and the network can fit a fixed batch."""
    from dualflow.flow import flow_training_step

    torch.manual_seed(0)
    m = DualFlow(DualFlowConfig.preset("tiny"))
    x_a, x_b = _x(3)
    cond = _cond(3)
    opt = torch.optim.AdamW(m.parameters(), lr=3e-3)
    losses = []
    for step in range(30):
        g = torch.Generator().manual_seed(step % 2)
        mode = "reactive" if step % 2 else "interactive"
        out = flow_training_step(m, x_a, x_b, cond, mode=mode, generator=g)
        opt.zero_grad()
        out.loss.backward()
        opt.step()
        losses.append(out.loss.item())
    assert sum(losses[-4:]) / 4 < 0.8 * sum(losses[:4]) / 4
    # After an interactive step, everything but the unused null embeddings has a gradient.
    opt.zero_grad()
    flow_training_step(m, x_a, x_b, cond, mode="interactive").loss.backward()
    missing = {n for n, p in m.named_parameters() if p.grad is None or not p.grad.any()}
    assert missing <= {"null_text", "null_music", "null_retrieval"}, missing


def test_cached_actor_context_gives_the_same_reactive_field(model):
    x_a, x_b = _x()
    cond = _cond()
    ctx = model.actor_context(x_a, cond)
    assert len(ctx.keys) == model.config.n_blocks and ctx.keys[0].shape == (B, T, 32)
    for t in (0.1, 0.8):
        ref = model(x_a, x_b, t, cond, mode="reactive")[1]
        cached = model(x_a, x_b, t, cond, mode="reactive", actor_context=ctx)[1]
        torch.testing.assert_close(cached, ref)
    with pytest.raises(DualFlowError, match="actor_context"):
        model(x_a[:, :8], x_b[:, :8], 0.5, Conditions(), mode="reactive", actor_context=ctx)


def test_reactive_sampler_computes_the_actor_stream_once_per_condition(model, monkeypatch):
    from dualflow.flow import SamplingSettings, generate

    calls = []
    original = model.actor_context
    monkeypatch.setattr(model, "actor_context", lambda *a, **k: calls.append(1) or original(*a, **k))
    x_a, _ = _x()
    generate(model, T, _cond(), mode="reactive", x_actor=x_a, sampling=SamplingSettings(steps=4, cfg_scale=2.0))
    assert len(calls) == 2  # conditional + unconditional, not 2 x 4 steps


def test_parameter_breakdown_adds_up():
    from dualflow.model import parameter_breakdown

    parts = parameter_breakdown("tiny")
    assert sum(parts.values()) == count_parameters("tiny")
    cfg = DualFlowConfig.preset("tiny")
    conv = cfg.n_blocks * sum(cfg.width * cfg.width * k + cfg.width for k in cfg.conv_kernels) + cfg.n_blocks * 3
    assert parts["temporal convolutions"] == conv
