"""The ``dualflow-bridge retarget`` subcommand end to end (real files, real solver)."""

import json

import numpy as np
import yaml

from dualflow.motion import REST_POSE, Motion, TwoPersonMotion
from firmware_cfg.registry import resolve
from retarget import RobotTrajectory
from ros_free_bridge.cli import main


def _clip(T=24, shift=0.0):
    t = np.arange(T) / 30.0
    pos = np.repeat(REST_POSE[None], T, axis=0).copy()
    pos[:, :, 0] += shift
    pos[:, [18, 20], 2] += 0.2 * np.sin(2 * np.pi * t)[:, None]
    return pos


def test_retarget_a_duet_file_writes_trajectory_report_and_figure(tmp_path, capsys):
    from dualflow.motion.io import save_motion

    duet = TwoPersonMotion(Motion(_clip(shift=1.0), 30.0, name="a"), Motion(_clip(), 30.0, name="b"), "wave")
    src = tmp_path / "duet.npz"
    save_motion(duet, src)
    out = tmp_path / "out"
    rc = main(["retarget", str(src), "--robot", "op3", "--no-compile", "--window", "0", "--out", str(out), "--strict"])
    assert rc == 0, capsys.readouterr()
    for suffix in (".npz", ".csv", ".report.json", ".report.md", ".joints.png"):
        assert (out / f"duet{suffix}").is_file(), suffix
    traj = RobotTrajectory.load_npz(out / "duet.npz")
    # the arms move from the first frame: by default the robot is led in from standing, and the
    # clip's 24 frames follow the lead-in (meta t0_s, saved with the trajectory)
    t0 = traj.meta["t0_s"]
    assert t0 > 0 and traj.meta["lead_in"]["frames"] == round(t0 * 30)
    assert traj.robot == "op3" and traj.n_frames == 24 + round(t0 * 30) and traj.joint_names[0] == "r_sho_pitch"
    rep = json.loads((out / "duet.report.json").read_text())
    assert rep["limit_violations"] == 0 and rep["velocity_violations"] == 0 and rep["passed"] is True
    # the reactor (standing at x = 0) was retargeted, not the actor (at x = 1 m)
    assert abs(traj.root_pos[:, 0].mean()) < 0.05
    assert "PASS" in capsys.readouterr().out


def test_foot_collision_model_is_chosen_on_the_command_line(tmp_path, capsys):
    from dualflow.motion.io import save_motion

    src = tmp_path / "one.npz"
    save_motion(Motion(_clip(), 30.0, name="one"), src)
    for model in ("distance", "sole-plane"):
        out = tmp_path / model
        rc = main(
            [
                "retarget",
                str(src),
                "--robot",
                "op3",
                "--no-compile",
                "--window",
                "0",
                "--foot-collision",
                model,
                "--out",
                str(out),
                "--strict",
            ]
        )
        assert rc == 0, capsys.readouterr()
        assert RobotTrajectory.load_npz(out / "one.npz").meta["collision_model"] == model


def test_user_errors_are_one_line_with_exit_code_2(tmp_path, capsys):
    from dualflow.motion.io import save_motion

    src = tmp_path / "one.npz"
    save_motion(Motion(_clip(), 30.0, name="one"), src)
    assert main(["retarget", str(src), "--robot", "no_such_robot", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: --robot no_such_robot: unknown robot") and "\n" not in err
    data = yaml.safe_load(resolve("op3").profile.read_text())
    data["keypoints"]["left_knee"] = {"body": "l_knee_bone"}
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(data))
    assert main(["retarget", str(src), "--robot", "op3", "--profile", str(bad), "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "keypoints.left_knee.body" in err and "l_knee_bone" in err
    save_motion(Motion(REST_POSE[None], 30.0, name="single"), tmp_path / "single.npz")
    assert main(["retarget", str(tmp_path / "single.npz"), "--no-compile", "--out", str(tmp_path)]) == 2
    assert "at least 2" in capsys.readouterr().err


def test_no_lead_in_starts_the_trajectory_at_the_clips_first_frame(tmp_path, capsys):
    from dualflow.motion.io import save_motion

    src = tmp_path / "one.npz"
    save_motion(Motion(_clip(), 30.0, name="one"), src)
    out = tmp_path / "out"
    argv = ["retarget", str(src), "--robot", "op3", "--no-compile", "--window", "0", "--out", str(out)]
    assert main([*argv, "--no-lead-in"]) == 0, capsys.readouterr()
    traj = RobotTrajectory.load_npz(out / "one.npz")
    assert traj.n_frames == 24 and traj.meta.get("t0_s", 0.0) == 0.0 and not traj.meta.get("lead_in")
