"""DD100's duet and solo dance metrics where the data allows (numpy only).

Contract: FID_cd / Div_cd over duet features (mean distances between 10 key joints of follower
and leader), FID_k / Div_k over per-joint kinetic features, FID_g / Div_g over boolean
relational pose features measured in a body frame (:data:`GEOMETRIC_FEATURES`). Positions are
metres (Z-up world or canonical). The kinetic and geometric features are our own
implementations: their values compare our runs, not published tables. Details: docs/model.md.
"""

from __future__ import annotations

import numpy as np

from dualflow.errors import DualFlowError
from dualflow.evaluation.metrics import fid

DUET_KEY_JOINTS: tuple[int, ...] = (0, 7, 8, 10, 11, 15, 16, 17, 20, 21)


def _positions(p, what: str) -> np.ndarray:
    a = np.asarray(p, dtype=np.float64)
    if a.ndim != 3 or a.shape[1] < 22 or a.shape[2] != 3 or len(a) < 3:
        raise DualFlowError(f"{what}: expected (T >= 3, 22, 3) positions, got {a.shape}")
    return a


def duet_feature(follower, leader) -> np.ndarray:
    """(100,) time-mean of the 10 × 10 key-joint distance matrix (follower rows, leader columns)."""
    f = _positions(follower, "duet feature follower")[:, DUET_KEY_JOINTS]
    ld = _positions(leader, "duet feature leader")[:, DUET_KEY_JOINTS]
    n = min(len(f), len(ld))
    return np.linalg.norm(f[:n, :, None] - ld[:n, None, :], axis=-1).reshape(n, -1).mean(axis=0)


def kinetic_feature(positions, fps: float = 30.0, up: int = 2) -> np.ndarray:
    """(66,) per-joint [horizontal KE, vertical KE, energy expenditure] (module docstring)."""
    p = _positions(positions, "kinetic feature")[:, :22]
    rel = p - p[:, :1]
    rel[:, 0] = p[:, 0]  # the root keeps its own trajectory
    v = np.diff(rel, axis=0) * fps
    a = np.diff(v, axis=0) * fps
    horiz = [i for i in range(3) if i != up]
    ke_h = 0.5 * (v[..., horiz] ** 2).sum(-1).mean(0)
    ke_v = 0.5 * (v[..., up] ** 2).mean(0)
    energy = (np.linalg.norm(a, axis=-1) * np.linalg.norm(v[1:], axis=-1)).mean(0)
    return np.stack([ke_h, ke_v, energy], axis=1).reshape(-1)


#: SMPL joint indices used by the geometric relations
_J = {
    "pelvis": 0,
    "l_hip": 1,
    "r_hip": 2,
    "l_knee": 4,
    "r_knee": 5,
    "l_ankle": 7,
    "r_ankle": 8,
    "spine3": 9,
    "neck": 12,
    "head": 15,
    "l_shoulder": 16,
    "r_shoulder": 17,
    "l_elbow": 18,
    "r_elbow": 19,
    "l_wrist": 20,
    "r_wrist": 21,
}

#: Names of the relations of :func:`geometric_feature`, in output order ({s} = l, r).
GEOMETRIC_FEATURES: tuple[str, ...] = tuple(
    f"{s}_{name}"
    for s in ("l", "r")
    for name in (
        "wrist_in_front",
        "wrist_behind",
        "wrist_above_neck",
        "wrist_below_pelvis",
        "wrist_out_sideways",
        "elbow_bent",
        "arm_stretched",
        "knee_bent",
        "foot_raised",
        "foot_in_front",
        "foot_out_sideways",
        "wrist_fast",
        "ankle_fast",
    )
) + ("hands_together", "hands_apart", "feet_apart", "head_forward", "pelvis_fast", "turning")


