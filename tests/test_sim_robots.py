"""The bundled robot models: they compile, match the published OP3 facts and the
hardware config, follow the documented axis conventions, stand and fall."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import mujoco
import numpy as np
import pytest
import yaml
from test_op3_reference import KEYPOINT_SITES, ROBOTIS_ID_ORDER

from firmware_cfg.errors import ConfigError
from firmware_cfg.registry import bundled_names, joint_limits, joint_names, resolve
from sim.scene import Scene, SceneConfig

ROOT = Path(__file__).resolve().parents[1]
PI = math.pi
#: ROBOTIS's software limits (op3_kinematics_dynamics) for the head and the LEFT side, in
#: ROBOTIS's axes; the knee widened to 0.8 pi for ROBOTIS's sitting pose (op3.xml header).
#: A right joint's range is the left one mirrored: (-upper, -lower).
ROBOTIS_LIMITS = {
    "head_pan": (-0.5 * PI, 0.5 * PI),
    "head_tilt": (-0.5 * PI, 0.5 * PI),
    "sho_pitch": (-0.5 * PI, 0.5 * PI),
    "sho_roll": (-0.3 * PI, 0.5 * PI),
    "el": (-0.5 * PI, 0.5 * PI),
    "hip_yaw": (-0.45 * PI, 0.45 * PI),
    "hip_roll": (-0.3 * PI, 0.3 * PI),
    "hip_pitch": (-0.4 * PI, 0.4 * PI),
    "knee": (-0.1 * PI, 0.8 * PI),
    "ank_pitch": (-0.45 * PI, 0.45 * PI),
    "ank_roll": (-0.45 * PI, 0.45 * PI),
}


@pytest.fixture(scope="module")
def op3() -> Scene:
    return Scene(SceneConfig(robot="op3"))


@pytest.mark.parametrize("name", bundled_names())
def test_bundled_models_compile_with_stand_keyframe_and_sites(name):
    scene = Scene(SceneConfig(robot=name))
    m = scene.model
    assert scene.robot.joint_names == joint_names(name)  # XML reading agrees with the compiled model
    assert m.key("stand") is not None
    assert scene.robot.fixed_base == resolve(name).fixed_base == (name == "ub14")
    for site in ("pelvis", "torso", "head", "l_shoulder", "r_shoulder", "l_elbow", "r_elbow", "l_hand", "r_hand"):
        m.site(site)  # raises KeyError when missing
    # the standing pose is collision-free: no self contact, nothing below the floor
    mujoco.mj_forward(m, scene.data)
    robot = set(scene.robot.geom_ids.tolist())
    for c in scene.data.contact[: scene.data.ncon]:
        assert not (c.geom1 in robot and c.geom2 in robot), (m.geom(c.geom1).name, m.geom(c.geom2).name)
        assert c.dist > -1e-3
    assert np.all(scene.robot.stall_torque > 0) and np.all(np.isfinite(scene.robot.no_load_speed))


def test_op3_published_facts(op3):
    m = op3.model
    assert joint_names("op3") == ROBOTIS_ID_ORDER
    assert sum(m.body_mass) == pytest.approx(3.147, abs=0.001)  # ROBOTIS's description
    assert m.body("body_link").mass[0] == pytest.approx(1.34928)
    assert 0.48 <= op3.robot_height <= 0.54
    for site in KEYPOINT_SITES:
        m.site(site)
    foot = m.geom("l_foot")
    assert 2 * foot.size[0] == pytest.approx(0.127) and 2 * foot.size[1] == pytest.approx(0.080)
    # XM430-W350 at 11.1 V: stall torque, no-load speed; back-EMF damping = stall / no-load speed
    assert np.allclose(op3.robot.stall_torque, 3.8) and np.allclose(op3.robot.no_load_speed, 4.5)
    j = m.joint("r_knee")
    assert j.damping[0] >= 3.8 / 4.5
    # a saturated, unloaded servo cannot exceed the no-load speed: tau_s - b * w = 0 at w <= w0
    assert 3.8 / j.damping[0] <= 4.5 + 1e-9
    # published offsets (parent-relative)
    assert np.allclose(m.body("head_pan_link").pos, (-0.001, 0, 0.1365))
    assert np.allclose(m.body("l_sho_pitch_link").pos, (-0.001, 0.060, 0.111))
    assert np.allclose(m.body("r_sho_roll_link").pos, (0.019, -0.0285, -0.010))
    assert np.allclose(m.body("l_knee_link").pos, (0, 0, -0.11015))
    assert np.allclose(m.body("r_ank_roll_link").pos, (-0.0241, 0.019, 0))


def test_op3_limits_are_robotis_limits_mirrored_on_the_right():
    limits = joint_limits("op3")
    for joint, (lo, hi) in limits.items():
        key = joint if joint.startswith("head") else joint[2:]
        expect = (
            ROBOTIS_LIMITS[key] if not joint.startswith("r_") else (-ROBOTIS_LIMITS[key][1], -ROBOTIS_LIMITS[key][0])
        )
        assert (lo, hi) == pytest.approx(expect, abs=1e-6), joint


def test_op3_limits_match_hardware_config():
    path = ROOT / "firmware_cfg" / "robots" / "op3" / "hardware.yaml"  # bundled: its absence is a failure, not a skip
    cfg = yaml.safe_load(path.read_text())
    servos = [s for bus in cfg["buses"] for s in bus["servos"]]
    by_id = sorted(servos, key=lambda s: s["id"])
    assert tuple(s["joint"] for s in by_id) == ROBOTIS_ID_ORDER  # ID order = MJCF actuator order
    mjcf = joint_limits("op3")
    for s in servos:
        assert tuple(s["limits"]) == pytest.approx(mjcf[s["joint"]], abs=1e-6), s["joint"]


def _site_in_body_frame(scene: Scene, site: str, body: str, joints: dict) -> np.ndarray:
    d = scene.data
    mujoco.mj_resetData(scene.model, d)
    for j, v in joints.items():
        d.qpos[scene.model.joint(j).qposadr[0]] = v
    mujoco.mj_kinematics(scene.model, d)
    R = d.xmat[scene.model.body(body).id].reshape(3, 3)
    return R.T @ (d.site_xpos[scene.model.site(site).id] - d.xpos[scene.model.body(body).id])


def test_op3_axis_conventions(op3):
    """ROBOTIS's axes: the two sides are not mirrored, so a mirror-image pose has opposite
    signs on the left and the right (op3.xml's header lists each joint)."""
    # knee flexion (left +, right -): the ankle moves backwards (-X) relative to the pelvis
    assert _site_in_body_frame(op3, "l_ankle", "body_link", {"l_knee": 0.5})[0] < -0.02
    assert _site_in_body_frame(op3, "r_ankle", "body_link", {"r_knee": -0.5})[0] < -0.02
    # hip flexion (left -, right +): the thigh comes forward
    assert _site_in_body_frame(op3, "l_knee", "body_link", {"l_hip_pitch": -0.5})[0] > 0.02
    assert _site_in_body_frame(op3, "r_knee", "body_link", {"r_hip_pitch": 0.5})[0] > 0.02
    # shoulder roll: left +, right - lower the arm from the T-pose
    assert _site_in_body_frame(op3, "l_hand", "body_link", {"l_sho_roll": 1.2})[2] < -0.05
    assert _site_in_body_frame(op3, "r_hand", "body_link", {"r_sho_roll": -1.2})[2] < -0.05
    # elbow: with the arm hanging, left - and right + swing the forearm in towards the body
    hang_l = _site_in_body_frame(op3, "l_hand", "body_link", {"l_sho_roll": 1.5})
    assert _site_in_body_frame(op3, "l_hand", "body_link", {"l_sho_roll": 1.5, "l_el": -1.0})[1] < hang_l[1] - 0.05
    hang_r = _site_in_body_frame(op3, "r_hand", "body_link", {"r_sho_roll": -1.5})
    assert _site_in_body_frame(op3, "r_hand", "body_link", {"r_sho_roll": -1.5, "r_el": 1.0})[1] > hang_r[1] + 0.05
    # hip abduction (left -, right +): the foot moves outward
    assert _site_in_body_frame(op3, "l_foot", "body_link", {"l_hip_roll": -0.3})[1] > 0.1
    assert _site_in_body_frame(op3, "r_foot", "body_link", {"r_hip_roll": 0.3})[1] < -0.1
    # mirror symmetry: opposite values on the two sides give mirror-image sites
    pose = {
        "sho_pitch": 0.3,
        "sho_roll": 0.7,
        "el": 0.4,
        "hip_yaw": 0.2,
        "hip_roll": 0.15,
        "hip_pitch": -0.4,
        "knee": 0.8,
        "ank_pitch": -0.3,
        "ank_roll": 0.1,
    }
    both = {**{f"l_{k}": v for k, v in pose.items()}, **{f"r_{k}": -v for k, v in pose.items()}}
    for site in ("hand", "elbow", "knee", "ankle", "foot", "toe"):
        left = _site_in_body_frame(op3, f"l_{site}", "body_link", both)
        right = _site_in_body_frame(op3, f"r_{site}", "body_link", both)
        assert np.allclose(left * (1, -1, 1), right, atol=1e-9), site


def test_op3_stands_still_for_10_s(op3):
    op3.reset()
    m, d, r = op3.model, op3.data, op3.robot
    start_xy = d.xpos[r.root_body, :2].copy()
    mujoco.mj_step(m, d, int(10.0 / m.opt.timestep))
    assert d.time == pytest.approx(10.0)
    assert d.xpos[r.root_body, 2] > 0.95 * op3.stand_root_height
    assert np.degrees(np.arccos(d.xmat[r.root_body, 8])) < 3.0
    assert np.linalg.norm(d.xpos[r.root_body, :2] - start_xy) < 0.01
    assert np.abs(d.qpos[r.qpos_adr] - op3.stand_ctrl).max() < 0.1
    assert np.abs(d.qvel).max() < 0.02  # still, not oscillating


def test_op3_falls_when_pushed_hard(op3):
    op3.reset()
    m, d, r = op3.model, op3.data, op3.robot
    mujoco.mj_step(m, d, 250)  # settle 0.5 s
    d.xfrc_applied[r.root_body, 0] = 40.0  # N, forward, on the torso for 0.2 s
    mujoco.mj_step(m, d, 100)
    d.xfrc_applied[:] = 0.0
    mujoco.mj_step(m, d, 1000)
    tilt = np.degrees(np.arccos(d.xmat[r.root_body, 8]))
    assert tilt > 60.0 or d.xpos[r.root_body, 2] < 0.5 * op3.stand_root_height


def test_op3_survives_a_gentle_push(op3):
    op3.reset()
    m, d, r = op3.model, op3.data, op3.robot
    mujoco.mj_step(m, d, 250)
    d.xfrc_applied[r.root_body, 0] = 3.0
    mujoco.mj_step(m, d, 50)
    d.xfrc_applied[:] = 0.0
    mujoco.mj_step(m, d, 1000)
    assert np.degrees(np.arccos(d.xmat[r.root_body, 8])) < 10.0


def test_unknown_robot_is_a_clear_error():
    with pytest.raises(ConfigError, match="bundled robots are op3, ub14"):
        resolve("nao")
    with pytest.raises(ConfigError, match="no such file or folder"):
        resolve("/nonexistent/robot.xml")


def test_importing_sim_does_not_import_mujoco_or_torch():
    code = (
        "import sys, sim, firmware_cfg.registry as r; r.joint_limits('op3'); "
        "print('mujoco' in sys.modules, 'torch' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    assert out.stdout.split() == ["False", "False"]


def test_servo_torque_speed_curve_caps_speed_at_no_load_speed():
    """A big step on head_pan (vertical axis: no gravity load) saturates the servo; the
    back-EMF term makes the torque fall with speed, so the joint settles near
    (tau_s - friction) / b = (3.8 - 0.05) / 0.864 = 4.34 rad/s and never above 4.5."""
    scene = Scene(SceneConfig(robot="op3", fixed_base=True, base_pos=(0, 0, 0.5)))
    m, d, r = scene.model, scene.data, scene.robot
    j = r.joint_names.index("head_pan")
    d.ctrl[r.actuator_ids[j]] = 1.5
    speeds, forces = [], []
    for _ in range(150):  # 0.3 s
        mujoco.mj_step(m, d)
        speeds.append(d.qvel[r.dof_adr[j]])
        forces.append(d.actuator_force[r.actuator_ids[j]])
    speeds = np.array(speeds)
    assert forces[0] == pytest.approx(3.8)  # saturated at the stall torque
    assert 4.0 < speeds.max() <= 4.5
    plateau = speeds[(speeds > 0.95 * speeds.max())]
    assert len(plateau) > 20  # it runs at the no-load-limited speed for a while, not a spike
