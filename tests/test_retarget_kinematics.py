"""Symbolic CasADi kinematics against MuJoCo's own forward kinematics, and the geometry helpers."""

import casadi as ca
import mujoco
import numpy as np
import pytest
from retarget_toy import TOY_XML

from firmware_cfg.registry import resolve
from retarget import RetargetError
from retarget.kinematics import RobotKinematics, euler_to_mat, mat_to_euler, mat_to_quat, quat_to_mat
from retarget.robot import segment_distance_sq

ROBOTS = [resolve(name).mjcf for name in ("op3", "ub14")]


def _random_qpos(m, rng):
    qpos = m.qpos0.copy()
    for j in range(m.njnt):
        adr = m.jnt_qposadr[j]
        if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
            qpos[adr : adr + 3] = rng.normal(size=3)
            q = rng.normal(size=4)
            qpos[adr + 3 : adr + 7] = q / np.linalg.norm(q)
        else:
            qpos[adr] = rng.uniform(-3.0, 3.0)  # beyond the ranges on purpose: FK must hold anywhere
    return qpos


def _check_against_mujoco(model, n=40, seed=0):
    kin = RobotKinematics(model, "m")
    frames = [kin.body_frame(b) for b in range(1, model.nbody)]
    f = kin.function(
        "fk",
        [
            ca.vertcat(*[p for p, _ in frames]),
            ca.vertcat(*[ca.reshape(R.T, 9, 1) for _, R in frames]),
            ca.vertcat(*[kin.site_point(s) for s in range(model.nsite)]) if model.nsite else ca.SX.zeros(0, 1),
            kin.com(),
        ],
    )
    data = mujoco.MjData(model)
    rng = np.random.default_rng(seed)
    worst = 0.0
    for _ in range(n):
        qpos = _random_qpos(model, rng)
        data.qpos[:] = qpos
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        P, R, S, C = (np.array(v) for v in f(kin.x_from_qpos(qpos)))
        worst = max(
            worst,
            np.abs(P.reshape(-1, 3) - data.xpos[1:]).max(),
            np.abs(R.reshape(-1, 3, 3) - data.xmat[1:].reshape(-1, 3, 3)).max(),
            np.abs(S.reshape(-1, 3) - data.site_xpos).max() if model.nsite else 0.0,
        )
        assert np.allclose(C.ravel(), data.subtree_com[0], atol=1e-9)
    return worst, kin


def test_toy_fk_matches_mujoco_to_1e9():
    worst, kin = _check_against_mujoco(mujoco.MjModel.from_xml_string(TOY_XML))
    assert worst < 1e-9
    assert kin.floating and kin.nx == 6 + 20


@pytest.mark.parametrize("path", ROBOTS, ids=[p.stem for p in ROBOTS])
def test_bundled_robot_fk_matches_mujoco_to_1e9(path):
    worst, kin = _check_against_mujoco(mujoco.MjModel.from_xml_path(str(path)), n=25, seed=1)
    assert worst < 1e-9


def test_joint_order_follows_the_actuators():
    assert ROBOTS, "the bundled robot MJCFs are missing from the package"
    kin = RobotKinematics.from_xml(ROBOTS[0])
    m = kin.model
    assert kin.joint_names == tuple(mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, a) for a in range(m.nu))


def test_qpos_round_trip_and_euler_helpers():
    model = mujoco.MjModel.from_xml_string(TOY_XML)
    kin = RobotKinematics(model, "toy")
    rng = np.random.default_rng(3)
    for _ in range(10):
        qpos = _random_qpos(model, rng)
        back = kin.qpos_from_x(kin.x_from_qpos(qpos))
        assert np.allclose(back[:3], qpos[:3]) and np.allclose(back[7:], qpos[7:])
        assert np.allclose(quat_to_mat(back[3:7]), quat_to_mat(qpos[3:7]), atol=1e-12)
    e = np.array([2.5, -0.7, 1.1])
    assert np.allclose(mat_to_euler(euler_to_mat(e)), e)
    R = euler_to_mat(e)
    assert np.allclose(quat_to_mat(mat_to_quat(R)), R)


def test_fixed_base_option_freezes_the_root():
    model = mujoco.MjModel.from_xml_string(TOY_XML)
    kin = RobotKinematics(model, "toy", fixed_base=True)
    assert not kin.floating and kin.nx == 20
    pos, quat = kin.root_pose(np.zeros((3, 20)))
    assert np.allclose(pos, model.qpos0[:3]) and np.allclose(quat, [1, 0, 0, 0])


def test_segment_distance_matches_brute_force():
    rng = np.random.default_rng(4)
    s = np.linspace(0, 1, 401)
    for _ in range(30):
        p0, p1, q0, q1 = rng.normal(size=(4, 3))
        if rng.random() < 0.3:
            q1 = q0 + 0.5 * (p1 - p0)  # parallel segments
        a = p0 + s[:, None] * (p1 - p0)
        b = q0 + s[:, None] * (q1 - q0)
        brute = np.min(np.sum((a[:, None] - b[None]) ** 2, axis=-1))
        got = segment_distance_sq(p0, p1, q0, q1)
        assert got <= brute + 1e-9
        assert got == pytest.approx(brute, abs=2e-3 * (1 + brute))


def test_missing_mjcf_and_ball_joints_are_user_errors(tmp_path):
    with pytest.raises(RetargetError, match="not found"):
        RobotKinematics.from_xml(tmp_path / "nope.xml")
    ball = TOY_XML.replace(
        '<joint name="head_pan" axis="0 0 1" range="-1.5 1.5"/>', '<joint name="head_pan" type="ball"/>'
    )
    with pytest.raises(RetargetError, match="ball joint"):
        RobotKinematics(mujoco.MjModel.from_xml_string(ball), "toy")
