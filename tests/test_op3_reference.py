"""The bundled op3 is the real ROBOTIS OP3: its kinematics, axes, masses and inertias agree
with MuJoCo Menagerie's model of ROBOTIS's description (../shared/robots/robotis_op3, a
reference kept outside the package), and it stands on its own servos from its "stand"
keyframe.

The model is loaded by path (firmware_cfg/robots/op3/op3.xml), so these tests judge the
robot's files alone, whatever resolves robot names.
"""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
OP3_XML = ROOT / "firmware_cfg" / "robots" / "op3" / "op3.xml"
REFERENCE_XML = Path(__file__).resolve().parents[2] / "shared" / "robots" / "robotis_op3" / "op3.xml"
needs_reference = pytest.mark.skipif(
    not REFERENCE_XML.is_file(),
    reason=f"reference model not found at {REFERENCE_XML} (../shared/robots is absent on this machine)",
)

#: Retarget keypoint sites every bundled humanoid with legs has (its profile names them).
KEYPOINT_SITES = (
    "pelvis",
    "torso",
    "head",
    "l_shoulder",
    "r_shoulder",
    "l_elbow",
    "r_elbow",
    "l_hand",
    "r_hand",
    "l_hip",
    "r_hip",
    "l_knee",
    "r_knee",
    "l_ankle",
    "r_ankle",
    "l_foot",
    "r_foot",
    "l_toe",
    "r_toe",
)
#: ROBOTIS's servo IDs 1..20, in order.
ROBOTIS_ID_ORDER = (
    "r_sho_pitch",
    "l_sho_pitch",
    "r_sho_roll",
    "l_sho_roll",
    "r_el",
    "l_el",
    "r_hip_yaw",
    "l_hip_yaw",
    "r_hip_roll",
    "l_hip_roll",
    "r_hip_pitch",
    "l_hip_pitch",
    "r_knee",
    "l_knee",
    "r_ank_pitch",
    "l_ank_pitch",
    "r_ank_roll",
    "l_ank_roll",
    "head_pan",
    "head_tilt",
)


@pytest.fixture(scope="module")
def ours() -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(OP3_XML))


@pytest.fixture(scope="module")
def ref() -> mujoco.MjModel:
    if not REFERENCE_XML.is_file():
        pytest.skip(f"reference model not found at {REFERENCE_XML}")
    return mujoco.MjModel.from_xml_path(str(REFERENCE_XML))


def _hinges(m: mujoco.MjModel) -> list[str]:
    return [m.joint(j).name for j in range(m.njnt) if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE]


def _pose(m: mujoco.MjModel, d: mujoco.MjData, root: np.ndarray, q: dict) -> None:
    """Free root at ``root`` (x y z qw qx qy qz), hinges by name, then forward kinematics."""
    d.qpos[:7] = root
    for name, value in q.items():
        d.qpos[m.joint(name).qposadr[0]] = value
    mujoco.mj_kinematics(m, d)


def _inertia_tensor(m: mujoco.MjModel, b: int) -> np.ndarray:
    """(3, 3) inertia about the body's centre of mass, in the body frame."""
    R = np.zeros(9)
    mujoco.mju_quat2Mat(R, m.body_iquat[b])
    R = R.reshape(3, 3)
    return R @ np.diag(m.body_inertia[b]) @ R.T


@needs_reference
def test_same_bodies_and_joints(ours, ref):
    ref_bodies = {ref.body(b).name for b in range(1, ref.nbody)}
    our_bodies = {ours.body(b).name for b in range(1, ours.nbody)}
    assert ref_bodies == our_bodies
    assert set(_hinges(ref)) == set(_hinges(ours)) == set(ROBOTIS_ID_ORDER)
    for name in _hinges(ref):
        assert ours.body(ours.joint(name).bodyid[0]).name == ref.body(ref.joint(name).bodyid[0]).name, name


