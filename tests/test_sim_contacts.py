"""Support-polygon margins (vectorised over runs of ticks) and the root pose the check
reads from qpos instead of copying MuJoCo's body frames every tick."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from sim.check import _root_pose_series
from sim.contacts import SupportMargin, support_margin
from sim.scene import Scene

SQUARE = np.array([[-0.05, -0.03], [0.05, -0.03], [0.05, 0.03], [-0.05, 0.03]])  # 100 x 60 mm


@pytest.mark.parametrize("point, expected", [
    ((0.0, 0.0), 0.03),  # centre: nearest edges are the long ones, 30 mm away
    ((0.04, 0.0), 0.01),  # 10 mm from the front edge
    ((0.08, 0.0), -0.03),  # 30 mm in front of the front edge
    ((0.08, 0.07), -0.05),  # beyond a corner: 30 mm by 40 mm -> 50 mm
])
def test_margin_to_a_rectangle(point, expected):
    assert support_margin(np.array(point), SQUARE) == pytest.approx(expected, abs=1e-12)


def test_degenerate_supports_and_no_support():
    seg = np.array([[0.0, 0.0], [0.1, 0.0], [0.05, 0.0]])  # collinear: a segment 0..0.1 on x
    assert support_margin(np.array([0.05, 0.02]), seg) == pytest.approx(-0.02)
    assert support_margin(np.array([0.13, -0.04]), seg) == pytest.approx(-0.05)
    assert support_margin(np.array([0.03, 0.04]), np.array([[0.0, 0.0]])) == pytest.approx(-0.05)
    assert math.isnan(support_margin(np.array([0.0, 0.0]), np.zeros((0, 2))))


def test_many_equals_one_tick_at_a_time():
    """Runs of equal polygons, jitter below the rounding, changing counts, empty
    ticks and degenerate polygons: the vectorised margins equal the per-tick ones."""
    rng = np.random.default_rng(3)
    polys, cur = [], SQUARE
    for k in range(400):
        r = rng.random()
        if r < 0.15:
            n = int(rng.choice([0, 1, 2, 3, 4, 8]))
            cur = rng.normal(0, 0.05, (n, 2))
        elif r < 0.3:
            cur = cur + rng.normal(0, 2e-4, cur.shape)  # same polygon after 1 mm rounding, mostly
        polys.append(cur.copy())
    points = rng.normal(0, 0.06, (len(polys), 2))
    got = SupportMargin().many(points, polys)
    run_first = []  # the polygon a run is evaluated with: its first tick's points
    for k, p in enumerate(polys):
        same = k > 0 and len(p) == len(polys[k - 1]) and np.array_equal(np.round(p / 1e-3), np.round(polys[k - 1] / 1e-3))
        run_first.append(run_first[-1] if same else p)
    want = np.array([support_margin(x, p) for x, p in zip(points, run_first)])
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    np.testing.assert_allclose(got[~np.isnan(want)], want[~np.isnan(want)], atol=1e-12)
    assert np.isnan(want).any() and (want < 0).any() and (want > 0).any()


def test_root_pose_from_qpos_matches_mujoco_frames():
    scene = Scene()
    m, d, r = scene.model, scene.data, scene.robot
    rng = np.random.default_rng(0)
    qpos, pos, zz = [], [], []
    for _ in range(5):
        quat = rng.normal(size=4) * rng.uniform(0.5, 2.0)  # not unit length: MuJoCo normalises
        scene.set_robot_pose(scene.stand_ctrl, rng.normal(size=3), quat)
        mujoco.mj_kinematics(m, d)
        qpos.append(d.qpos.copy())
        pos.append(d.xpos[r.root_body].copy())
        zz.append(d.xmat[r.root_body, 8])
    got_pos, got_zz = _root_pose_series(np.array(qpos + [qpos[0]]), r.free_qpos, d.xpos[r.root_body], d.xmat[r.root_body], 5)
    np.testing.assert_allclose(got_pos[:5], pos, atol=1e-12)
    np.testing.assert_allclose(got_zz[:5], zz, atol=1e-12)
    assert np.isnan(got_pos[5]).all() and np.isnan(got_zz[5])  # after the run: not simulated
