"""DD100's solo and interactive dance metrics where the data allows (numpy only).

Duolando (Siyao et al. 2024) reports, over generated followers against the test set:

* **FID_cd / Div_cd** (interactive): the *duet feature* of a clip is the matrix of
  distances between 10 key joints of the follower and 10 of the leader, averaged
  over time (100 numbers; joints pelvis, ankles, feet, head, shoulders, wrists =
  SMPL 0, 7, 8, 10, 11, 15, 16, 17, 20, 21, as in Duolando's ``metrics_duet.py``).
  Generated and ground-truth features are standardised with the ground truth's
  per-dimension mean and std; FID_cd is the Fréchet distance between the two
  sets, Div_cd the mean pairwise distance within the generated set.
* **FID_k / Div_k** (solo, kinetic): per-joint kinetic features of the follower
  in the fairmotion/Bailando spirit — positions relative to the root; per joint
  the mean horizontal kinetic energy ½‖v_h‖², the mean vertical kinetic energy
  ½v_z² and the mean energy expenditure ‖a‖·‖v‖ (v, a by finite differences in
  m/s, m/s²), 66 numbers for 22 joints. This is our own implementation of the
  idea, so its values are comparable between our runs, not to published tables.
* FID_g (Bailando's boolean geometric features) is not implemented.

Positions here are the project's Z-up world (or canonical) metres; only
distances and the vertical axis matter.
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


def _standardise(gt: np.ndarray, gen: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    mean, std = gt.mean(0), gt.std(0) + 1e-10
    return (gt - mean) / std, (gen - mean) / std


def mean_pairwise_distance(feats) -> float:
    x = np.asarray(feats, dtype=np.float64)
    n = len(x)
    if n < 2:
        return float("nan")
    d = np.linalg.norm(x[:, None] - x[None, :], axis=-1)
    return float(d.sum() / (n * (n - 1)))


def dd100_metrics(gen_pairs, gt_pairs, fps: float = 30.0) -> dict[str, float]:
    """{'fid_k', 'div_k', 'fid_cd', 'div_cd'} of generated vs ground-truth (leader, follower)
    position pairs (lists of ((T, 22, 3), (T, 22, 3)))."""
    if len(gen_pairs) < 2 or len(gt_pairs) < 2:
        raise DualFlowError("DD100 metrics need at least 2 generated and 2 ground-truth clips")
    gt_k = np.stack([kinetic_feature(f, fps) for _, f in gt_pairs])
    gen_k = np.stack([kinetic_feature(f, fps) for _, f in gen_pairs])
    gt_cd = np.stack([duet_feature(f, ld) for ld, f in gt_pairs])
    gen_cd = np.stack([duet_feature(f, ld) for ld, f in gen_pairs])
    gt_k, gen_k = _standardise(gt_k, gen_k)
    gt_cd, gen_cd = _standardise(gt_cd, gen_cd)
    return {"fid_k": fid(gen_k, gt_k), "div_k": mean_pairwise_distance(gen_k),
            "fid_cd": fid(gen_cd, gt_cd), "div_cd": mean_pairwise_distance(gen_cd)}
