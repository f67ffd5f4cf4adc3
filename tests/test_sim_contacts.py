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


@pytest.mark.parametrize(
    "point, expected",
    [
        ((0.0, 0.0), 0.03),  # centre: nearest edges are the long ones, 30 mm away
        ((0.04, 0.0), 0.01),  # 10 mm from the front edge
        ((0.08, 0.0), -0.03),  # 30 mm in front of the front edge
        ((0.08, 0.07), -0.05),  # beyond a corner: 30 mm by 40 mm -> 50 mm
    ],
)
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
    for _ in range(400):
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
        same = (
            k > 0 and len(p) == len(polys[k - 1]) and np.array_equal(np.round(p / 1e-3), np.round(polys[k - 1] / 1e-3))
        )
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
    got_pos, got_zz = _root_pose_series(
        np.array(qpos + [qpos[0]]), r.free_qpos, d.xpos[r.root_body], d.xmat[r.root_body], 5
    )
    np.testing.assert_allclose(got_pos[:5], pos, atol=1e-12)
    np.testing.assert_allclose(got_zz[:5], zz, atol=1e-12)
    assert np.isnan(got_pos[5]).all() and np.isnan(got_zz[5])  # after the run: not simulated


def _contacts(scene: Scene) -> list[tuple]:
    """The current contacts as comparable rows: sorted geom pair, depth, point, normal,
    dimension, friction, solref, solimp, margin, adhesion."""
    c = scene.data.contact
    rows = []
    for i in range(scene.data.ncon):
        g = tuple(sorted(int(x) for x in c.geom[i]))
        rows.append(
            (
                g,
                round(float(c.dist[i]), 12),
                tuple(np.round(c.pos[i], 12)),
                tuple(np.round(np.abs(c.frame[i, :3]), 12)),
                int(c.dim[i]),
                tuple(np.round(c.friction[i], 12)),
                tuple(c.solref[i]),
                tuple(c.solimp[i]),
                float(c.includemargin[i]),
                float(c.adhesion[i]),
            )
        )
    return sorted(rows)


@pytest.mark.parametrize("robot, fixed", [("op3", None), ("op3", True), ("ub14", None)])
def test_floor_pairs_give_the_same_contacts_as_the_dynamic_floor(robot, fixed):
    """Robot-floor contacts come from explicit pairs (the floor out of the broad phase):
    standing, lying on its side and crumpled, the contacts equal the dynamic floor's
    (pairs, depths, points, friction, solver parameters), and so does the motion."""
    from sim.scene import SceneConfig

    pair = Scene(SceneConfig(robot=robot, fixed_base=fixed))
    dyn = Scene(SceneConfig(robot=robot, fixed_base=fixed, floor_pairs=False))
    assert pair.model.npair > 0 and dyn.model.npair == 0
    assert pair.model.geom_contype[pair.floor_geom] == 0 and dyn.model.geom_contype[dyn.floor_geom] == 1
    rng = np.random.default_rng(7)
    r = pair.robot
    poses = [(pair.stand_ctrl, (1.0, 0.0, 0.0, 0.0))]
    for _ in range(4):  # random in-limit joints, tilted or lying root
        q = rng.uniform(r.lower, r.upper)
        quat = rng.normal(size=4)
        poses.append((q, tuple(quat / np.linalg.norm(quat))))
    touched = set()
    for q, quat in poses:
        for sc in (pair, dyn):
            sc.set_robot_pose(q, (0.0, 0.0, 0.3), quat, ground=True)
            if not sc.robot.fixed_base:  # 3 mm into the floor: depths are compared too
                sc.data.qpos[sc.robot.free_qpos + 2] -= 0.003
                mujoco.mj_forward(sc.model, sc.data)
        got, want = _contacts(pair), _contacts(dyn)
        assert got == want
        touched |= {g for row in got for g in row[0] if pair.floor_geom in row[0]}
        mujoco.mj_step(pair.model, pair.data, 100)
        mujoco.mj_step(dyn.model, dyn.data, 100)
        np.testing.assert_allclose(pair.data.qpos, dyn.data.qpos, atol=1e-9)
    if not pair.robot.fixed_base:
        assert len(touched - {pair.floor_geom}) >= 4  # more than the feet touched the floor


def test_floor_stays_dynamic_when_a_geom_needs_other_mixing(tmp_path):
    """A robot geom with a contact priority (its parameters win, not the mix): no pairs are
    made and the floor keeps its contype/conaffinity, so contacts still happen."""
    from sim.scene import SceneConfig

    xml = tmp_path / "bot.xml"
    xml.write_text("""<mujoco><worldbody><body name="base" pos="0 0 0.2"><freejoint/>
      <geom name="trunk" type="box" size="0.05 0.05 0.05" mass="1"/>
      <body name="leg" pos="0 0 -0.05"><joint name="j" axis="0 1 0" range="-1 1"/>
        <geom name="shin" type="capsule" fromto="0 0 0 0 0 -0.1" size="0.02" priority="1" mass="0.2"/>
      </body></body></worldbody>
      <actuator><position name="j" joint="j" kp="5"/></actuator></mujoco>""")
    sc = Scene(SceneConfig(robot=str(xml)))
    assert sc.model.npair == 0 and sc.model.geom_contype[sc.floor_geom] == 1
    sc.set_robot_pose(np.zeros(1), (0.0, 0.0, 0.3), (1.0, 0.0, 0.0, 0.0), ground=True)
    mujoco.mj_step(sc.model, sc.data, 50)
    assert sc.data.ncon > 0