@needs_reference
def test_forward_kinematics_of_every_body_matches_over_1000_random_poses(ours, ref):
    """World position and orientation of every body frame, for random root poses and joint
    angles drawn within op3's ranges: at most 1 mm apart (measured: identical)."""
    rng = np.random.default_rng(23)
    do, dr = mujoco.MjData(ours), mujoco.MjData(ref)
    names = _hinges(ours)
    pairs = [(ours.body(ref.body(b).name).id, b) for b in range(1, ref.nbody)]
    ours_ids, ref_ids = (np.array(v) for v in zip(*pairs))
    worst_pos = worst_rot = 0.0
    for _ in range(1000):
        q = {n: rng.uniform(*ours.joint(n).range) for n in names}
        root = np.concatenate([rng.uniform(-1.0, 1.0, 3), rng.normal(size=4)])
        root[3:] /= np.linalg.norm(root[3:])
        _pose(ours, do, root, q)
        _pose(ref, dr, root, q)
        worst_pos = max(worst_pos, float(np.linalg.norm(do.xpos[ours_ids] - dr.xpos[ref_ids], axis=1).max()))
        worst_rot = max(worst_rot, float(np.abs(do.xmat[ours_ids] - dr.xmat[ref_ids]).max()))
    assert worst_pos <= 1e-3, f"body frames up to {worst_pos * 1000:.3f} mm apart"
    assert worst_rot <= 1e-3, f"body orientations differ by up to {worst_rot:.2e} (rotation-matrix entries)"


@needs_reference
def test_joint_axes_and_anchors_match_in_the_world_at_zero_pose(ours, ref):
    do, dr = mujoco.MjData(ours), mujoco.MjData(ref)
    root = np.array([0.0, 0.0, 0.3, 1.0, 0.0, 0.0, 0.0])
    _pose(ours, do, root, {})
    _pose(ref, dr, root, {})
    mujoco.mj_comPos(ours, do)
    mujoco.mj_comPos(ref, dr)
    for name in _hinges(ref):
        jo, jr = ours.joint(name).id, ref.joint(name).id
        assert np.allclose(do.xaxis[jo], dr.xaxis[jr], atol=1e-9), (name, do.xaxis[jo], dr.xaxis[jr])
        assert np.allclose(do.xanchor[jo], dr.xanchor[jr], atol=1e-6), name


@needs_reference
def test_masses_within_5_percent_total_and_per_link(ours, ref):
    total_ours, total_ref = ours.body_subtreemass[1], ref.body_subtreemass[1]
    assert total_ours == pytest.approx(total_ref, rel=0.05)
    for b in range(1, ref.nbody):
        name = ref.body(b).name
        assert ours.body(name).mass[0] == pytest.approx(ref.body_mass[b], rel=0.05), name


@needs_reference
def test_centres_of_mass_and_inertias_match(ours, ref):
    """Centre of mass within 1 mm in the link frame; the inertia tensor about it within 5 %
    (Frobenius norm of the difference over the reference's norm)."""
    for b in range(1, ref.nbody):
        name = ref.body(b).name
        o = ours.body(name).id
        assert np.linalg.norm(ours.body_ipos[o] - ref.body_ipos[b]) <= 1e-3, name
        I_ours, I_ref = _inertia_tensor(ours, o), _inertia_tensor(ref, b)
        assert np.linalg.norm(I_ours - I_ref) <= 0.05 * np.linalg.norm(I_ref), (name, I_ours, I_ref)


