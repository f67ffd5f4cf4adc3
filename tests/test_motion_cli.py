"""``dualflow-bridge motion info|convert|preview`` and the stick-figure preview."""

from __future__ import annotations

import subprocess
import sys

import imageio_ffmpeg
import numpy as np
import pytest
from PIL import Image

from dualflow import DualFlowError
from dualflow.motion import REST_POSE, Motion, TwoPersonMotion
from dualflow.motion.io import load_any, load_motion, save_motion
from dualflow.motion.preview import PERSON_COLOURS, FrameRenderer, PreviewConfig, render_preview
from dualflow.synthetic import make_duet
from ros_free_bridge.cli import main


def walker(T=30, fps=30.0, x0=0.0, direction=1.0, name="walker") -> Motion:
    t = np.arange(T) / fps
    pos = np.repeat(REST_POSE[None], T, axis=0)
    if direction < 0:
        pos = pos * [-1, -1, 1]  # turned to face -X
    pos[:, :, 0] += x0 + direction * 0.8 * t[:, None]
    return Motion(pos, fps=fps, name=name)


@pytest.fixture
def duet_file(tmp_path):
    pair = TwoPersonMotion(walker(x0=-1.0), walker(x0=1.0, direction=-1.0, name="partner"), text="meet in the middle")
    save_motion(pair, tmp_path / "duet.npz")
    return tmp_path / "duet.npz"


def run(argv, capsys):
    code = main(argv)
    out = capsys.readouterr()
    return code, out.out, out.err


def _rgb(hex_colour: str) -> np.ndarray:
    return np.array([int(hex_colour[i : i + 2], 16) for i in (1, 3, 5)])


def _has_colour(frame: np.ndarray, hex_colour: str, tol: int = 40) -> bool:
    return bool((np.abs(frame.astype(int) - _rgb(hex_colour)).max(axis=-1) < tol).sum() > 20)


def _mp4_frames(path):
    gen = imageio_ffmpeg.read_frames(str(path))
    meta = next(gen)
    w, h = meta["size"]
    frames = [np.frombuffer(f, np.uint8).reshape(h, w, 3) for f in gen]
    return meta, frames


# -- info / convert ------------------------------------------------------------------
def test_info_prints_frames_fps_duration_height_and_extents(duet_file, capsys):
    code, out, _ = run(["motion", "info", str(duet_file)], capsys)
    assert code == 0
    assert "frames    30" in out and "fps       30" in out and "duration  0.967 s" in out
    assert out.count("height (standing estimate)  1.72 m") == 2
    assert (
        "extents  x -1.02 .. -0.12   y -0.69 .. +0.69   z +0.02 .. +1.58 m" in out
        and "text      meet in the middle" in out
    )
    assert "pelvis distance  0.45 .. 2.00 m" in out


def test_info_on_the_cmu_pair(cmu_pair_paths, capsys):
    a, b = map(str, cmu_pair_paths)
    code, out, _ = run(["motion", "info", "--actor", a, "--reactor", b], capsys)
    assert code == 0
    assert "frames    303" in out and "fps       120" in out
    assert "joint map cmu, unit cmu (0.056444 m), dropped frame 0" in out
    assert "pelvis distance  0.74" in out


def test_convert_between_formats_and_resample(duet_file, tmp_path, capsys):
    code, out, _ = run(["motion", "convert", str(duet_file), str(tmp_path / "out.bvh"), "--fps", "15"], capsys)
    assert code == 0 and "out_actor.bvh and" in out
    actor = load_motion(tmp_path / "out_actor.bvh", drop_first=False)
    assert actor.fps == pytest.approx(15.0) and actor.n_frames == 15
    np.testing.assert_allclose(actor.positions, walker(x0=-1.0).resample(15).positions, atol=1e-5)
    code, _, _ = run(
        [
            "motion",
            "convert",
            str(tmp_path / "out_actor.bvh"),
            str(tmp_path / "out_reactor.bvh"),
            str(tmp_path / "again.npz"),
            "--keep-first-frame",
        ],
        capsys,
    )
    assert code == 0
    again = load_any(tmp_path / "again.npz")
    assert isinstance(again, TwoPersonMotion) and again.n_frames == 15
    np.testing.assert_allclose(again.reactor.positions[0, 0, :2], [1.0, 0.0], atol=1e-5)


