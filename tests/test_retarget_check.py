"""End to end: retarget-check over a folder with a good clip, a two-person file, a broken file
and a motion too fast for the servos; and a batch with a clip that kills its worker process.
Real BVH parser, CasADi/IPOPT and MuJoCo, real worker processes."""

import csv
import json
import os
import re
import signal
from pathlib import Path

import numpy as np
import pytest

from dualflow.motion import REST_POSE, Motion, TwoPersonMotion
from dualflow.motion.io import save_motion
from dualflow.synthetic import make_leader
from ros_free_bridge.batch import clip_check
from ros_free_bridge.batch.config import BatchConfig
from ros_free_bridge.batch.run import run_batch
from ros_free_bridge.cli import main

pytestmark = pytest.mark.slow


def test_a_folder_gives_one_row_per_clip_and_a_failure_never_stops_the_batch(tmp_path, capsys):
    clips = tmp_path / "clips"
    clips.mkdir()
    save_motion(Motion(np.repeat(REST_POSE[None], 60, 0), 30.0), clips / "standing.npz")
    # two people: the robot takes the reactor's part (here standing still, 45 frames)
    walker = Motion(make_leader(1.5, 30.0, 2).positions + [2.0, 0.0, 0.0], 30.0)
    save_motion(TwoPersonMotion(walker, Motion(np.repeat(REST_POSE[None], 45, 0), 30.0)), clips / "duet.npz")
    leader = make_leader(3.0, 30.0, 1)
    save_motion(Motion(leader.positions, fps=120.0).resample(30.0), clips / "too_fast.npz")  # 4x faster
    (clips / "broken.bvh").write_text("HIERARCHY\nROOT Hips\n{\n OFFSET 0 0\n")
    out = tmp_path / "out"
    code = main(["retarget-check", str(clips), "-o", str(out), "--jobs", "2", "--no-compile", "--no-video"])
    assert code == 1  # not every clip passes
    rows = {r["clip"]: r for r in csv.DictReader(open(out / "results.csv"))}
    assert list(rows) == ["broken.bvh", "duet.npz", "standing.npz", "too_fast.npz"]  # file order, all present
    assert rows["broken.bvh"]["status"] == "error" and "line 4" in rows["broken.bvh"]["reason"]
    assert rows["standing.npz"]["status"] == "pass"
    assert rows["duet.npz"]["status"] == "pass" and rows["duet.npz"]["frames"] == "45"
    fast = rows["too_fast.npz"]
    # 4x too fast: the servos cannot follow. The retargeter follows at reduced amplitude within
    # every limit (no spurious "infeasible": it is not a retarget failure) and the row says so:
    # which parts were speed-limited, how long, from when and how far from the person. Then the
    # physics verdict decides (the check's
    # stabilizer may keep the robot up); a fall is reported at its time, limits still held
    assert fast["stage"] != "retarget" and fast["limit_violations"] == "0", fast
    changed = fast["changed"]
    assert "speed-limited:" in changed, changed
    part = next(c for c in changed.split("; ") if c.startswith("speed-limited:"))
    n, total, start, worst = re.match(
        r"speed-limited: (\d+)x ([\d.]+) s from ([\d.]+) s \(up to (\d+) mm\)", part
    ).groups()
    assert int(n) >= 1 and 0 < float(total) <= 3.0 and 0 <= float(start) < 3.0 and int(worst) > 0
    assert rows["standing.npz"]["changed"] == "", "a person standing still is played as is"
    if fast["status"] == "fail":
        assert fast["stage"] == "check" and fast["check_reason"]
        assert 0 <= float(fast["first_failure_s"]) <= 3.0  # seconds into the 3 s file
    for name in ("trajectory.npz", "retarget.report.json", "check.json", "check.md"):
        assert (out / "clips" / "standing.npz" / name).stat().st_size > 0, name
    table = (out / "results.md").read_text()
    passing = 2 + (fast["status"] == "pass")
    assert f"{passing} of 4 clips pass" in table and "| standing.npz | PASS |" in table
    assert "too_fast.npz" in capsys.readouterr().out


REAL_CHECK_CLIP = clip_check.check_clip


def check_clip_killing_stand0(path, cfg, name=None, **kw):
    """The real check, except that the worker process checking stand0 dies at once, as a
    segfault in a native library would kill it (fault injection, forked into the workers)."""
    if Path(path).stem == "stand0":
        os.kill(os.getpid(), signal.SIGKILL)
    return REAL_CHECK_CLIP(path, cfg, name, **kw)


@pytest.mark.parametrize("jobs", [1, 2])
def test_a_clip_that_kills_its_worker_costs_only_its_own_row(tmp_path, monkeypatch, jobs):
    """Every time stand0 is checked its process dies: in the pool (taking the clips in flight or
    queued with it) and again when run alone. It gets an error row; every other clip its result."""
    clips = []
    for k in range(4):
        clips.append(tmp_path / f"stand{k}.npz")
        save_motion(Motion(np.repeat(REST_POSE[None], 30, 0), 30.0), clips[-1])
    monkeypatch.setattr(clip_check, "check_clip", check_clip_killing_stand0)
    rows = run_batch(clips, BatchConfig(out=tmp_path / "out", compile=False, video=False), jobs=jobs, progress=False)
    assert [r.clip for r in rows] == [f"stand{k}.npz" for k in range(4)]
    assert rows[0].status == "error" and "worker process died" in rows[0].reason
    assert [r.status for r in rows[1:]] == ["pass"] * 3


