"""Is a generated partner a plausible human body? Figures on world positions (numpy only).

All inputs are (T, 22, 3) SMPL-22 joint positions in metres, Z up, floor at z = 0, at ``fps``
frames per second (DESIGN.md). The definitions (issue 28):

* contact: a foot (ankle and toe joint of one side) touches the floor when its ankle is below
  ``CONTACT_ANKLE_M`` or its toe below ``CONTACT_TOE_M``;
* skate: the share of contact frames (both feet pooled) whose ankle moves horizontally faster
  than ``SKATE_SPEED`` m/s (speed from the forward difference);
* jerk: mean over frames and joints of |third difference of positions| * fps^3 (m/s^3);
* bone-length CV: per bone, std / mean of its length over time; the mean over the 21 bones;
* facing error: mean angle (degrees) between where the partner faces (up x (right hip - left
  hip + right shoulder - left shoulder)) and the horizontal direction to the actor's pelvis;
* distance: pelvis-to-pelvis horizontal distance (m);
* MPJPE: mean per-joint distance to a reference body (m), frames paired by index.
"""

from __future__ import annotations

import numpy as np

from dualflow.motion.skeleton import FACE_JOINTS, bone_lengths

CONTACT_ANKLE_M = 0.10
CONTACT_TOE_M = 0.05
SKATE_SPEED = 0.3
FEET = ((7, 10), (8, 11))  # (ankle, toe) of the left and the right foot


def foot_contacts(p: np.ndarray) -> np.ndarray:
    """(T, 2) bool: left / right foot in contact (the height rule above)."""
    return np.stack([(p[:, a, 2] < CONTACT_ANKLE_M) | (p[:, t, 2] < CONTACT_TOE_M) for a, t in FEET], axis=1)


def skate(p: np.ndarray, fps: float = 30.0) -> float:
    """Share of contact frames with horizontal ankle speed above SKATE_SPEED (0 when no contact)."""
    c = foot_contacts(p)[:-1]
    speed = np.stack([np.linalg.norm(np.diff(p[:, a, :2], axis=0), axis=-1) * fps for a, _ in FEET], axis=1)
    return float((speed[c] > SKATE_SPEED).mean()) if c.any() else 0.0


def jerk(p: np.ndarray, fps: float = 30.0) -> float:
    """Mean |third difference| * fps^3 over frames and joints, m/s^3."""
    if len(p) < 4:
        return 0.0
    return float(np.linalg.norm(np.diff(p, n=3, axis=0), axis=-1).mean() * fps**3)


def bone_cv(p: np.ndarray) -> float:
    """Mean over bones of std / mean of the bone's length over time."""
    lengths = bone_lengths(p)
    return float((lengths.std(0) / np.maximum(lengths.mean(0), 1e-9)).mean())


def facing(p: np.ndarray) -> np.ndarray:
    """(T, 2) horizontal unit vectors the body faces (hips and shoulders, as the features' canonical frame)."""
    rh, lh, rs, ls = FACE_JOINTS  # (right hip, left hip, right shoulder, left shoulder)
    across = (p[:, rh] - p[:, lh]) + (p[:, rs] - p[:, ls])
    fwd = np.stack([-across[:, 1], across[:, 0]], axis=-1)  # z x across, horizontal part (Z up)
    return fwd / np.maximum(np.linalg.norm(fwd, axis=-1, keepdims=True), 1e-9)


def facing_error(partner: np.ndarray, actor: np.ndarray) -> float:
    """Mean angle (deg) between the partner's facing and the direction to the actor's pelvis."""
    n = min(len(partner), len(actor))
    to_actor = actor[:n, 0, :2] - partner[:n, 0, :2]
    to_actor /= np.maximum(np.linalg.norm(to_actor, axis=-1, keepdims=True), 1e-9)
    cos = np.clip(np.sum(facing(partner[:n]) * to_actor, axis=-1), -1.0, 1.0)
    return float(np.degrees(np.arccos(cos)).mean())


def distance(partner: np.ndarray, actor: np.ndarray) -> np.ndarray:
    """(T,) horizontal pelvis-to-pelvis distance, m."""
    n = min(len(partner), len(actor))
    return np.linalg.norm(partner[:n, 0, :2] - actor[:n, 0, :2], axis=-1)


def mpjpe(a: np.ndarray, b: np.ndarray) -> float:
    """Mean per-joint position error (m) over the common frames."""
    n = min(len(a), len(b))
    return float(np.linalg.norm(a[:n] - b[:n], axis=-1).mean())


def diversity(samples: list[np.ndarray]) -> float:
    """Mean pairwise MPJPE (m) between generated partners of one actor (seeds or texts)."""
    pairs = [(i, j) for i in range(len(samples)) for j in range(i + 1, len(samples))]
    return float(np.mean([mpjpe(samples[i], samples[j]) for i, j in pairs])) if pairs else 0.0


def plausibility(
    partner: np.ndarray, actor: np.ndarray, reference: np.ndarray | None = None, fps: float = 30.0
) -> dict:
    """All the figures above for one partner clip (reference: the real partner, for MPJPE)."""
    d = distance(partner, actor)
    out = {
        "skate": skate(partner, fps),
        "jerk": jerk(partner, fps),
        "bone_cv": bone_cv(partner),
        "facing_deg": facing_error(partner, actor),
        "dist_mean": float(d.mean()),
        "dist_in_range": float(((d >= 0.5) & (d <= 1.5)).mean()),
    }
    if reference is not None:
        out["mpjpe_real"] = mpjpe(partner, reference)
    return out
