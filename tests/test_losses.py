"""DualFlow losses on hand-made motions with known values (zero for identical motions)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from dualflow.losses import (
    HAND_JOINTS,
    LOWER_JOINTS,
    UPPER_JOINTS,
    CleanBatch,
    LossSettings,
    LossWeights,
    Prediction,
    SyncWeights,
    bone_length_loss,
    bone_lengths,
    denormalize,
    distance_map_loss,
    dualflow_losses,
    facing_direction,
    foot_contact_loss,
    joint_positions,
    joint_velocity_loss,
    relative_orientation_loss,
    sync_loss,
    triplet_loss,
)
from dualflow.motion import REST_POSE
from dualflow.motion.features import FEATURE_SLICES

T = 6


REST_YUP = torch.tensor(np.asarray(REST_POSE)[:, [1, 2, 0]], dtype=torch.float64)  # (22, 3)


def yaw(points: torch.Tensor, angle: float) -> torch.Tensor:
    """Rotate (..., 3) Y-up points about the vertical (y) axis by angle (rad)."""
    c, s = math.cos(angle), math.sin(angle)
    rot = torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], dtype=points.dtype)
    return points @ rot.T


def still(pose: torch.Tensor, batch: int = 2) -> torch.Tensor:
    """(22, 3) -> (B, T, 22, 3) standing still."""
    return pose.expand(batch, T, 22, 3).clone()


def features(pos: torch.Tensor, contacts: float = 1.0) -> torch.Tensor:
    """Feature tensor (B, T, 262) with the given positions and constant contacts, rest zero."""
    f = torch.zeros(*pos.shape[:2], 262, dtype=pos.dtype)
    f[..., FEATURE_SLICES["positions"]] = pos.reshape(*pos.shape[:2], 66)
    f[..., FEATURE_SLICES["contacts"]] = contacts
    return f


def test_rest_pose_faces_plus_z_in_the_yup_feature_frame():
    f = facing_direction(still(REST_YUP))
    torch.testing.assert_close(f[0, 0], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))


def test_denormalize_and_joint_positions():
    mean = torch.arange(262, dtype=torch.float64)
    std = torch.full((262,), 2.0, dtype=torch.float64)
    x = torch.ones(1, 1, 262, dtype=torch.float64)
    f = denormalize(x, mean, std)
    torch.testing.assert_close(f[0, 0, :3], torch.tensor([2.0, 3.0, 4.0], dtype=torch.float64))
    assert joint_positions(f).shape == (1, 1, 22, 3)
    assert joint_positions(f)[0, 0, 1, 0].item() == 5.0  # column 3 = joint 1, x


def test_foot_contact_loss_known_slide():
    pos = still(REST_YUP)
    contacts = torch.ones(2, T, 4, dtype=torch.float64)
    assert foot_contact_loss(pos, contacts).item() == 0.0
    slide = pos + torch.arange(T, dtype=torch.float64)[None, :, None, None] * torch.tensor(
        [0.01, 0.0, 0.02], dtype=torch.float64
    )
    assert foot_contact_loss(slide, contacts).item() == pytest.approx(0.01**2 + 0.02**2)
    # Feet in the air may move freely.
    assert foot_contact_loss(slide, torch.zeros_like(contacts)).item() == 0.0
    # Half the feet in contact: half the value.
    half = contacts.clone()
    half[..., :2] = 0
    assert foot_contact_loss(slide, half).item() == pytest.approx(0.5 * (0.01**2 + 0.02**2))


def test_joint_velocity_loss_known_drift_and_offset_invariance():
    gt = still(REST_YUP)
    assert joint_velocity_loss(gt, gt).item() == 0.0
    assert joint_velocity_loss(gt + 0.3, gt).item() == pytest.approx(0.0, abs=1e-24)  # constant offset
    drift = gt + torch.arange(T, dtype=torch.float64)[None, :, None, None] * torch.tensor(
        [0.0, 0.03, 0.04], dtype=torch.float64
    )
    assert joint_velocity_loss(drift, gt).item() == pytest.approx(0.05**2)


def test_bone_length_loss_known_scale():
    gt = still(REST_YUP)
    assert bone_length_loss(gt, gt).item() == 0.0
    scaled = gt[..., :1, :] + 1.1 * (gt - gt[..., :1, :])
    expected = (0.1**2) * (bone_lengths(REST_YUP) ** 2).mean().item()
    assert bone_length_loss(scaled, gt).item() == pytest.approx(expected)
    assert bone_length_loss(yaw(gt, 1.0) + 2.0, gt).item() == pytest.approx(0.0, abs=1e-20)  # rigid motion


def _points(x: float) -> torch.Tensor:
    """Every joint at (x, 0, 0): a degenerate 'person' whose cross distances are all |x_a - x_b|."""
    p = torch.zeros(2, T, 22, 3, dtype=torch.float64)
    p[..., 0] = x
    return p


def test_distance_map_loss_known_offset_and_threshold():
    a = _points(0.0)
    assert distance_map_loss(a, _points(0.5), a, _points(0.5)).item() == 0.0
    assert distance_map_loss(a, _points(0.8), a, _points(0.5)).item() == pytest.approx(0.09)
    # Ground-truth pairs farther than the threshold do not count.
    assert distance_map_loss(a, _points(3.0), a, _points(2.0), threshold=1.0).item() == 0.0
    assert distance_map_loss(a, _points(3.0), a, _points(2.0), threshold=2.5).item() == pytest.approx(1.0)


def test_sync_loss_known_offset_with_distance_and_anatomical_weights():
    a = _points(0.0)
    w = SyncWeights(alpha=1.0, hands=2.0, upper=1.0, lower=1.0, small=0.25)
    assert sync_loss(a, _points(0.5), a, _points(0.5), weights=w).item() == 0.0
    n_h, n_u, n_l = len(HAND_JOINTS), len(UPPER_JOINTS), len(LOWER_JOINTS)
    same = n_h**2 + n_u**2 + n_l**2
    mean_wj = (2.0 * n_h**2 + n_u**2 + n_l**2 + 0.25 * (484 - same)) / 484
    expected = math.exp(-0.5) * 0.3**2 * mean_wj
    assert sync_loss(a, _points(0.8), a, _points(0.5), weights=w).item() == pytest.approx(expected)
    # The joint-weight table is symmetric in its groups and has hands on top.
    wj = w.joint_weights()
    assert wj[20, 21] == 2.0 and wj[16, 18] == 1.0 and wj[0, 7] == 1.0 and wj[20, 0] == 0.25 and wj[15, 15] == 0.25
    # Nearer pairs weigh more: the same error at a larger ground-truth distance costs less.
    far = sync_loss(a, _points(2.3), a, _points(2.0), weights=w).item()
    assert far == pytest.approx(math.exp(-2.0) * 0.3**2 * mean_wj)


def test_relative_orientation_loss_known_turn_and_yaw_invariance():
    a = still(REST_YUP)
    b = still(yaw(REST_YUP, math.pi)) + torch.tensor([0.0, 0.0, 1.5], dtype=torch.float64)  # face to face
    assert relative_orientation_loss(a, b, a, b).item() == pytest.approx(0.0, abs=1e-12)
    # Turning B by 90 degrees: (cos, sin) goes from (-1, 0) to (0, +-1): squared error 2.
    b_turned = still(yaw(REST_YUP, math.pi / 2)) + torch.tensor([0.0, 0.0, 1.5], dtype=torch.float64)
    assert relative_orientation_loss(a, b_turned, a, b).item() == pytest.approx(2.0)
    # Rotating the whole pair about the vertical axis changes nothing.
    assert relative_orientation_loss(yaw(a, 0.7), yaw(b, 0.7), a, b).item() == pytest.approx(0.0, abs=1e-12)


def test_triplet_loss_known_values():
    e1 = torch.tensor([1.0, 0.0, 0.0])
    e2 = torch.tensor([0.0, 1.0, 0.0])
    labels = torch.tensor([0, 0, 1])
    # Anchor and positive identical, negative orthogonal: d+ = 0, d- = 1 -> max(0, 0 - 1 + 0.2) = 0.
    assert triplet_loss(torch.stack([e1, e1, e2]), labels=labels).item() == pytest.approx(0.0)
    # v = (e1, e2, e1). Anchor 0: positive 1 orthogonal (d = 1), negative 2 identical (d = 0):
    # 1 - 0 + 0.2 = 1.2. Anchor 1: positive 0 and negative 2 both orthogonal: 1 - 1 + 0.2 = 0.2.
    # Anchor 2 (label 1) has no positive. Mean over the two triplets: 0.7.
    assert triplet_loss(torch.stack([e1, e2, e1]), labels=labels).item() == pytest.approx(0.7)
    # Same choice from text similarity: texts 0 and 1 alike (cos 0.96), text 2 unrelated.
    text = torch.tensor([[1.0, 0.0], [0.96, 0.28], [0.0, 1.0]])
    assert triplet_loss(torch.stack([e1, e2, e1]), text=text).item() == pytest.approx(0.7)
    # Scale does not matter (cosine distance); no text and no labels -> 0 with a graph.
    v = torch.stack([e1, e2, e1]).requires_grad_(True)
    assert triplet_loss(3.0 * v, text=text).item() == pytest.approx(0.7)
    # A larger margin adds to every active triplet.
    assert triplet_loss(v, text=text, margin=0.5).item() == pytest.approx(1.0)
    zero = triplet_loss(v)
    assert zero.item() == 0.0 and zero.requires_grad


def _pair_batch():
    a = still(REST_YUP)
    b = still(yaw(REST_YUP, math.pi)) + torch.tensor([0.0, 0.0, 0.8], dtype=torch.float64)
    return features(a), features(b)


def test_dualflow_losses_are_zero_for_a_perfect_prediction_and_weighted():
    fa, fb = _pair_batch()
    mean, std = torch.zeros(262, dtype=torch.float64), torch.ones(262, dtype=torch.float64)
    zero_v = torch.zeros_like(fa)
    truth = CleanBatch(x0_a=fa, x0_b=fb, mean=mean, std=std)
    terms = dualflow_losses(Prediction(torch.tensor(0.5, dtype=torch.float64), zero_v, zero_v, fa, fb), truth)
    assert set(terms) == {"flow", "triplet", "foot", "vel", "bone", "dm", "ro", "sync", "total"}
    assert terms["total"].item() == pytest.approx(0.5)
    for name in ("triplet", "foot", "vel", "bone", "dm", "ro", "sync"):
        assert terms[name].item() == pytest.approx(0.0, abs=1e-12), name
    # A known slide of the reactor's whole body: foot = 30 * |u|^2 averaged over 2 persons,
    # vel = 30 * |u|^2 / 2, and the distance-based terms become non-zero.
    u = torch.tensor([0.01, 0.0, 0.0], dtype=torch.float64)
    pos_b = joint_positions(fb) + torch.arange(T, dtype=torch.float64)[None, :, None, None] * u
    slid = Prediction(torch.tensor(0.0), zero_v, zero_v, fa, features(pos_b))
    terms = dualflow_losses(slid, truth)
    assert terms["foot"].item() == pytest.approx(30 * 1e-4 / 2)
    assert terms["vel"].item() == pytest.approx(30 * 1e-4 / 2)
    assert terms["bone"].item() == pytest.approx(0.0, abs=1e-12)
    assert terms["sync"].item() > 0 and terms["dm"].item() > 0
    custom = dualflow_losses(slid, truth, settings=LossSettings(weights=LossWeights(geo=2.0)))
    assert custom["foot"].item() == pytest.approx(2 * terms["foot"].item())


def test_reactive_losses_use_the_ground_truth_actor():
    fa, fb = _pair_batch()
    mean, std = torch.zeros(262, dtype=torch.float64), torch.ones(262, dtype=torch.float64)
    zero_v = torch.zeros_like(fa)
    wrong_actor = fa.clone()
    wrong_actor[..., FEATURE_SLICES["positions"]] += 0.3
    pred = Prediction(flow=torch.tensor(0.0), v_a=zero_v, v_b=zero_v, x0_hat_a=wrong_actor, x0_hat_b=fb)
    truth = CleanBatch(x0_a=fa, x0_b=fb, mean=mean, std=std)
    reactive = dualflow_losses(pred, truth, mode="reactive")
    interactive = dualflow_losses(pred, truth, mode="interactive")
    assert reactive["total"].item() == pytest.approx(0.0, abs=1e-12)
    assert interactive["dm"].item() > 0 and interactive["sync"].item() > 0


def test_frame_mask_ignores_padded_frames():
    gt = still(REST_YUP)
    pred = gt.clone()
    pred[:, -2:] += 5.0  # garbage on the padding only
    mask = torch.ones(2, T, dtype=torch.bool)
    mask[:, -2:] = False
    assert joint_velocity_loss(pred, gt, mask).item() == 0.0
    assert bone_length_loss(pred * 3, gt * 3, mask).item() == 0.0
    a = _points(0.0)
    b_pred = _points(0.5)
    b_pred[:, -2:] = 0.9
    assert sync_loss(a, b_pred, a, _points(0.5), mask).item() == 0.0
    assert distance_map_loss(a, b_pred, a, _points(0.5), mask).item() == 0.0


def test_step_losses_backpropagate_through_a_model_step():
    """The trainer's one call: all terms are finite and the total reaches the network's weights."""
    from dualflow.flow import flow_training_step
    from dualflow.losses import step_losses
    from dualflow.model import Conditions, DualFlow, DualFlowConfig

    torch.manual_seed(0)
    model = DualFlow(DualFlowConfig.preset("tiny"))
    fa, fb = _pair_batch()
    mean = torch.zeros(262)
    std = torch.full((262,), 0.5)
    x0_a, x0_b = fa.float() / 0.5, fb.float() / 0.5
    text = torch.randn(2, 384)
    for mode in ("interactive", "reactive"):
        out = flow_training_step(
            model, x0_a, x0_b, Conditions(text=text), mode=mode, generator=torch.Generator().manual_seed(0)
        )
        terms = step_losses(out, x0_a, x0_b, mean, std, mode=mode, labels=torch.tensor([0, 1]))
        assert all(torch.isfinite(v) for v in terms.values())
        assert terms["total"].item() > terms["flow"].item()  # x0_hat of an untrained model is off
        model.zero_grad()
        terms["total"].backward()
        assert model.out_b.weight.grad.abs().sum() > 0
