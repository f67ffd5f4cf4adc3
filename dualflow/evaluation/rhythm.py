"""Rhythm metrics: Beat Alignment Score (BAS) and Beat Echo Degree (BED) (numpy only).

Motion beats (Bailando, Siyao et al. 2022; Duolando 2024, ``utils/metrics_duet.py``
of lisiyao21/Duolando): the mean joint speed per frame

    s[t] = (1/J) Σ_j ‖p_j[t+1] − p_j[t]‖                        (metres per frame)

is smoothed with a Gaussian of σ = 5 frames, and the motion beats are its strict
local minima (the moments the dancer "hits" a pose).

* **BAS**: for every music beat b (frames), the nearest motion beat m scores
  exp(−(m − b)² / (2σ²)) with σ² = 9 frames²; BAS is the mean over music beats.
  Motion with a speed minimum on every music beat scores 1.
* **BED** (Duolando's interactive rhythm metric): the same score with the
  leader's (actor's) motion beats in place of the music beats and the follower's
  (reactor's) motion beats as the candidates: how well B's beats echo A's.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.signal import argrelextrema

from dualflow.errors import DualFlowError

#: Smoothing of the joint speed, frames.
SPEED_SMOOTH_SIGMA = 5.0
#: σ² of the alignment kernel, frames².
BEAT_SIGMA_SQ = 9.0


def joint_speed(positions) -> np.ndarray:
    """(T, J, 3) positions -> (T-1,) mean joint speed in metres per frame."""
    p = np.asarray(positions, dtype=np.float64)
    if p.ndim != 3 or p.shape[-1] != 3 or len(p) < 3:
        raise DualFlowError(f"motion beats: expected (T >= 3, J, 3) positions, got shape {p.shape}")
    return np.linalg.norm(np.diff(p, axis=0), axis=-1).mean(axis=1)


def motion_beats(positions, sigma: float = SPEED_SMOOTH_SIGMA) -> np.ndarray:
    """Frames of the strict local minima of the smoothed mean joint speed."""
    speed = gaussian_filter1d(joint_speed(positions), sigma)
    return argrelextrema(speed, np.less)[0]


def alignment_score(reference_beats, candidate_beats, sigma_sq: float = BEAT_SIGMA_SQ) -> float:
    """mean over reference beats b of exp(−min_m (m − b)² / (2σ²)); 0 when there are no candidates,
    NaN when there are no reference beats."""
    ref = np.asarray(reference_beats, dtype=np.float64).reshape(-1)
    cand = np.asarray(candidate_beats, dtype=np.float64).reshape(-1)
    if len(ref) == 0:
        return float("nan")
    if len(cand) == 0:
        return 0.0
    d2 = np.min((ref[:, None] - cand[None, :]) ** 2, axis=1)
    return float(np.exp(-d2 / (2.0 * sigma_sq)).mean())


def beat_alignment_score(positions, music_beat_frames) -> float:
    """BAS of one person's (T, J, 3) motion against the music's beat frames."""
    beats = np.asarray(music_beat_frames).reshape(-1)
    beats = beats[(beats >= 0) & (beats < len(positions) - 1)]
    return alignment_score(beats, motion_beats(positions))


def beat_echo_degree(actor_positions, reactor_positions) -> float:
    """BED: how well the reactor's motion beats echo the actor's (module docstring)."""
    return alignment_score(motion_beats(actor_positions), motion_beats(reactor_positions))
