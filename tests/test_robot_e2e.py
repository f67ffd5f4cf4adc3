"""A published humanoid, unmodified, through every command (issue: any user's MJCF humanoid in
every command): robot init -> robot check -> retarget the CMU pair -> check -> render ->
run --transport sim -> demo --robot -> retarget-check --robot.

The reference models in ../shared/robots (MuJoCo Menagerie's ROBOTIS OP3 and Unitree G1) are
used as they are published; the test skips with a reason where they or the CMU capture are
absent. Physics verdicts are not asserted here (whether the robot stays up is the balance
issue's): each command must run to its end, exit 0 or 1 (never 2, the bad-input code, and
never a traceback), and leave its outputs complete.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from ros_free_bridge.cli import main

SHARED = Path(os.environ.get("DUALFLOW_SHARED", Path(__file__).resolve().parents[2] / "shared"))
MODELS = {"robotis_op3": "robotis_op3/op3.xml", "unitree_g1": "unitree_g1/g1.xml"}


def _require(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"reference data not found at {path} (../shared is absent on this machine)")
    return path


@pytest.fixture(scope="module", params=sorted(MODELS))
def robot_folder(request, tmp_path_factory):
    """``robot init`` on the published model, then ``robot check``: both exit 0."""
    mjcf = _require(SHARED / "robots" / MODELS[request.param])
    folder = tmp_path_factory.mktemp(request.param) / "robot"
    assert main(["robot", "init", str(mjcf), "-o", str(folder)]) == 0
    assert (folder / "profile.yaml").is_file() and (folder / "hardware.yaml").is_file()
    assert main(["robot", "check", str(folder)]) == 0
    return folder


@pytest.fixture(scope="module")
def cmu():
    a = _require(SHARED / "data" / "mocap" / "cmu" / "18_01.bvh")
    b = _require(SHARED / "data" / "mocap" / "cmu" / "19_01.bvh")
    return a, b


@pytest.mark.slow
def test_published_robot_through_every_command(robot_folder, cmu, tmp_path, capsys):
    from firmware_cfg.registry import joint_names
    from retarget.trajectory import RobotTrajectory

    actor, reactor = cmu
    names = joint_names(robot_folder)

    # retarget the CMU pair (the robot takes the reactor's part), with the profile as written
    rt = tmp_path / "retarget"
    assert (
        main(
            [
                "retarget",
                str(actor),
                str(reactor),
                "--robot",
                str(robot_folder),
                "--ground",
                "--balance",
                "--out",
                str(rt),
            ]
        )
        == 0
    )
    traj = RobotTrajectory.load_npz(rt / "19_01.npz")
    assert traj.joint_names == names and traj.n_frames >= 70 and np.all(np.isfinite(traj.joint_pos))
    report = json.loads((rt / "19_01.report.json").read_text())
    assert report["limit_violations"] == 0

    # check and render take the folder, and the trajectory finds its robot by itself
    capsys.readouterr()
    code = main(["check", str(rt / "19_01.npz"), "-o", str(tmp_path / "check"), "--no-plots"])
    assert code in (0, 1), capsys.readouterr().err
    verdict = json.loads((tmp_path / "check" / "19_01.json").read_text())
    assert verdict["joint_names"] == list(names) and verdict["passed"] == (code == 0)
    video = tmp_path / "clip.mp4"
    code = main(
        [
            "render",
            str(rt / "19_01.npz"),
            "--robot",
            str(robot_folder),
            "-o",
            str(video),
            "--width",
            "160",
            "--height",
            "120",
            "--fps",
            "10",
        ]
    )
    assert code in (0, 1) and video.stat().st_size > 1000

    # the live bridge on the simulated robot (no hardware config needed), the recorded actor
    run_out = tmp_path / "run"
    code = main(
        [
            "run",
            "--robot",
            str(robot_folder),
            "--actor",
            str(actor),
            "--partner",
            "imitate",
            "--transport",
            "sim",
            "--sim-clock",
            "lockstep",
            "--quiet",
            "-o",
            str(run_out),
        ]
    )
    assert code in (0, 1), capsys.readouterr().err
    assert (run_out / "telemetry.dftl").stat().st_size > 0

    # the demo with this robot as the partner (no hardware.yaml filled in: no emulated bus)
    demo_out = tmp_path / "demo"
    code = main(["demo", "--robot", str(robot_folder), "--actor", str(actor), "--no-video", "-o", str(demo_out)])
    assert code in (0, 1), capsys.readouterr().err
    assert (demo_out / "check.json").is_file()

    # a folder of clips checked on this robot
    clips = tmp_path / "clips"
    clips.mkdir()
    (clips / "19_01.bvh").write_bytes(reactor.read_bytes())
    code = main(["retarget-check", str(clips), "--robot", str(robot_folder), "-o", str(tmp_path / "rc"), "--jobs", "1"])
    assert code in (0, 1), capsys.readouterr().err
    import csv

    with open(tmp_path / "rc" / "results.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 1 and rows[0]["clip"].startswith("19_01") and rows[0]["status"] != "error", rows