def _unit_rows(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-9)


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    cos = np.sum(_unit_rows(a) * _unit_rows(b), axis=-1)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def geometric_feature(positions, fps: float = 30.0) -> np.ndarray:
    """(len(GEOMETRIC_FEATURES),) fractions of frames where each boolean relation holds (module docstring).

    positions (T >= 3, 22, 3) metres, any world axes. Body frame per frame: u = unit(neck − pelvis),
    r = the component of (r_hip − l_hip) + (r_shoulder − l_shoulder) orthogonal to u, normalised,
    f = u × r (forward). Scales of the clip: hl = mean humerus length, sw = mean shoulder width,
    hw = mean hip width. Per side: wrist in front of / behind the chest plane through the neck by
    0.3 hl; wrist above the neck / below the pelvis along u; wrist out sideways beyond the shoulder
    by 0.5 hl; elbow angle < 110°; wrist farther than 1.8 hl from the shoulder; knee angle < 140°;
    ankle 0.3 hl above the other along u; ankle 0.6 hl in front of / 0.6 hl sideways from the hip;
    wrist and ankle speed above 2.5 hl/s. Both: wrists closer than 0.5 sw / farther than 2.5 sw;
    ankles farther than 2 hw; head 0.5 hl in front of the pelvis; pelvis faster than 1.5 hl/s;
    forward direction turning faster than 90°/s. Velocities by finite differences between
    frames t − 1 and t, so every relation is averaged over frames 1 … T − 1.
    """
    p = _positions(positions, "geometric feature")[:, :22]
    j = {k: p[:, v] for k, v in _J.items()}
    up = _unit_rows(j["neck"] - j["pelvis"])
    side = (j["r_hip"] - j["l_hip"]) + (j["r_shoulder"] - j["l_shoulder"])
    right = _unit_rows(side - np.sum(side * up, axis=-1, keepdims=True) * up)
    fwd = np.cross(up, right)
    hl = float(np.mean([np.linalg.norm(j[f"{s}_elbow"] - j[f"{s}_shoulder"], axis=-1).mean() for s in "lr"]))
    sw = float(np.linalg.norm(j["r_shoulder"] - j["l_shoulder"], axis=-1).mean())
    hw = float(np.linalg.norm(j["r_hip"] - j["l_hip"], axis=-1).mean())
    hl, sw, hw = max(hl, 1e-3), max(sw, 1e-3), max(hw, 1e-3)

    def along(v, axis):
        return np.sum(v * axis, axis=-1)

    def speed(x):
        v = np.zeros(len(x))
        v[1:] = np.linalg.norm(np.diff(x, axis=0), axis=-1) * fps
        return v

    rel: list[np.ndarray] = []
    for s, o in (("l", "r"), ("r", "l")):
        sign = -1.0 if s == "l" else 1.0  # the left side lies along −right
        wrist, shoulder, elbow = j[f"{s}_wrist"], j[f"{s}_shoulder"], j[f"{s}_elbow"]
        hip, knee, ankle = j[f"{s}_hip"], j[f"{s}_knee"], j[f"{s}_ankle"]
        rel += [
            along(wrist - j["neck"], fwd) > 0.3 * hl,
            along(wrist - j["neck"], fwd) < -0.3 * hl,
            along(wrist - j["neck"], up) > 0.0,
            along(wrist - j["pelvis"], up) < 0.0,
            sign * along(wrist - shoulder, right) > 0.5 * hl,
            _angle_deg(shoulder - elbow, wrist - elbow) < 110.0,
            np.linalg.norm(wrist - shoulder, axis=-1) > 1.8 * hl,
            _angle_deg(hip - knee, ankle - knee) < 140.0,
            along(ankle - j[f"{o}_ankle"], up) > 0.3 * hl,
            along(ankle - hip, fwd) > 0.6 * hl,
            sign * along(ankle - hip, right) > 0.6 * hl,
            speed(wrist) > 2.5 * hl,
            speed(ankle) > 2.5 * hl,
        ]
    turn = np.zeros(len(p))
    turn[1:] = _angle_deg(fwd[1:], fwd[:-1]) * fps
    rel += [
        np.linalg.norm(j["l_wrist"] - j["r_wrist"], axis=-1) < 0.5 * sw,
        np.linalg.norm(j["l_wrist"] - j["r_wrist"], axis=-1) > 2.5 * sw,
        np.linalg.norm(j["l_ankle"] - j["r_ankle"], axis=-1) > 2.0 * hw,
        along(j["head"] - j["pelvis"], fwd) > 0.5 * hl,
        speed(j["pelvis"]) > 1.5 * hl,
        turn > 90.0,
    ]
    return np.stack(rel, axis=1)[1:].mean(axis=0).astype(np.float64)


def _standardise(gt: np.ndarray, gen: np.ndarray, floor: float = 1e-10) -> tuple[np.ndarray, np.ndarray]:
    """Both sets standardised with the ground truth's per-dimension mean and std (+ ``floor``)."""
    mean, std = gt.mean(0), gt.std(0) + floor
    return (gt - mean) / std, (gen - mean) / std


#: std floor of the geometric fractions: a relation that never changes over the ground truth
#: (e.g. never "turning") would otherwise scale any generated change by 1e10.
GEOMETRIC_STD_FLOOR = 0.01


def mean_pairwise_distance(feats) -> float:
    x = np.asarray(feats, dtype=np.float64)
    n = len(x)
    if n < 2:
        return float("nan")
    d = np.linalg.norm(x[:, None] - x[None, :], axis=-1)
    return float(d.sum() / (n * (n - 1)))


def dd100_metrics(gen_pairs, gt_pairs, fps: float = 30.0) -> dict[str, float]:
    """{'fid_k', 'div_k', 'fid_g', 'div_g', 'fid_cd', 'div_cd'} of generated vs ground-truth
    (leader, follower) position pairs (lists of ((T, 22, 3), (T, 22, 3)))."""
    if len(gen_pairs) < 2 or len(gt_pairs) < 2:
        raise DualFlowError("DD100 metrics need at least 2 generated and 2 ground-truth clips")
    gt_k = np.stack([kinetic_feature(f, fps) for _, f in gt_pairs])
    gen_k = np.stack([kinetic_feature(f, fps) for _, f in gen_pairs])
    gt_cd = np.stack([duet_feature(f, ld) for ld, f in gt_pairs])
    gen_cd = np.stack([duet_feature(f, ld) for ld, f in gen_pairs])
    gt_k, gen_k = _standardise(gt_k, gen_k)
    gt_cd, gen_cd = _standardise(gt_cd, gen_cd)
    gt_g = np.stack([geometric_feature(f, fps) for _, f in gt_pairs])
    gen_g = np.stack([geometric_feature(f, fps) for _, f in gen_pairs])
    gt_g, gen_g = _standardise(gt_g, gen_g, GEOMETRIC_STD_FLOOR)
    return {
        "fid_k": fid(gen_k, gt_k),
        "div_k": mean_pairwise_distance(gen_k),
        "fid_g": fid(gen_g, gt_g),
        "div_g": mean_pairwise_distance(gen_g),
        "fid_cd": fid(gen_cd, gt_cd),
        "div_cd": mean_pairwise_distance(gen_cd),
    }
