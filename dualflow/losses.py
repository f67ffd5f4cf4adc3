"""DualFlow's training losses (paper eq. 2-10, appendix D.5), in metric units.

Contract: every geometric and interaction term works on the predicted clean motion
x0_hat = x_t + (1 - t) v_hat de-normalised to the feature's units (metres in the canonical Y-up
frame, metres per frame, contacts 0/1); :class:`LossWeights` defaults are the paper's
(L_flow + 0.1 L_triplet + 30 L_foot + 30 L_vel + 10 L_BL + 3 L_DM + 0.01 L_RO + 5 L_sync).
Per-person terms average over the generated people; in reactive mode the interaction terms pair
the predicted reactor with the true actor. Every loss takes an optional frame_mask (B, T) bool.
Each term's definition: docs/model.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from dualflow.errors import DualFlowError
from dualflow.motion.features import FEATURE_DIM, FEATURE_SLICES
from dualflow.motion.skeleton import FACE_JOINTS, FOOT_JOINTS, N_JOINTS, PARENTS

#: Vertical axis of the Y-up feature frame.
UP_AXIS = 1

# ---------------------------------------------------------------------------------------------
# Weights
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class LossWeights:
    """Weights of the loss terms (defaults: paper sec. 3.4 and appendix D.5)."""

    flow: float = 1.0
    triplet: float = 0.1
    foot: float = 30.0
    vel: float = 30.0
    bone: float = 10.0
    dm: float = 3.0
    ro: float = 0.01
    sync: float = 5.0
    geo: float = 1.0  # lambda_geo of eq. 10
    inter: float = 1.0  # lambda_inter of eq. 10


#: Anatomical groups of eq. 8 (SMPL-22 indices). The SMPL body has no finger joints, so
#: "hands" are the wrists; "upper" is shoulders, elbows and the torso (spine, collars);
#: "lower" is pelvis, hips, knees, ankles and feet; neck and head fall in "other".
HAND_JOINTS: tuple[int, ...] = (20, 21)
UPPER_JOINTS: tuple[int, ...] = (3, 6, 9, 13, 14, 16, 17, 18, 19)
LOWER_JOINTS: tuple[int, ...] = (0, 1, 2, 4, 5, 7, 8, 10, 11)


@dataclass(frozen=True)
class SyncWeights:
    """w_d = exp(-alpha d_gt) with alpha in 1/m; w_j = hands / upper / lower / small (eq. 7-8).

    The paper does not publish the values; these favour hand-to-hand pairs (duets hold hands)
    and keep cross-group pairs at a small weight.
    """

    alpha: float = 1.0
    hands: float = 2.0
    upper: float = 1.0
    lower: float = 1.0
    small: float = 0.25

    def joint_weights(self, device=None) -> torch.Tensor:
        """w_j (22, 22): row = joint of person A, column = joint of person B."""
        group = torch.full((N_JOINTS,), -1)
        group[list(HAND_JOINTS)] = 0
        group[list(UPPER_JOINTS)] = 1
        group[list(LOWER_JOINTS)] = 2
        values = torch.tensor([self.hands, self.upper, self.lower])
        same = group[:, None] == group[None, :]
        w = torch.where(
            same & (group[:, None] >= 0),
            values[group.clamp_min(0)][:, None].expand(-1, N_JOINTS),
            torch.tensor(self.small),
        )
        return w.to(device)


# ---------------------------------------------------------------------------------------------
# Features -> metric quantities
# ---------------------------------------------------------------------------------------------


def denormalize(x: torch.Tensor, mean, std) -> torch.Tensor:
    """features = normalized * std + mean; mean/std (262,) tensors or arrays (NormStats fields)."""
    mean = torch.as_tensor(mean, dtype=x.dtype, device=x.device)
    std = torch.as_tensor(std, dtype=x.dtype, device=x.device)
    if mean.shape != (FEATURE_DIM,) or std.shape != (FEATURE_DIM,):
        raise DualFlowError(
            f"normalization mean/std must have shape ({FEATURE_DIM},), got {tuple(mean.shape)}, {tuple(std.shape)}"
        )
    return x * std + mean


def joint_positions(features: torch.Tensor) -> torch.Tensor:
    """(B, T, 262) de-normalised features -> joint positions (B, T, 22, 3), metres, Y-up."""
    return features[..., FEATURE_SLICES["positions"]].reshape(*features.shape[:-1], N_JOINTS, 3)


def foot_contacts(features: torch.Tensor) -> torch.Tensor:
    """(B, T, 262) de-normalised features -> contact labels (B, T, 4) in {0, 1} (threshold 0.5)."""
    return (features[..., FEATURE_SLICES["contacts"]] > 0.5).to(features.dtype)


def _masked_mean(values: torch.Tensor, frame_mask: torch.Tensor | None) -> torch.Tensor:
    """Mean of values (B, T, ...) over real frames (frame_mask (B, T)) and all trailing dims."""
    if frame_mask is None:
        return values.mean()
    m = frame_mask.to(values.dtype).reshape(frame_mask.shape + (1,) * (values.ndim - 2))
    per_frame = values[0, 0].numel()
    return (values * m).sum() / (m.sum() * per_frame).clamp_min(1.0)


def _pair_mask(frame_mask: torch.Tensor | None) -> torch.Tensor | None:
    """Mask of frame differences t -> t+1: both frames real. (B, T) -> (B, T-1)."""
    return None if frame_mask is None else frame_mask[:, 1:] & frame_mask[:, :-1]


# ---------------------------------------------------------------------------------------------
# Geometric losses (eq. 5)
# ---------------------------------------------------------------------------------------------


def foot_contact_loss(pos_pred: torch.Tensor, contacts_gt: torch.Tensor, frame_mask=None) -> torch.Tensor:
    """L_foot = mean c_gt[t] ||p_hat[t+1] - p_hat[t]||^2 over the 4 foot joints; m^2/frame^2.

    pos_pred (B, T, 22, 3); contacts_gt (B, T, 4) in FOOT_JOINTS order.
    """
    feet = pos_pred[:, :, list(FOOT_JOINTS)]
    slide = ((feet[:, 1:] - feet[:, :-1]) ** 2).sum(-1)  # (B, T-1, 4)
    return _masked_mean(slide * contacts_gt[:, :-1], _pair_mask(frame_mask))


def joint_velocity_loss(pos_pred: torch.Tensor, pos_gt: torch.Tensor, frame_mask=None) -> torch.Tensor:
    """L_vel = mean ||dp_hat - dp||^2 over frames and joints, dp[t] = p[t+1] - p[t]; m^2/frame^2."""
    d_pred = pos_pred[:, 1:] - pos_pred[:, :-1]
    d_gt = pos_gt[:, 1:] - pos_gt[:, :-1]
    return _masked_mean(((d_pred - d_gt) ** 2).sum(-1), _pair_mask(frame_mask))


def bone_lengths(pos: torch.Tensor) -> torch.Tensor:
    """(..., 22, 3) -> (..., 21) length of the bone ending at each non-root joint, metres."""
    return torch.linalg.vector_norm(pos[..., 1:, :] - pos[..., list(PARENTS[1:]), :], dim=-1)


def bone_length_loss(pos_pred: torch.Tensor, pos_gt: torch.Tensor, frame_mask=None) -> torch.Tensor:
    """L_BL = mean (|bone_hat| - |bone|)^2 over frames and the 21 bones; m^2."""
    return _masked_mean((bone_lengths(pos_pred) - bone_lengths(pos_gt)) ** 2, frame_mask)


# ---------------------------------------------------------------------------------------------
# Interaction losses (eq. 6-9)
# ---------------------------------------------------------------------------------------------


def cross_distances(pos_a: torch.Tensor, pos_b: torch.Tensor) -> torch.Tensor:
    """d(j1, j2) = ||p_A[j1] - p_B[j2]||: (B, T, 22, 3) x2 -> (B, T, 22, 22), metres."""
    return torch.linalg.vector_norm(pos_a[..., :, None, :] - pos_b[..., None, :, :], dim=-1)


def distance_map_loss(pos_a, pos_b, pos_a_gt, pos_b_gt, frame_mask=None, threshold: float = 1.0) -> torch.Tensor:
    """L_DM = mean of (d_p - d_gt)^2 over joint pairs with d_gt < threshold (m) in real frames; m^2."""
    d_p = cross_distances(pos_a, pos_b)
    d_gt = cross_distances(pos_a_gt, pos_b_gt)
    near = (d_gt < threshold).to(d_p.dtype)
    if frame_mask is not None:
        near = near * frame_mask.to(d_p.dtype)[..., None, None]
    return ((d_p - d_gt) ** 2 * near).sum() / near.sum().clamp_min(1.0)


def facing_direction(pos: torch.Tensor) -> torch.Tensor:
    """Unit horizontal facing (B, T, 3) in the Y-up frame: forward = up x across, y zeroed.

    across = (r_hip - l_hip) + (r_shoulder - l_shoulder) (FACE_JOINTS = r_hip, l_hip, r_sho, l_sho).
    """
    r_hip, l_hip, r_sho, l_sho = FACE_JOINTS
    across = (pos[..., r_hip, :] - pos[..., l_hip, :]) + (pos[..., r_sho, :] - pos[..., l_sho, :])
    up = torch.zeros_like(across)
    up[..., UP_AXIS] = 1.0
    forward = torch.linalg.cross(up, across, dim=-1)
    forward = forward.clone()
    forward[..., UP_AXIS] = 0.0
    return F.normalize(forward, dim=-1, eps=1e-8)


def relative_orientation(pos_a: torch.Tensor, pos_b: torch.Tensor) -> torch.Tensor:
    """(cos psi, sin psi) (B, T, 2) of B's facing relative to A's about the vertical axis."""
    f_a, f_b = facing_direction(pos_a), facing_direction(pos_b)
    cos = (f_a * f_b).sum(-1)
    sin = torch.linalg.cross(f_a, f_b, dim=-1)[..., UP_AXIS]
    return torch.stack([cos, sin], dim=-1)


def relative_orientation_loss(pos_a, pos_b, pos_a_gt, pos_b_gt, frame_mask=None) -> torch.Tensor:
    """L_RO = mean ||r_hat - r_gt||^2, r = (cos, sin) of the relative yaw; dimensionless."""
    r_p = relative_orientation(pos_a, pos_b)
    r_gt = relative_orientation(pos_a_gt, pos_b_gt)
    return _masked_mean(((r_p - r_gt) ** 2).sum(-1), frame_mask)


def sync_loss(pos_a, pos_b, pos_a_gt, pos_b_gt, frame_mask=None, weights: SyncWeights = SyncWeights()) -> torch.Tensor:
    """L_sync = mean_{b,t} mean_{j1,j2} w_d w_j (d_p - d_gt)^2, w_d = exp(-alpha d_gt) (eq. 6-8); m^2."""
    d_p = cross_distances(pos_a, pos_b)
    d_gt = cross_distances(pos_a_gt, pos_b_gt)
    w = torch.exp(-weights.alpha * d_gt) * weights.joint_weights(d_p.device).to(d_p.dtype)
    return _masked_mean(w * (d_p - d_gt) ** 2, frame_mask)


# ---------------------------------------------------------------------------------------------
# Triplet contrastive loss (eq. 3)
# ---------------------------------------------------------------------------------------------


def triplet_loss(
    velocities: torch.Tensor,
    text: torch.Tensor | None = None,
    labels: torch.Tensor | None = None,
    *,
    margin: float = 0.2,
    positive_similarity: float = 0.8,
    negative_similarity: float = 0.4,
) -> torch.Tensor:
    """L_triplet = mean over (anchor, positive, negative) of max(0, d(v, v+) - d(v, v-) + m).

    velocities (B, ...) predicted velocities, flattened per sample; d = 1 - cosine similarity.
    Positives / negatives of anchor i, among the other samples of the batch:
      labels (B,) int given (style / genre / rule): positive = same label, negative = other label;
      else text (B, D_text): positive if cos(text_i, text_j) >= positive_similarity,
      negative if cos(text_i, text_j) <= negative_similarity (cosine distance >= 0.6, the
      paper's "low text similarity (> 0.6)").
    Every sample is an anchor and every valid (positive, negative) pair counts (the paper picks
    one random anchor per batch; averaging over all has the same expectation, less variance).
    Returns 0 (attached to the graph) when no triplet exists or neither text nor labels are given.
    """
    b = velocities.shape[0]
    v = F.normalize(velocities.reshape(b, -1), dim=-1, eps=1e-8)
    dist = 1.0 - v @ v.T  # (B, B)
    zero = velocities.sum() * 0.0
    eye = torch.eye(b, dtype=torch.bool, device=velocities.device)
    if labels is not None:
        labels = labels.to(velocities.device)
        same = labels[:, None] == labels[None, :]
        pos, neg = same & ~eye, ~same
    elif text is not None:
        t = F.normalize(text.to(velocities.device, velocities.dtype), dim=-1, eps=1e-8)
        sim = t @ t.T
        pos, neg = (sim >= positive_similarity) & ~eye, (sim <= negative_similarity) & ~eye
    else:
        return zero
    # valid[i, p, n]: p is a positive and n a negative of anchor i. A weighted mean rather than
    # `valid.any()` and boolean indexing: no data-dependent shape, so no host sync on a GPU.
    valid = (pos[:, :, None] & neg[:, None, :]).to(dist.dtype)
    hinge = F.relu(dist[:, :, None] - dist[:, None, :] + margin)
    return (hinge * valid).sum() / valid.sum().clamp_min(1.0) + zero


# ---------------------------------------------------------------------------------------------
# Everything together (eq. 10)
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class LossSettings:
    """Weights and thresholds of :func:`dualflow_losses`: the term weights, the sync loss's
    pair weights, and the distance-map threshold in metres (only pairs nearer than it count)."""

    weights: LossWeights = LossWeights()
    sync_weights: SyncWeights = SyncWeights()
    dm_threshold: float = 1.0


@dataclass(frozen=True)
class Prediction:
    """What the network predicted for a batch: flow = L_flow (scalar), v_a / v_b the velocities,
    x0_hat_a / x0_hat_b the predicted clean motions, all normalised (B, T, 262)."""

    flow: torch.Tensor
    v_a: torch.Tensor
    v_b: torch.Tensor
    x0_hat_a: torch.Tensor
    x0_hat_b: torch.Tensor

    @classmethod
    def from_step(cls, step) -> Prediction:
        """From a ``dualflow.flow.FlowStep``."""
        return cls(step.loss, step.v_a, step.v_b, step.x0_hat_a, step.x0_hat_b)


@dataclass(frozen=True)
class CleanBatch:
    """The ground truth of a batch: normalised clean motions x0_a / x0_b (B, T, 262) and the
    (262,) mean / std (tensors or arrays) that de-normalise them."""

    x0_a: torch.Tensor
    x0_b: torch.Tensor
    mean: torch.Tensor | np.ndarray
    std: torch.Tensor | np.ndarray


def dualflow_losses(
    pred: Prediction,
    truth: CleanBatch,
    *,
    mode: str = "interactive",
    text: torch.Tensor | None = None,
    labels: torch.Tensor | None = None,
    frame_mask: torch.Tensor | None = None,
    settings: LossSettings = LossSettings(),
) -> dict[str, torch.Tensor]:
    """Weighted loss terms and their sum: {"flow", "triplet", "foot", "vel", "bone", "dm", "ro",
    "sync", "total"} (scalars; each term already multiplied by its weight(s), see module docstring).

    pred: the network's prediction (``Prediction.from_step`` of a ``dualflow.flow.FlowStep``);
    truth: the clean batch and its normalisation stats. mode "reactive": geometric losses on the
    reactor only, interaction losses between the ground-truth actor and the predicted reactor.
    text (B, D) / labels (B,) pick triplet positives; frame_mask (B, T) bool marks real frames.
    """
    if mode not in ("interactive", "reactive"):
        raise DualFlowError(f"mode must be 'interactive' or 'reactive', got {mode!r}")
    w = settings.weights
    x0_a, mean, std = truth.x0_a, truth.mean, truth.std
    feat_hat_b = denormalize(pred.x0_hat_b, mean, std)
    feat_b = denormalize(truth.x0_b, mean, std)
    feat_a = denormalize(x0_a, mean, std)
    p_hat_b, p_b, p_a = joint_positions(feat_hat_b), joint_positions(feat_b), joint_positions(feat_a)
    if mode == "reactive":
        p_hat_a = p_a  # eq. 9's note: the ground-truth actor
        persons = [(p_hat_b, p_b, feat_b)]
    else:
        p_hat_a = joint_positions(denormalize(pred.x0_hat_a, mean, std))
        persons = [(p_hat_a, p_a, feat_a), (p_hat_b, p_b, feat_b)]

    def per_person(fn) -> torch.Tensor:
        return sum(fn(pred, gt, feat) for pred, gt, feat in persons) / len(persons)

    foot = per_person(lambda pred, gt, feat: foot_contact_loss(pred, foot_contacts(feat), frame_mask))
    vel = per_person(lambda pred, gt, feat: joint_velocity_loss(pred, gt, frame_mask))
    bone = per_person(lambda pred, gt, feat: bone_length_loss(pred, gt, frame_mask))
    dm = distance_map_loss(p_hat_a, p_hat_b, p_a, p_b, frame_mask, settings.dm_threshold)
    ro = relative_orientation_loss(p_hat_a, p_hat_b, p_a, p_b, frame_mask)
    sync = sync_loss(p_hat_a, p_hat_b, p_a, p_b, frame_mask, settings.sync_weights)
    v = torch.cat([pred.v_a, pred.v_b], -1)
    if frame_mask is not None:
        v = v * frame_mask.to(v.dtype)[..., None]
    triplet = triplet_loss(v, text, labels)

    terms = {
        "flow": w.flow * pred.flow,
        "triplet": w.triplet * triplet,
        "foot": w.geo * w.foot * foot,
        "vel": w.geo * w.vel * vel,
        "bone": w.geo * w.bone * bone,
        "dm": w.inter * w.dm * dm,
        "ro": w.inter * w.ro * ro,
        "sync": w.inter * w.sync * sync,
    }
    terms["total"] = sum(terms.values())
    return terms


def step_losses(step, x0_a: torch.Tensor, x0_b: torch.Tensor, mean, std, **kwargs) -> dict[str, torch.Tensor]:
    """``dualflow_losses`` for a ``dualflow.flow.FlowStep`` and its clean batch (normalised x0_a, x0_b).

    The trainer's one call: ``terms = step_losses(out, x0_a, x0_b, stats.mean, stats.std,
    mode=mode, text=cond.text, labels=batch["rule"])``; ``terms["total"].backward()``.
    kwargs: mode, text, labels, frame_mask, settings (a ``LossSettings``).
    """
    return dualflow_losses(Prediction.from_step(step), CleanBatch(x0_a, x0_b, mean, std), **kwargs)
