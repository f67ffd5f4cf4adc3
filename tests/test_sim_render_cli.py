"""Rendering to mp4 and the check / render / view subcommands."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import pytest

from dualflow.motion import REST_POSE, Motion
from firmware_cfg.registry import joint_names
from retarget import RobotTrajectory
from ros_free_bridge.cli import main
from sim import SimError
from sim.human_figure import People
from sim.render import CameraConfig, RenderConfig, render_trajectory
from sim.scene import Scene

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def wave_npz(tmp_path_factory) -> Path:
    stand = Scene().stand_ctrl
    t = np.arange(31) / 30.0
    q = np.tile(stand, (len(t), 1))
    q[:, 0] = -0.5 * np.sin(2.0 * t) ** 2
    n = len(t)
    traj = RobotTrajectory(
        joint_names("op3"), q, np.tile([0, 0, 0.27], (n, 1)), np.tile([1.0, 0, 0, 0], (n, 1)), 30.0, "op3"
    )
    return traj.save_npz(tmp_path_factory.mktemp("traj") / "wave.npz")


@pytest.fixture(scope="module")
def too_fast_npz(tmp_path_factory) -> Path:
    stand = Scene().stand_ctrl
    t = np.arange(31) / 30.0
    q = np.tile(stand, (len(t), 1))
    q[:, 0] = -1.2 * np.sin(6.0 * t) ** 2
    n = len(t)
    traj = RobotTrajectory(
        joint_names("op3"), q, np.tile([0, 0, 0.27], (n, 1)), np.tile([1.0, 0, 0, 0], (n, 1)), 30.0, "op3"
    )
    return traj.save_npz(tmp_path_factory.mktemp("traj") / "too_fast.npz")


def _render(*args, **kwargs):
    # no skip without OpenGL: the demo (the README's main job) renders too, so a machine where
    # offscreen rendering fails cannot run this project, and these tests say so
    return render_trajectory(*args, **kwargs)


def test_render_side_by_side_mp4(wave_npz, tmp_path):
    actor = Motion(np.tile(REST_POSE, (31, 1, 1)) + (1.5, 0, 0), 30.0)
    reactor = Motion(np.tile(REST_POSE, (31, 1, 1)), 30.0)
    out = tmp_path / "duet.mp4"
    path, result = _render(
        wave_npz,
        out,
        RenderConfig(width=160, height=128, fps=10, side_by_side=True),
        people=People(actor, reactor=reactor),
    )
    assert path == out and result.passed
    frames = [f for f in imageio.get_reader(out)]
    assert len(frames) == 11  # 1 s at 10 fps, both ends
    assert frames[0].shape == (128, 3 * 160, 3)
    # each panel shows something besides the floor and sky: the figures are drawn
    for panel in range(3):
        img = frames[5][:, panel * 160 : (panel + 1) * 160].astype(float)
        assert img.std() > 10
    assert not list(tmp_path.glob("*partial*"))


def test_render_kinematic_camera_moves_the_view(wave_npz, tmp_path):
    a, _ = _render(wave_npz, tmp_path / "a.mp4", RenderConfig(width=128, height=96, fps=5, playback="kinematic"))
    b, _ = _render(
        wave_npz,
        tmp_path / "b.mp4",
        RenderConfig(
            width=128, height=96, fps=5, playback="kinematic", camera=CameraConfig(azimuth=90.0, elevation=-40.0)
        ),
    )
    fa, fb = imageio.get_reader(a).get_data(0), imageio.get_reader(b).get_data(0)
    assert fa.shape == (96, 128, 3)
    assert np.abs(fa.astype(float) - fb.astype(float)).mean() > 5


def test_render_bad_config_is_a_sim_error(wave_npz, tmp_path):
    with pytest.raises(SimError, match="must end in .mp4"):
        _render(wave_npz, tmp_path / "x.avi", RenderConfig(width=64, height=64, fps=5))
    with pytest.raises(SimError, match="fps"):
        _render(wave_npz, tmp_path / "x.mp4", RenderConfig(fps=0))


def test_cli_check_pass_and_fail(wave_npz, too_fast_npz, tmp_path, capsys):
    assert main(["check", str(wave_npz), "-o", str(tmp_path), "--no-plots"]) == 0
    assert "PASS" in capsys.readouterr().out
    assert json.loads((tmp_path / "wave.json").read_text())["passed"] is True
    assert main(["check", str(too_fast_npz), "-o", str(tmp_path), "--no-plots"]) == 1
    assert "FAIL" in capsys.readouterr().out and "speed_limit" in (tmp_path / "too_fast.json").read_text()
    assert main(["check", str(tmp_path / "missing.npz")]) == 2
    assert "not found" in capsys.readouterr().err
    assert main(["check", str(wave_npz), "--physics-hz", "250", "--control-hz", "100"]) == 2
    assert "whole multiple" in capsys.readouterr().err


def test_cli_view_without_display_says_so(wave_npz):
    env = {k: v for k, v in __import__("os").environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    out = subprocess.run(
        [sys.executable, "-m", "ros_free_bridge", "view", str(wave_npz)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env=env,
        timeout=120,
    )
    assert out.returncode == 2
    assert "no display" in out.stderr and "render" in out.stderr
    assert "Traceback" not in out.stderr


def test_cli_render_writes_mp4(wave_npz, tmp_path, capsys):
    out = tmp_path / "cli.mp4"
    # no skip without offscreen OpenGL (see above): the demo renders too, so such a machine fails here
    code = main(["render", str(wave_npz), "-o", str(out), "--width", "96", "--height", "64", "--fps", "5"])
    assert code == 0, capsys.readouterr().err
    assert out.stat().st_size > 1000
