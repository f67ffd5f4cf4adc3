"""Music features at the motion frame rate, and beat times, with librosa (paper sec. 3.2-3.3).

Contract: :func:`music_features` / :func:`analyse_music` return (n_frames, D) float32 rows where
row i describes the audio around t = i / fps (audio resampled to fps · 512 Hz, hop 512), of a
kind: "edge35" (:data:`EDGE35_LAYOUT`), "duolando54" (:data:`DUOLANDO54_LAYOUT`), "beats4"
(beat impulse, sin/cos of the beat phase, downbeat) or "jukebox" (precomputed 4800-d .npy,
never computed here). Beats come from the same analysis, so metrics and beat columns agree.
Unreadable or missing audio raises :class:`DualFlowError` naming the file.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dualflow.errors import DualFlowError

HOP = 512
MUSIC_KINDS = ("edge35", "duolando54", "jukebox", "beats4")
MUSIC_DIMS = {"edge35": 35, "duolando54": 54, "jukebox": 4800, "beats4": 4}
EDGE35_LAYOUT = {
    "envelope": slice(0, 1),
    "mfcc": slice(1, 21),
    "chroma": slice(21, 33),
    "peaks": slice(33, 34),
    "beats": slice(34, 35),
}
DUOLANDO54_LAYOUT = {
    "mfcc": slice(0, 20),
    "mfcc_delta": slice(20, 40),
    "chroma": slice(40, 52),
    "envelope": slice(52, 53),
    "beats": slice(53, 54),
}


@dataclass
class MusicAnalysis:
    """One track analysed at a motion frame rate.

    features (T, D) float32 (row i at t = i / fps s); beat_times (N,) s; beat_frames (N,) int
    rows of the beats; tempo_bpm: the tracker's tempo; fps; duration_s of the audio analysed.
    """

    features: np.ndarray
    beat_times: np.ndarray
    beat_frames: np.ndarray
    tempo_bpm: float
    fps: float
    duration_s: float
    kind: str


def analysis_rate(fps: float, hop: int = HOP) -> int:
    """Sample rate (Hz) at which one hop of ``hop`` samples is one motion frame: round(fps·hop)."""
    if not float(fps) > 0:
        raise DualFlowError(f"music fps must be > 0, got {fps!r}")
    return int(round(float(fps) * hop))


def load_audio(path: str | Path, sr: int, offset_s: float = 0.0, duration_s: float | None = None) -> np.ndarray:
    """Mono waveform (N,) float32 at ``sr`` Hz from wav/ogg/flac/mp3 (librosa.load)."""
    import librosa

    p = Path(path)
    if not p.is_file():
        raise DualFlowError(f"{p}: music file not found; pass an existing wav/ogg/mp3 file")
    try:
        with warnings.catch_warnings():  # librosa warns before falling back to audioread; we report instead
            warnings.simplefilter("ignore", (UserWarning, FutureWarning))
            y, _ = librosa.load(str(p), sr=int(sr), mono=True, offset=float(offset_s), duration=duration_s)
    except Exception as exc:  # soundfile/audioread raise many types for a bad file
        raise DualFlowError(
            f"{p}: cannot read audio ({type(exc).__name__}: {exc}); use a valid wav/ogg/flac/mp3 file"
        ) from exc
    if y.size < 2 * HOP:
        raise DualFlowError(f"{p}: audio is empty or shorter than {2 * HOP / sr:.3f} s after offset {offset_s} s")
    if not np.all(np.isfinite(y)):
        raise DualFlowError(f"{p}: audio contains NaN or infinite samples")
    return y.astype(np.float32)


def _fit_rows(x: np.ndarray, n_frames: int | None) -> np.ndarray:
    """Trim to n_frames rows, or repeat the last row (beat/peak one-hots padded with 0)."""
    if n_frames is None:
        return x
    n = int(n_frames)
    if n < 1:
        raise DualFlowError(f"n_frames must be >= 1, got {n_frames!r}")
    if x.shape[0] >= n:
        return x[:n]
    return np.concatenate([x, np.repeat(x[-1:], n - x.shape[0], axis=0)], axis=0)


def _one_hot(indices: np.ndarray, n: int) -> np.ndarray:
    out = np.zeros(n, dtype=np.float32)
    idx = np.asarray(indices, dtype=np.int64)
    out[idx[(idx >= 0) & (idx < n)]] = 1.0
    return out


def analyse_waveform(
    y: np.ndarray, sr: int, kind: str = "edge35", fps: float = 30.0, n_frames: int | None = None
) -> MusicAnalysis:
    """Features + beats of a mono waveform already at ``sr = analysis_rate(fps)``.

    onset envelope o = librosa.onset.onset_strength (hop 512); beats b = beat_track(o) (EDGE
    uses tightness 100 and a tempo prior from librosa's tempo estimate); peaks =
    onset_detect(o). MFCC: 20 coefficients; chroma: CENS (edge35) or CQT (duolando54);
    ΔMFCC: librosa.feature.delta(mfcc, width=3).
    """
    import librosa

    if kind not in ("edge35", "duolando54"):
        raise DualFlowError(
            f"music kind {kind!r} is not computed from audio; choose 'edge35' or 'duolando54' "
            "(Jukebox features load from .npy with load_jukebox)"
        )
    if int(sr) != analysis_rate(fps):
        raise DualFlowError(f"waveform must be at {analysis_rate(fps)} Hz for {fps} fps (got {sr}); use load_audio")
    y = np.asarray(y, dtype=np.float32)
    env = librosa.onset.onset_strength(y=y, sr=sr, hop_length=HOP)
    t = env.shape[0]
    start_bpm = float(np.atleast_1d(librosa.feature.tempo(onset_envelope=env, sr=sr, hop_length=HOP))[0])
    tempo, beats = librosa.beat.beat_track(
        onset_envelope=env, sr=sr, hop_length=HOP, start_bpm=start_bpm, tightness=100
    )
    beats = np.asarray(beats, dtype=np.int64)
    mfcc = librosa.feature.mfcc(y=y, sr=sr, n_mfcc=20, hop_length=HOP)[:, :t].T
    if kind == "edge35":
        chroma = librosa.feature.chroma_cens(y=y, sr=sr, hop_length=HOP, n_chroma=12)[:, :t].T
        peaks = librosa.onset.onset_detect(onset_envelope=env, sr=sr, hop_length=HOP)
        feats = np.concatenate(
            [env[:, None], mfcc, chroma, _one_hot(peaks, t)[:, None], _one_hot(beats, t)[:, None]], 1
        )
    else:
        delta = librosa.feature.delta(mfcc.T, width=3).T
        chroma = librosa.feature.chroma_cqt(y=y, sr=sr, hop_length=HOP, n_chroma=12)[:, :t].T
        feats = np.concatenate([mfcc, delta, chroma, env[:, None], _one_hot(beats, t)[:, None]], 1)
    feats = _fit_rows(feats.astype(np.float32), n_frames)
    beats = beats[beats < feats.shape[0]]
    return MusicAnalysis(
        features=feats,
        beat_times=beats.astype(np.float64) * HOP / sr,
        beat_frames=beats,
        tempo_bpm=float(np.atleast_1d(tempo)[0]),
        fps=float(fps),
        duration_s=y.size / float(sr),
        kind=kind,
    )


def analyse_music(
    path: str | Path,
    kind: str = "edge35",
    fps: float = 30.0,
    n_frames: int | None = None,
    offset_s: float = 0.0,
    duration_s: float | None = None,
) -> MusicAnalysis:
    """Load ``path`` and analyse it (see :func:`analyse_waveform`); the one entry point for audio."""
    if kind not in ("edge35", "duolando54"):
        raise DualFlowError(
            f"music kind {kind!r} is not an audio analysis; choose 'edge35' or 'duolando54' "
            f"(all kinds: {', '.join(MUSIC_KINDS)}, see music_features)"
        )
    sr = analysis_rate(fps)
    return analyse_waveform(load_audio(path, sr, offset_s, duration_s), sr, kind, fps, n_frames)


def beat_track_features(beat_times_s: np.ndarray, n_frames: int, fps: float = 30.0) -> np.ndarray:
    """The synthetic duets' (T, 4) beat track for tracked beats (see dualflow.synthetic.beat_features).

    The tracked beats are replaced by a regular grid t_j = b_0 + j·P, P = median beat interval,
    extended over the whole clip (the synthetic music is strictly periodic, so is the track the
    model learnt); the downbeat is every 4th grid beat. Needs at least 2 beats.
    """
    from dualflow.synthetic import beat_features

    b = np.asarray(beat_times_s, dtype=np.float64)
    if b.size < 2:
        raise DualFlowError(f"beat track: need at least 2 beats to know the tempo, found {b.size}; use longer music")
    period = float(np.median(np.diff(b)))
    first = b[0] - period * np.ceil(b[0] / period)  # the grid's first beat at or before t = 0
    grid = first + period * np.arange(int(np.ceil((n_frames / fps - first) / period)) + 2)
    feats, _ = beat_features(np.arange(int(n_frames)) / float(fps), grid, float(fps))
    return feats.astype(np.float32)


def music_features(
    path: str | Path, kind: str = "edge35", fps: float = 30.0, n_frames: int | None = None, **kw
) -> np.ndarray:
    """(T, D) float32 per-motion-frame features of an audio file (``.npy`` → Jukebox features)."""
    if kind == "jukebox" or str(path).endswith(".npy"):
        return load_jukebox(path, n_frames)
    if kind == "beats4":
        a = analyse_music(path, "edge35", fps, None, **kw)
        return beat_track_features(a.beat_times, n_frames or a.features.shape[0], fps)
    return analyse_music(path, kind, fps, n_frames, **kw).features


def beat_times(path: str | Path, fps: float = 30.0, **kw) -> np.ndarray:
    """Beat times (N,) in seconds of an audio file, from the same analysis as the features."""
    return analyse_music(path, "edge35", fps, **kw).beat_times


def load_jukebox(path: str | Path, n_frames: int | None = None, dim: int = MUSIC_DIMS["jukebox"]) -> np.ndarray:
    """Precomputed Jukebox features (T, 4800) float32 from a .npy file (no pickle).

    The file must already be at the motion frame rate (EDGE stores them at 30 fps);
    ``n_frames`` trims or repeats the last row.
    """
    p = Path(path)
    if not p.is_file():
        raise DualFlowError(f"{p}: Jukebox feature file not found; precompute (T, {dim}) features into a .npy file")
    try:
        x = np.load(p, allow_pickle=False)
    except Exception as exc:
        raise DualFlowError(f"{p}: not a readable .npy array ({exc}); save features with numpy.save") from exc
    if x.ndim != 2 or x.shape[1] != dim or x.shape[0] < 1:
        raise DualFlowError(f"{p}: Jukebox features must have shape (T, {dim}), got {x.shape}")
    if not np.issubdtype(x.dtype, np.floating) or not np.all(np.isfinite(x)):
        raise DualFlowError(f"{p}: Jukebox features must be finite floats, got dtype {x.dtype}")
    return _fit_rows(x.astype(np.float32), n_frames)
