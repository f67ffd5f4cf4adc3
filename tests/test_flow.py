"""Rectified flow: path, training target, time sampling, ODE solvers, guidance, determinism."""

from __future__ import annotations

import pytest
import torch

from dualflow import DualFlowError
from dualflow.flow import (
    RectifiedPath,
    SamplingSettings,
    TimeSampler,
    flow_loss,
    flow_training_step,
    generate,
    guided_velocity,
    ode_solve,
    time_grid,
)
from dualflow.model import Conditions, DualFlow, DualFlowConfig


def _tiny(randomise: bool = True) -> DualFlow:
    torch.manual_seed(0)
    m = DualFlow(DualFlowConfig.preset("tiny"))
    if randomise:
        for name, p in m.named_parameters():
            if name.startswith(("out_a", "out_b")) or ".modulation." in name:
                torch.nn.init.normal_(p, std=0.1)
    return m


def test_path_endpoints_velocity_and_x0_recovery():
    path = RectifiedPath()
    g = torch.Generator().manual_seed(0)
    x0, eps = torch.randn(4, 5, 262, generator=g), torch.randn(4, 5, 262, generator=g)
    torch.testing.assert_close(path.interpolate(x0, eps, torch.zeros(4)), eps)
    torch.testing.assert_close(path.interpolate(x0, eps, torch.ones(4)), x0)
    t = torch.tensor([0.0, 0.25, 0.5, 0.9])
    x_t = path.interpolate(x0, eps, t)
    torch.testing.assert_close(x_t[1], 0.75 * eps[1] + 0.25 * x0[1])
    v = path.target_velocity(x0, eps)
    torch.testing.assert_close(v, x0 - eps)
    # x0_hat = x_t + (1 - t) v recovers the data exactly when v is the true velocity.
    torch.testing.assert_close(path.x0_from_velocity(x_t, t, v), x0)


def test_time_samplers():
    g = torch.Generator().manual_seed(0)
    u = TimeSampler().sample(50_000, g)
    assert u.min() >= 0 and u.max() <= 1 and abs(u.mean().item() - 0.5) < 0.01
    ln = TimeSampler("logit_normal", mean=0.0, std=1.0).sample(50_000, g)
    assert ln.min() > 0 and ln.max() < 1
    assert abs(ln.median().item() - 0.5) < 0.01
    # More mass in the middle than uniform: P(0.25 < t < 0.75) is about 0.73 for std = 1.
    middle = ((ln > 0.25) & (ln < 0.75)).float().mean().item()
    assert 0.68 < middle < 0.78
    shifted = TimeSampler("logit_normal", mean=1.0).sample(20_000, g)
    assert abs(shifted.median().item() - torch.sigmoid(torch.tensor(1.0)).item()) < 0.01
    with pytest.raises(DualFlowError, match="kind"):
        TimeSampler("cosine")


def test_flow_loss_known_values():
    target = torch.zeros(2, 3, 4)
    assert flow_loss(target + 1.0, target).item() == pytest.approx(1.0)
    assert flow_loss(target, target).item() == 0.0
    pred = target.clone()
    pred[1, 2] = 10.0  # error only on a padded frame
    mask = torch.ones(2, 3, dtype=torch.bool)
    mask[1, 2] = False
    assert flow_loss(pred, target, mask).item() == 0.0
    assert flow_loss(pred, target).item() == pytest.approx(100.0 * 4 / 24)


@pytest.mark.parametrize("mode", ["interactive", "reactive"])
def test_training_step_targets_with_an_untrained_zero_output_model(mode):
    """The untrained model outputs v = 0, so L_flow = mean((x0 - eps)^2) with the same noise."""
    m = _tiny(randomise=False)
    g0 = torch.Generator().manual_seed(3)
    x0_a, x0_b = torch.randn(2, 8, 262, generator=g0), torch.randn(2, 8, 262, generator=g0)
    out = flow_training_step(m, x0_a, x0_b, mode=mode, generator=torch.Generator().manual_seed(7))
    g = torch.Generator().manual_seed(7)
    t = torch.rand(2, generator=g)
    eps_b = torch.randn(x0_b.shape, generator=g)
    torch.testing.assert_close(out.t, t)
    torch.testing.assert_close(out.target_b, x0_b - eps_b)
    x_t_b = RectifiedPath().interpolate(x0_b, eps_b, t)
    torch.testing.assert_close(out.x0_hat_b, x_t_b)  # v_hat = 0
    if mode == "reactive":
        assert torch.all(out.target_a == 0) and torch.equal(out.x0_hat_a, x0_a)
        expected = ((x0_b - eps_b) ** 2).mean()
    else:
        eps_a = torch.randn(x0_a.shape, generator=g)
        expected = torch.cat([(x0_a - eps_a) ** 2, (x0_b - eps_b) ** 2], -1).mean()
    torch.testing.assert_close(out.loss, expected)