def test_servo_id_order_imu_and_keypoint_sites(ours):
    actuated = tuple(ours.joint(ours.actuator_trnid[a, 0]).name for a in range(ours.nu))
    assert actuated == ROBOTIS_ID_ORDER
    assert tuple(ours.actuator(a).name for a in range(ours.nu)) == ROBOTIS_ID_ORDER
    imu = ours.site("imu")
    assert ours.body(imu.bodyid[0]).name == "body_link"
    for sensor, kind in (
        ("imu_gyro", mujoco.mjtSensor.mjSENS_GYRO),
        ("imu_accel", mujoco.mjtSensor.mjSENS_ACCELEROMETER),
        ("imu_quat", mujoco.mjtSensor.mjSENS_FRAMEQUAT),
    ):
        s = ours.sensor(sensor)
        assert s.type[0] == kind and s.objid[0] == imu.id, sensor
    for site in KEYPOINT_SITES:
        ours.site(site)
    for foot in ("l_foot", "r_foot"):
        g = ours.geom(foot)
        assert g.type[0] == mujoco.mjtGeom.mjGEOM_BOX
        assert 2 * g.size[:2] == pytest.approx((0.127, 0.080))
    assert all(ours.geom(g).name for g in range(ours.ngeom))


def test_knee_signs_are_robotis(ours):
    """On the real OP3 the left knee flexes with positive angles, the right with negative
    ones: flexion moves the ankle backwards (-X)."""
    d = mujoco.MjData(ours)
    root = np.array([0.0, 0.0, 0.3, 1.0, 0.0, 0.0, 0.0])
    _pose(ours, d, root, {})
    rest = {s: d.site_xpos[ours.site(s).id].copy() for s in ("l_ankle", "r_ankle")}
    _pose(ours, d, root, {"l_knee": 0.5, "r_knee": -0.5})
    for s in ("l_ankle", "r_ankle"):
        assert d.site_xpos[ours.site(s).id][0] - rest[s][0] < -0.02, s
    assert ours.joint("l_knee").range[1] > 2.0 and ours.joint("r_knee").range[0] < -2.0


def _scene_with_floor() -> tuple[mujoco.MjModel, mujoco.MjData]:
    spec = mujoco.MjSpec.from_file(str(OP3_XML))
    spec.worldbody.add_geom(
        name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[2.0, 2.0, 0.1], friction=[1.0, 0.02, 0.001]
    )
    m = spec.compile()
    d = mujoco.MjData(m)
    mujoco.mj_resetDataKeyframe(m, d, m.key("stand").id)
    mujoco.mj_forward(m, d)
    return m, d


def test_stand_keyframe_rests_on_flat_feet_without_self_contact():
    m, d = _scene_with_floor()
    floor = m.geom("floor").id
    for c in d.contact[: d.ncon]:
        assert floor in (c.geom1, c.geom2), (m.geom(c.geom1).name, m.geom(c.geom2).name)
        assert abs(c.dist) < 1e-3
    for foot in ("l_foot", "r_foot"):
        assert abs(d.site_xpos[m.site(foot).id][2]) < 1e-4
        assert d.xmat[m.body(m.geom(foot).bodyid[0]).id][8] == pytest.approx(1.0, abs=1e-6)  # sole level


def test_stands_for_3_s_holding_the_stand_keyframe():
    """Position servos hold the keyframe's ctrl: the torso stays within a few degrees of
    upright (measured: 0.4 deg), the root does not wander (5 mm, from the servos giving under
    the weight) and the feet do not slide."""
    m, d = _scene_with_floor()
    root0 = d.xpos[1].copy()
    feet0 = np.array([d.site_xpos[m.site(s).id][:2] for s in ("l_foot", "r_foot")])
    mujoco.mj_step(m, d, int(round(3.0 / m.opt.timestep)))
    tilt = np.degrees(np.arccos(np.clip(d.xmat[1][8], -1.0, 1.0)))
    assert tilt < 2.0
    assert np.linalg.norm(d.xpos[1][:2] - root0[:2]) < 0.01
    assert d.xpos[1][2] > root0[2] - 0.005
    feet = np.array([d.site_xpos[m.site(s).id][:2] for s in ("l_foot", "r_foot")])
    assert np.abs(feet - feet0).max() < 0.002
    assert np.abs(d.qvel).max() < 0.05
