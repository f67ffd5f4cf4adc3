"""Music features and beats: synthetic clicks with known beat times, the real recordings, errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dualflow.errors import DualFlowError
from dualflow.music import (
    DUOLANDO54_LAYOUT,
    EDGE35_LAYOUT,
    MUSIC_DIMS,
    analyse_music,
    analyse_waveform,
    analysis_rate,
    beat_times,
    beat_track_features,
    load_jukebox,
    music_features,
)

FPS = 30.0
BEATS_S = np.arange(0.5, 11.6, 0.5)  # 120 bpm clicks


def _clicks(fps: float = FPS, seconds: float = 12.0) -> np.ndarray:
    import librosa

    sr = analysis_rate(fps)
    return librosa.clicks(times=BEATS_S, sr=sr, length=int(seconds * sr), click_freq=1000.0).astype(np.float32)


@pytest.fixture(scope="module")
def click_edge():
    return analyse_waveform(_clicks(), analysis_rate(FPS), "edge35", FPS)


def _match_error(found: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """For each true beat, distance (s) to the nearest found beat."""
    return np.abs(found[None, :] - truth[:, None]).min(axis=1)


def test_click_track_beats_and_tempo(click_edge):
    a = click_edge
    assert a.features.shape == (int(12 * FPS) + 1, 35) and a.features.dtype == np.float32
    assert abs(a.tempo_bpm - 120.0) < 3.0
    # Every click found within 1.5 frames (the onset envelope lags about one hop), no extras.
    inner = BEATS_S[(BEATS_S > 1.0) & (BEATS_S < 11.0)]
    assert _match_error(a.beat_times, inner).max() < 1.5 / FPS
    assert len(a.beat_times) <= len(BEATS_S) + 1
    # The one-hot beat column marks exactly the tracker's beat frames, and the times are rows / fps.
    np.testing.assert_array_equal(np.flatnonzero(a.features[:, EDGE35_LAYOUT["beats"]][:, 0]), a.beat_frames)
    np.testing.assert_allclose(a.beat_times, a.beat_frames / FPS)
    # Onset peaks sit on the clicks; the envelope is highest there.
    peaks = np.flatnonzero(a.features[:, EDGE35_LAYOUT["peaks"]][:, 0]) / FPS
    assert _match_error(peaks, inner).max() < 1.5 / FPS
    env = a.features[:, 0]
    on = np.round(inner * FPS).astype(int)
    assert env[np.clip(on[:, None] + np.arange(0, 3), 0, len(env) - 1)].max(1).min() > 4 * np.median(env)


def test_duolando_layout_and_delta_is_the_mfcc_derivative():
    a = analyse_waveform(_clicks(seconds=6.0), analysis_rate(FPS), "duolando54", FPS)
    assert a.features.shape == (181, MUSIC_DIMS["duolando54"])
    mfcc = a.features[:, DUOLANDO54_LAYOUT["mfcc"]]
    delta = a.features[:, DUOLANDO54_LAYOUT["mfcc_delta"]]
    # width-3 delta = central difference (x[i+1] - x[i-1]) / 2 in the interior.
    np.testing.assert_allclose(delta[1:-1], (mfcc[2:] - mfcc[:-2]) / 2, atol=1e-3 * np.abs(mfcc).max())
    chroma = a.features[:, DUOLANDO54_LAYOUT["chroma"]]
    assert chroma.min() >= 0 and chroma.max() <= 1.0 + 1e-5
    beats = np.flatnonzero(a.features[:, DUOLANDO54_LAYOUT["beats"]][:, 0])
    np.testing.assert_array_equal(beats, a.beat_frames)


def test_rows_follow_the_motion_frame_rate_and_n_frames(tmp_path):
    import soundfile as sf

    sr = analysis_rate(20.0)
    assert sr == 10240
    path = tmp_path / "clicks.wav"
    sf.write(path, _clicks(20.0, 6.0), sr)
    a = analyse_music(path, "edge35", fps=20.0)
    assert a.features.shape[0] == 6 * 20 + 1
    inner = BEATS_S[(BEATS_S > 1.0) & (BEATS_S < 5.0)]
    assert _match_error(a.beat_times, inner).max() < 1.5 / 20.0
    short = analyse_music(path, "edge35", fps=20.0, n_frames=50)
    np.testing.assert_array_equal(short.features, a.features[:50])
    assert short.beat_frames.max() < 50
    long = music_features(path, "edge35", fps=20.0, n_frames=200)
    assert long.shape == (200, 35)
    np.testing.assert_array_equal(long[121:], np.repeat(a.features[-1:], 79, 0))


def test_real_recordings(music_dir: Path):
    files = sorted(p for p in music_dir.glob("*.ogg") if ".hq." not in p.name)
    assert files, f"no .ogg in {music_dir}"
    for f in files:
        a = analyse_music(f, "edge35", FPS, duration_s=8.0)
        assert a.features.shape == (241, 35) and np.all(np.isfinite(a.features))
        assert 60 <= a.tempo_bpm <= 200
        assert len(a.beat_times) >= 8 * a.tempo_bpm / 60 * 0.6  # most beats found
        gaps = np.diff(a.beat_times)
        assert np.median(np.abs(gaps - 60.0 / a.tempo_bpm)) < 2.0 / FPS  # beats are regular at the tempo
        assert a.features[:, EDGE35_LAYOUT["mfcc"]].std(0).min() > 0  # real, varying audio
    bt = beat_times(files[0], duration_s=8.0)
    np.testing.assert_allclose(bt, analyse_music(files[0], "edge35", FPS, duration_s=8.0).beat_times)
    d = music_features(files[0], "duolando54", FPS, n_frames=120, duration_s=4.0)
    assert d.shape == (120, 54) and np.all(np.isfinite(d))


def test_jukebox_npy(tmp_path):
    good = tmp_path / "song.npy"
    x = np.random.default_rng(0).standard_normal((40, 4800)).astype(np.float32)
    np.save(good, x)
    np.testing.assert_array_equal(load_jukebox(good), x)
    np.testing.assert_array_equal(music_features(good, n_frames=30), x[:30])
    assert load_jukebox(good, n_frames=50).shape == (50, 4800)
    bad = tmp_path / "bad.npy"
    np.save(bad, np.zeros((40, 35), np.float32))
    with pytest.raises(DualFlowError, match=r"\(T, 4800\)"):
        load_jukebox(bad)
    obj = tmp_path / "obj.npy"
    np.save(obj, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(DualFlowError, match="obj.npy"):
        load_jukebox(obj)


def test_bad_audio_gives_one_clear_error(tmp_path):
    with pytest.raises(DualFlowError, match="not found"):
        analyse_music(tmp_path / "missing.wav")
    junk = tmp_path / "junk.ogg"
    junk.write_bytes(b"this is not audio" * 100)
    with pytest.raises(DualFlowError, match="junk.ogg"):
        analyse_music(junk)
    with pytest.raises(DualFlowError, match="not an audio analysis"):
        analyse_music(junk, kind="mel128")
    with pytest.raises(DualFlowError, match="Hz"):
        analyse_waveform(np.zeros(50000, np.float32), 22050, "edge35", FPS)
    with pytest.raises(DualFlowError, match="fps"):
        analysis_rate(0)


def test_beat_track_in_the_synthetic_format(click_edge):
    f = beat_track_features(click_edge.beat_times, 300, FPS)
    assert f.shape == (300, 4) and f.dtype == np.float32
    impulses = np.flatnonzero(f[:, 0])
    assert np.all(np.abs(np.diff(impulses) - 15) <= 1)  # 120 bpm at 30 fps
    assert _match_error(impulses / FPS, BEATS_S[BEATS_S < 9.9]).max() < 1.5 / FPS
    np.testing.assert_allclose(f[impulses, 2], 1.0, atol=0.03)  # phase 0 on a beat
    np.testing.assert_allclose(f[:, 1] ** 2 + f[:, 2] ** 2, 1.0, atol=1e-5)
    assert abs(len(np.flatnonzero(f[:, 3])) - len(impulses) / 4) <= 1  # bars of 4
    with pytest.raises(DualFlowError, match="at least 2 beats"):
        beat_track_features(np.array([1.0]), 10)
