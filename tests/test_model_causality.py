"""Reactive mode is causal with look-ahead L: reactor frame i sees actor frames <= i + L only.

Checked on the network itself (not only on the streamer), with gradients and perturbations.
"""

from __future__ import annotations

import pytest
import torch

from dualflow.model import Conditions, DualFlow, DualFlowConfig

T = 24


def _model(look_ahead: int = 3) -> DualFlow:
    torch.manual_seed(0)
    model = DualFlow(DualFlowConfig.preset("tiny", look_ahead=look_ahead)).eval()
    # The output linears and adaLN modulations start at zero; give them weights so that every
    # path (text/time conditioning included) is live.
    for name, p in model.named_parameters():
        if name.startswith(("out_a", "out_b")) or ".modulation." in name:
            torch.nn.init.normal_(p, std=0.1)
    return model


def _inputs(batch: int = 2):
    g = torch.Generator().manual_seed(1)
    x_a = torch.randn(batch, T, 262, generator=g)
    x_b = torch.randn(batch, T, 262, generator=g)
    cond = Conditions(
        text=torch.randn(batch, 384, generator=g),
        music=torch.randn(batch, T, 35, generator=g),
        retrieval=torch.randn(batch, 4, 32, generator=g),
    )
    return x_a, x_b, cond


@pytest.mark.parametrize("look_ahead", [0, 3])
def test_reactor_gradient_reaches_only_actor_frames_up_to_i_plus_L(look_ahead):
    model = _model(look_ahead)
    x_a, x_b, cond = _inputs()
    for i in (0, 7, T - 5):
        xa = x_a.clone().requires_grad_(True)
        xb = x_b.clone().requires_grad_(True)
        _, v_b = model(xa, xb, torch.tensor([0.3, 0.7]), cond, mode="reactive")
        v_b[:, i].sum().backward()
        ga = xa.grad.abs().sum(dim=(0, 2))
        gb = xb.grad.abs().sum(dim=(0, 2))
        assert torch.all(ga[i + look_ahead + 1 :] == 0), f"frame {i} sees actor frames beyond i+L"
        assert ga[min(i + look_ahead, T - 1)] > 0, "the look-ahead frame i+L must be used"
        assert ga[: i + 1].sum() > 0
        assert torch.all(gb[i + 1 :] == 0), f"frame {i} sees the reactor's own future (noise)"
        assert gb[i] > 0


def test_interactive_mode_is_bidirectional():
    """The same weights without the reactive switch do look ahead (the test above can fail)."""
    model = _model(3)
    x_a, x_b, cond = _inputs()
    xa = x_a.clone().requires_grad_(True)
    _, v_b = model(xa, x_b, torch.tensor([0.3, 0.7]), cond, mode="interactive")
    v_b[:, 0].sum().backward()
    assert xa.grad[:, 10:].abs().sum() > 0


def test_perturbing_late_actor_frames_leaves_earlier_reactor_velocities_identical():
    model = _model(3)
    x_a, x_b, cond = _inputs()
    t = torch.tensor([0.5, 0.5])
    _, v_ref = model(x_a, x_b, t, cond, mode="reactive")
    for cut in (4, 12, 20):
        x_pert = x_a.clone()
        x_pert[:, cut:] += 5.0 * torch.randn_like(x_pert[:, cut:])
        _, v_new = model(x_pert, x_b, t, cond, mode="reactive")
        last_safe = cut - 3 - 1  # frames i with i + L < cut
        assert torch.equal(v_new[:, : last_safe + 1], v_ref[:, : last_safe + 1])
        assert not torch.allclose(v_new[:, last_safe + 1 :], v_ref[:, last_safe + 1 :])


def test_reactor_future_noise_does_not_change_its_past():
    model = _model(3)
    x_a, x_b, cond = _inputs()
    t = torch.tensor([0.2, 0.9])
    _, v_ref = model(x_a, x_b, t, cond, mode="reactive")
    x_pert = x_b.clone()
    x_pert[:, 10:] = torch.randn_like(x_pert[:, 10:])
    _, v_new = model(x_a, x_pert, t, cond, mode="reactive")
    assert torch.equal(v_new[:, :10], v_ref[:, :10])


def test_causality_holds_with_a_padding_mask():
    model = _model(2)
    x_a, x_b, cond = _inputs()
    frame_mask = torch.ones(2, T, dtype=torch.bool)
    frame_mask[1, 18:] = False
    xa = x_a.clone().requires_grad_(True)
    _, v_b = model(xa, x_b, 0.5, cond, mode="reactive", frame_mask=frame_mask)
    v_b[:, 5].sum().backward()
    assert torch.all(xa.grad[:, 8:] == 0)
    assert xa.grad[:, 7].abs().sum() > 0
