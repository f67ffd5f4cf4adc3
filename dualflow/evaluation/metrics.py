"""Distribution and text-alignment metrics on evaluator embeddings (numpy only).

Contract: InterGen's text-to-motion protocol (after Guo et al. 2022): FID between two embedding
sets, R-precision top-1/2/3 in batches of 96 matched pairs, MM distance, diversity (300
samples), multimodality (R generations per condition) and the mean with 95 % half-width
1.96 std / sqrt(n) over replications.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from scipy import linalg

from dualflow.errors import DualFlowError

#: InterGen's protocol constants.
R_PRECISION_BATCH = 96
DIVERSITY_TIMES = 300
MM_NUM_SAMPLES = 100
MM_NUM_REPEATS = 30
MM_NUM_TIMES = 10
REPLICATIONS = 20


def _matrix(x, what: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 2 or len(a) < 2 or not np.isfinite(a).all():
        raise DualFlowError(f"{what}: expected a finite (N >= 2, d) array of embeddings, got shape {a.shape}")
    return a


def activation_statistics(emb) -> tuple[np.ndarray, np.ndarray]:
    """(μ (d,), Σ (d, d)) of (N, d) embeddings (Σ with N − 1 in the denominator)."""
    a = _matrix(emb, "activation statistics")
    return a.mean(axis=0), np.cov(a, rowvar=False)


def frechet_distance(mu1, sigma1, mu2, sigma2, eps: float = 1e-6) -> float:
    """‖μ₁ − μ₂‖² + tr(Σ₁ + Σ₂ − 2 (Σ₁ Σ₂)^½); ε·I is added to both covariances when
    their product is singular (as in the reference implementations)."""
    mu1, mu2 = np.atleast_1d(mu1), np.atleast_1d(mu2)
    s1, s2 = np.atleast_2d(sigma1), np.atleast_2d(sigma2)
    diff = mu1 - mu2
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a singular product is handled below
        covmean = linalg.sqrtm(s1 @ s2)
        if not np.isfinite(covmean).all():
            offset = np.eye(len(s1)) * eps
            covmean = linalg.sqrtm((s1 + offset) @ (s2 + offset))
    covmean = np.real(covmean)
    return float(diff @ diff + np.trace(s1) + np.trace(s2) - 2.0 * np.trace(covmean))


def fid(emb_a, emb_b) -> float:
    """FID between two (N, d) embedding sets."""
    return frechet_distance(*activation_statistics(emb_a), *activation_statistics(emb_b))


def euclidean_distance_matrix(a, b) -> np.ndarray:
    """D[i, j] = ‖a_i − b_j‖ for (N, d) and (M, d) arrays."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    sq = (a * a).sum(1)[:, None] - 2.0 * a @ b.T + (b * b).sum(1)[None, :]
    return np.sqrt(np.maximum(sq, 0.0))


def r_precision(
    text_emb, motion_emb, top_k: int = 3, batch_size: int = R_PRECISION_BATCH, rng: np.random.Generator | None = None
) -> tuple[np.ndarray, float]:
    """(R-precision top-1..top_k (top_k,), MM distance) over batches of matched pairs.

    Pairs are shuffled by ``rng`` (unshuffled when None) and cut into batches of
    ``batch_size``; the last, incomplete batch is dropped as InterGen's loader does,
    unless there are fewer pairs than one batch, in which case all form one batch
    (the chance level is then k / N).
    """
    t, m = _matrix(text_emb, "R-precision text"), _matrix(motion_emb, "R-precision motion")
    if t.shape != m.shape:
        raise DualFlowError(f"R-precision: text {t.shape} and motion {m.shape} embeddings must pair up")
    n = len(t)
    order = np.arange(n) if rng is None else rng.permutation(n)
    size = min(int(batch_size), n)
    hits = np.zeros(top_k)
    mm_sum, count = 0.0, 0
    for start in range(0, n - size + 1, size):
        idx = order[start : start + size]
        d = euclidean_distance_matrix(t[idx], m[idx])
        mm_sum += float(np.trace(d))
        rank = (d < np.diag(d)[:, None]).sum(axis=1)  # motions strictly nearer than the match
        hits += np.array([(rank < k).sum() for k in range(1, top_k + 1)], dtype=np.float64)
        count += size
    return hits / count, mm_sum / count


def diversity(emb, times: int = DIVERSITY_TIMES, rng: np.random.Generator | None = None) -> float:
    """Mean distance between ``times`` random pairs (two draws without replacement)."""
    a = _matrix(emb, "diversity")
    rng = rng or np.random.default_rng(0)
    times = min(int(times), len(a))
    first = rng.choice(len(a), times, replace=False)
    second = rng.choice(len(a), times, replace=False)
    return float(np.linalg.norm(a[first] - a[second], axis=1).mean())


def multimodality(emb, times: int = MM_NUM_TIMES, rng: np.random.Generator | None = None) -> float:
    """(S, R, d) embeddings of R generations per condition -> mean distance of ``times`` pairs."""
    a = np.asarray(emb, dtype=np.float64)
    if a.ndim != 3 or a.shape[1] < 2 or not np.isfinite(a).all():
        raise DualFlowError(f"multimodality: expected finite (conditions, repeats >= 2, d) embeddings, got {a.shape}")
    rng = rng or np.random.default_rng(0)
    times = min(int(times), a.shape[1])
    first = rng.choice(a.shape[1], times, replace=False)
    second = rng.choice(a.shape[1], times, replace=False)
    return float(np.linalg.norm(a[:, first] - a[:, second], axis=2).mean())


@dataclass(frozen=True)
class Estimate:
    """Mean and 95 % confidence half-width (1.96 σ / √n) over n replications."""

    mean: float
    ci: float
    n: int

    @staticmethod
    def of(values) -> Estimate:
        v = np.asarray(values, dtype=np.float64).reshape(-1)
        if len(v) == 0:
            return Estimate(float("nan"), float("nan"), 0)
        return Estimate(float(v.mean()), float(1.96 * v.std() / np.sqrt(len(v))), len(v))