def test_the_streaming_retargeter_can_do_the_checking(tmp_path):
    """--retargeter streaming: the live bridge's retargeter makes the trajectory; a standing clip
    passes, and its trajectory says which retargeter made it."""
    clip = tmp_path / "standing.npz"
    save_motion(Motion(np.repeat(REST_POSE[None], 30, 0), 30.0), clip)
    cfg = BatchConfig(out=tmp_path / "out", compile=False, retargeter="streaming", video=False)
    [row] = run_batch([clip], cfg, jobs=1, progress=False)
    assert row.status == "pass" and row.limit_violations == 0
    with np.load(tmp_path / "out" / "clips" / "standing.npz" / "trajectory.npz", allow_pickle=False) as traj:
        assert json.loads(str(traj["header"]))["meta"]["mode"] == "streaming"


def test_the_changed_column_gives_no_error_for_a_lead_in_that_has_no_person_to_measure():
    from ros_free_bridge.batch.clip_check import changes_summary

    cell = changes_summary(
        [
            {"start_s": -3.07, "end_s": 0.0, "what": "lead-in", "why": "mid-step start"},
            {"start_s": 0.0, "end_s": 0.4, "what": "held down", "why": "in the air", "keypoint_error_mm": 32.4},
            {"start_s": 1.0, "end_s": 1.2, "what": "held down", "why": "in the air", "keypoint_error_mm": 40.6},
        ]
    )
    assert cell == "lead-in: 1x 3.07 s from -3.07 s; held down: 2x 0.60 s from 0.00 s (up to 41 mm)"


def test_an_unknown_robot_or_a_broken_profile_is_one_error_before_any_clip(tmp_path, capsys):
    """A robot that cannot load (an unknown name, a profile field that does not parse or bind)
    stops retarget-check at once with exit 2 naming it; it used to fail every clip, one row
    each, exit 1."""
    import shutil

    from firmware_cfg.registry import resolve

    clip = tmp_path / "clips" / "standing.npz"
    clip.parent.mkdir()
    save_motion(Motion(np.repeat(REST_POSE[None], 30, 0), 30.0), clip)
    op3 = resolve("op3")
    folder = tmp_path / "my_op3"
    shutil.copytree(Path(op3.profile).parent, folder)
    profile = folder / "profile.yaml"
    text = profile.read_text()
    out = tmp_path / "out"
    for robot, bad, named in (
        ("nosuchbot", None, "unknown robot"),
        (str(folder), "stand_pose: {l_knee: .nan}", "stand_pose.l_knee"),
        (str(folder), "stand_pose: {no_joint: 0.3}", "stand_pose.no_joint"),
    ):
        if bad:
            profile.write_text(text.rstrip("\n") + "\n" + bad + "\n")
        assert main(["retarget-check", str(clip.parent), "-o", str(out), "--robot", robot]) == 2
        err = capsys.readouterr().err
        assert named in err and "Traceback" not in err, err
        assert not out.exists()


def test_a_hardware_config_the_loop_refuses_is_one_error_before_any_clip(tmp_path, capsys):
    """The physics check plays each clip through the loop's safety filter, with the hardware
    config's limits: a robot folder whose hardware config the loop refuses (a servo with no
    model on a Dynamixel bus) stops retarget-check at once with exit 2 naming the field, where
    it failed every clip, one error row each."""
    import shutil

    import yaml

    from ros_free_bridge.robots import resolve_robot

    clip = tmp_path / "clips" / "standing.npz"
    clip.parent.mkdir()
    save_motion(Motion(np.repeat(REST_POSE[None], 30, 0), 30.0), clip)
    folder = tmp_path / "unfinished_op3"
    shutil.copytree(resolve_robot("op3").mjcf.parent, folder)
    hw = yaml.safe_load((folder / "hardware.yaml").read_text())
    hw["buses"][0]["servos"][0]["model"] = None
    (folder / "hardware.yaml").write_text(yaml.safe_dump(hw))
    out = tmp_path / "out"
    assert main(["retarget-check", str(clip.parent), "-o", str(out), "--robot", str(folder)]) == 2
    err = capsys.readouterr().err
    assert "model: required on a Dynamixel bus" in err and "Traceback" not in err, err
    assert not out.exists()


def test_the_planner_asked_for_a_robot_it_cannot_plan_is_one_error_before_any_clip(tmp_path, capsys):
    """--offline-engine planner plans a free-standing robot's steps with balance: on the
    fixed-base ub14, or with --no-balance, retarget-check stops at once with exit 2 naming the
    option and the fix (it once failed every clip of the folder, one row each); retarget without
    --balance likewise."""
    clip = tmp_path / "clips" / "standing.npz"
    clip.parent.mkdir()
    save_motion(Motion(np.repeat(REST_POSE[None], 30, 0), 30.0), clip)
    out = tmp_path / "out"
    for extra in (["--robot", "ub14"], ["--no-balance"]):
        code = main(["retarget-check", str(clip.parent), "-o", str(out), "--offline-engine", "planner", *extra])
        assert code == 2 and "--offline-engine planner" in capsys.readouterr().err
        assert not out.exists()
    assert main(["retarget", str(clip), "--offline-engine", "planner", "--out", str(out)]) == 2
    assert "add --balance" in capsys.readouterr().err
