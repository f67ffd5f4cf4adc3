"""The real CMU two-person capture retargeted to both bundled robots (skips without the data)."""

import numpy as np
import pytest

from retarget.offline import OfflineConfig, OfflineRetargeter
from retarget.report import clip_targets, configurations, evaluate
from retarget.robot import load_robot
from retarget.targets import make_targets

ROBOTS = ["op3", "ub14"]


@pytest.fixture(scope="module")
def cmu_people(request):
    from conftest import CMU_DIR, _require

    a, b = _require(CMU_DIR / "18_01.bvh"), _require(CMU_DIR / "19_01.bvh")  # skips where ../shared/data is absent
    from dualflow.motion.io import load_pair, put_on_ground

    pair = put_on_ground(load_pair(a, b, fps=30.0))
    return [pair.actor, pair.reactor]


@pytest.mark.slow
@pytest.mark.parametrize("robot", ROBOTS)
def test_cmu_clips_retarget_within_limits_with_feet_on_the_ground(robot, cmu_people):
    rb = load_robot(robot)
    r = OfflineRetargeter(rb, OfflineConfig(window=40, overlap=10, compile=False))
    for person in cmu_people:
        traj = r.retarget(person)
        tg = make_targets(rb, person)
        rep = evaluate(rb, traj, tg)
        assert rep.limit_violations == 0 and rep.velocity_violations == 0, rep
        assert rep.self_collisions == 0
        size_mm = 1000 * np.ptp(rb.robot_rest_keypoints, axis=0).max()
        # within 5 % of the robot's size where the robot follows the person, within 10 % in the
        # parts it reports doing differently (by default the op3 is led in from standing: 18_01's
        # right foot, in the air in the first frame, is held down 0.4 s, and the step each person
        # starts before the clip ends is not made: 33 mm mean over the whole clip, 55 mm in that step)
        kp = rb.evaluate(configurations(rb, traj))["keypoints"]
        tk, _, clip_t = clip_targets(traj, tg)
        err = 1000 * np.linalg.norm(kp - tk, axis=-1).mean(axis=1)  # (T,) mm, NaN in a lead-in
        changed = np.zeros(len(clip_t), dtype=bool)
        for c in rep.changes:
            if c["what"] != "lead-in":
                changed |= (clip_t >= c["start_s"] - 1e-6) & (clip_t < c["end_s"] - 1e-6)
            assert c.get("keypoint_error_mm", 0.0) < 0.1 * size_mm, c
        clip = clip_t >= -1e-9
        follows = clip & ~changed
        assert follows.sum() > 0.5 * clip.sum() and err[follows].mean() < 0.05 * size_mm, err[follows].mean()
        assert rep.keypoint_error_mean_mm < 0.1 * size_mm
        if rb.floating:
            sole = rb.evaluate(configurations(rb, traj))["sole"]
            assert sole[..., 2].min() > -1e-4  # no foot below the ground
            planned = np.asarray(traj.meta["contacts"], dtype=bool)  # the robot's schedule (a lead-in's too)
            for side in range(2):
                z = sole[planned[:, side], 4 * side : 4 * side + 4, 2]
                assert np.abs(z).max() < 1e-4  # feet in contact are on it
            assert rep.skate_share < 0.02
