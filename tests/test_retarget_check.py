"""End to end: retarget-check over a folder with a good clip, a broken file and a motion too
fast for the servos. Real BVH parser, CasADi/IPOPT and MuJoCo, two worker processes."""

import csv

import numpy as np
import pytest

from dualflow.motion import REST_POSE, Motion
from dualflow.motion.io import save_motion
from dualflow.synthetic import make_leader
from ros_free_bridge.cli import main

pytestmark = pytest.mark.slow


def test_a_folder_gives_one_row_per_clip_and_a_failure_never_stops_the_batch(tmp_path, capsys):
    clips = tmp_path / "clips"
    clips.mkdir()
    save_motion(Motion(np.repeat(REST_POSE[None], 60, 0), 30.0), clips / "standing.npz")
    leader = make_leader(3.0, 30.0, 1)
    save_motion(Motion(leader.positions, fps=120.0).resample(30.0), clips / "too_fast.npz")  # 4x faster
    (clips / "broken.bvh").write_text("HIERARCHY\nROOT Hips\n{\n OFFSET 0 0\n")
    out = tmp_path / "out"
    code = main(["retarget-check", str(clips), "-o", str(out), "--jobs", "2", "--no-compile"])
    assert code == 1  # not every clip passes
    rows = {r["clip"]: r for r in csv.DictReader(open(out / "results.csv"))}
    assert list(rows) == ["broken.bvh", "standing.npz", "too_fast.npz"]  # file order, all present
    assert rows["broken.bvh"]["status"] == "error" and "line 4" in rows["broken.bvh"]["reason"]
    assert rows["standing.npz"]["status"] == "pass"
    fast = rows["too_fast.npz"]
    # 4x too fast: either no trajectory within the servo limits exists at this speed (retarget
    # stage, offering re-timing) or the limit-respecting trajectory cannot be played (check stage)
    assert fast["status"] == "fail" and fast["stage"] in ("retarget", "check")
    if fast["stage"] == "retarget":
        assert "infeasible" in fast["reason"] and "retime" in fast["reason"]
    else:
        assert fast["check_reason"] and fast["limit_violations"] == "0"
    for name in ("trajectory.npz", "retarget.report.json", "check.json", "check.md"):
        assert (out / "clips" / "standing" / name).stat().st_size > 0, name
    table = (out / "results.md").read_text()
    assert "1 of 3 clips pass" in table and "| standing.npz | PASS |" in table
    assert "too_fast.npz" in capsys.readouterr().out