def test_euler_and_heun_on_known_odes():
    x0 = torch.zeros(1, 1, 1)
    # dx/dt = t: exact x(1) = 0.5. Euler with N steps: sum_k h * k h = (N - 1) / (2N); Heun is exact.
    f = lambda x, t: t.reshape(-1, 1, 1).expand_as(x)  # noqa: E731
    assert ode_solve(f, x0, steps=4).item() == pytest.approx(3 / 8)
    assert ode_solve(f, x0, steps=4, method="heun").item() == pytest.approx(0.5)
    # The conditional rectified-flow field towards a point x1, v = (x1 - x) / (1 - t), lands on x1.
    x1 = torch.tensor(2.5)
    g = lambda x, t: (x1 - x) / (1 - t.reshape(-1, 1, 1))  # noqa: E731
    assert ode_solve(g, torch.full((1, 1, 1), -1.0), steps=7).item() == pytest.approx(2.5)
    with pytest.raises(DualFlowError, match="method"):
        ode_solve(f, x0, method="rk4")
    with pytest.raises(DualFlowError, match="steps"):
        time_grid(0)


def test_projection_hook_imposes_known_values_at_every_grid_time():
    seen = []

    def project(x, t):
        seen.append(t)
        x = x.clone()
        x[:, 0] = 7.0
        return x

    out = ode_solve(lambda x, t: torch.ones_like(x), torch.zeros(1, 3, 1), steps=5, project=project)
    assert seen == pytest.approx([0.0, 0.2, 0.4, 0.6, 0.8, 1.0])
    assert out[0, 0, 0].item() == 7.0
    assert out[0, 1, 0].item() == pytest.approx(1.0)


def test_generate_is_deterministic_per_seed_and_counts_model_calls():
    m = _tiny()
    calls = []
    m.register_forward_hook(lambda *_: calls.append(1))
    cond = Conditions(text=torch.randn(2, 384))
    a1, b1 = generate(m, 10, cond, batch=2, sampling=SamplingSettings(steps=5, seed=11))
    assert len(calls) == 5
    a2, b2 = generate(m, 10, cond, batch=2, sampling=SamplingSettings(steps=5, seed=11))
    a3, b3 = generate(m, 10, cond, batch=2, sampling=SamplingSettings(steps=5, seed=12))
    assert torch.equal(a1, a2) and torch.equal(b1, b2)
    assert not torch.allclose(b1, b3)
    calls.clear()
    generate(m, 10, cond, batch=2, sampling=SamplingSettings(steps=5, method="heun", cfg_scale=2.5, seed=11))
    assert len(calls) == 5 * 2 * 2  # Heun: 2 evaluations per step; CFG: 2 calls per evaluation
    assert a1.shape == b1.shape == (2, 10, 262)


def test_reactive_generation_keeps_the_actor_clean():
    m = _tiny()
    actor = torch.randn(2, 12, 262)
    x_a, x_b = generate(m, 12, mode="reactive", x_actor=actor, sampling=SamplingSettings(steps=3, seed=0))
    assert torch.equal(x_a, actor)
    assert x_b.shape == actor.shape and not torch.allclose(x_b, actor)
    with pytest.raises(DualFlowError, match="x_actor"):
        generate(m, 12, mode="reactive", sampling=SamplingSettings(steps=3))


def test_classifier_free_guidance_combines_conditional_and_unconditional_fields():
    m = _tiny().eval()
    cond = Conditions(text=torch.randn(2, 384), music=torch.randn(2, 6, 35))
    x = torch.randn(2, 6, 524)
    t = torch.full((2,), 0.3)
    with torch.no_grad():
        v_c = guided_velocity(m, cond, mode="interactive", cfg_scale=1.0)(x, t)
        v_u = guided_velocity(m, cond.unconditional(), mode="interactive", cfg_scale=1.0)(x, t)
        v_g = guided_velocity(m, cond, mode="interactive", cfg_scale=3.0)(x, t)
    assert not torch.allclose(v_c, v_u)
    torch.testing.assert_close(v_g, v_u + 3.0 * (v_c - v_u))


def test_guidance_null_drops_retrieval_like_training_does():
    # training drops the retrieval tokens together with text and music (dualflow/retrieval.py), so the
    # guidance null must not keep them
    cond = Conditions(text=torch.randn(2, 384), music=torch.randn(2, 6, 35), retrieval=torch.randn(2, 4, 32))
    null = cond.unconditional()
    assert null.text is None and null.music is None and null.retrieval is None
