"""The real CMU two-person capture retargeted to both bundled robots (skips without the data)."""

import numpy as np
import pytest

from retarget.offline import OfflineConfig, OfflineRetargeter
from retarget.report import configurations, evaluate
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
        assert rep.keypoint_error_mean_mm < 0.05 * size_mm  # within 5 % of the robot's size
        if rb.floating:
            sole = rb.evaluate(configurations(rb, traj))["sole"]
            assert sole[..., 2].min() > -1e-4  # no foot below the ground
            for side in range(2):
                z = sole[tg.contacts[:, side], 4 * side : 4 * side + 4, 2]
                assert np.abs(z).max() < 1e-4  # feet in contact are on it
            assert rep.skate_share < 0.02