def test_convert_cmu_pair_to_npz(cmu_pair_paths, tmp_path, capsys):
    a, b = map(str, cmu_pair_paths)
    code, out, _ = run(
        ["motion", "convert", "--actor", a, "--reactor", b, str(tmp_path / "cmu.npz"), "--fps", "30"], capsys
    )
    assert code == 0 and "76 frames at 30 fps" in out
    pair = load_any(tmp_path / "cmu.npz")
    assert pair.meta["joint_map"] == ["cmu", "cmu"] and pair.actor.name == "18_01.bvh"


@pytest.mark.parametrize(
    "argv, match",
    [
        (["motion", "info", "missing.bvh"], "error: missing.bvh: no such file"),
        (["motion", "info", "--actor", "a.bvh"], "give both --actor and --reactor"),
        (["motion", "info", "a", "b", "c"], "at most two input files"),
        (["motion", "info"], "no input"),
        (["motion", "convert", "only_output.npz"], "no input"),
        (["motion", "preview", "-o", "x.avi", "--sample"], "must end in .mp4 or .gif"),
        (["motion", "preview", "-o", "x.gif", "--sample", "waltz"], "unknown rule 'waltz'"),
    ],
)
def test_user_errors_are_one_line_exit_2(argv, match, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, _, err = run(argv, capsys)
    assert code == 2
    assert match in err and err.count("\n") == 1 and "Traceback" not in err


def test_module_entry_point_and_help():
    out = subprocess.run(
        [sys.executable, "-m", "ros_free_bridge", "motion", "--help"], capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0
    for action in ("info", "convert", "preview"):
        assert action in out.stdout


# -- preview -------------------------------------------------------------------------
def test_preview_two_people_mp4(duet_file, tmp_path, capsys):
    out_path = tmp_path / "duet.mp4"
    code, out, _ = run(["motion", "preview", str(duet_file), "-o", str(out_path), "--size", "320x240"], capsys)
    assert code == 0 and out.startswith(f"wrote {out_path}")
    meta, frames = _mp4_frames(out_path)
    assert meta["size"] == (320, 240) and meta["fps"] == pytest.approx(30.0)
    assert len(frames) == 30
    mid = frames[15]
    assert _has_colour(mid, PERSON_COLOURS[0]) and _has_colour(mid, PERSON_COLOURS[1])
    assert np.abs(frames[0].astype(int) - frames[-1].astype(int)).max() > 100  # the people moved
    assert sorted(p.name for p in tmp_path.iterdir()) == ["duet.mp4", "duet.npz"]  # no partial files


def test_preview_sample_gif(tmp_path, capsys):
    out_path = tmp_path / "sample.gif"
    code, _, _ = run(
        ["motion", "preview", "--sample", "mirror", "--seconds", "1", "--size", "160x120", "-o", str(out_path)], capsys
    )
    assert code == 0
    with Image.open(out_path) as gif:
        assert gif.size == (160, 120)
        sample = make_duet("mirror", seconds=1.0, fps=30.0)
        assert gif.n_frames == sample.resample(25.0).n_frames  # resampled to the gif's 25 fps cap
        assert gif.info["duration"] == 40
        gif.seek(12)
        frame = np.asarray(gif.convert("RGB"))
    assert _has_colour(frame, PERSON_COLOURS[0]) and _has_colour(frame, PERSON_COLOURS[1])


def test_frame_renderer_draws_where_the_person_is():
    left = walker(T=2, x0=0.0)
    cfg = PreviewConfig(width=200, height=150, azimuth_deg=-90.0, elevation_deg=0.0)  # camera on -Y, +X to the right
    both = [left, walker(T=2, x0=3.0)]
    r = FrameRenderer(both, cfg)
    img = r.render(0)
    cols = np.flatnonzero(np.array([_has_colour(img[:, [c]], PERSON_COLOURS[0], tol=30) for c in range(img.shape[1])]))
    cols2 = np.flatnonzero(np.array([_has_colour(img[:, [c]], PERSON_COLOURS[1], tol=30) for c in range(img.shape[1])]))
    assert cols.size and cols2.size and cols.mean() < cols2.mean()  # the person at smaller x is further left
    with pytest.raises(DualFlowError, match="even"):
        render_preview(left, "x.mp4", PreviewConfig(width=201))
    with pytest.raises(DualFlowError, match="does not exist"):
        render_preview(left, "/no/such/folder/x.mp4")
    with pytest.raises(DualFlowError, match="give a Motion"):
        render_preview([left, "not a motion"], "x.gif")
