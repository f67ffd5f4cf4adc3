"""``check``, ``render`` and ``view`` take an MJCF as published (issue 23, item 4).

The reference models in ../shared/robots (MuJoCo Menagerie's robotis_op3 and unitree_g1)
are used unmodified, by path: their feet carry no ``l_foot``/``r_foot`` sites, the OP3's
joints have no range and it has no keyframe, the G1 limits its torques on the joints
(``actuatorfrcrange``), and both come with a ``scene.xml`` that adds its own floor. Those
tests skip where ../shared is absent. Small hand-written MJCFs cover the rest (unnamed
geoms, joints nobody gives a limit, missing servo data).
"""

from __future__ import annotations

import textwrap
from pathlib import Path

import mujoco
import numpy as np
import pytest

from retarget.trajectory import RobotTrajectory
from sim import SimError
from sim.check import CheckConfig, check_trajectory
from sim.report import markdown
from sim.scene import Scene, SceneConfig
from sim.virtual_robot import VirtualRobot, VirtualRobotConfig

SHARED_ROBOTS = Path(__file__).resolve().parents[2] / "shared" / "robots"
OP3_DIR = SHARED_ROBOTS / "robotis_op3"
G1_DIR = SHARED_ROBOTS / "unitree_g1"

#: model file -> the bodies that are its left and right feet
FEET = {
    OP3_DIR / "op3.xml": ("l_ank_roll_link", "r_ank_roll_link"),
    OP3_DIR / "scene.xml": ("l_ank_roll_link", "r_ank_roll_link"),
    G1_DIR / "g1.xml": ("left_ankle_roll_link", "right_ankle_roll_link"),
    G1_DIR / "scene.xml": ("left_ankle_roll_link", "right_ankle_roll_link"),
}


def _need(path: Path) -> Path:
    if not path.is_file():
        pytest.skip(f"reference model not found at {path} (../shared/robots is absent on this machine)")
    return path


def _standing(scene: Scene, seconds: float = 2.0, robot: str = "") -> RobotTrajectory:
    """The scene's standing pose held for ``seconds`` at 30 fps."""
    return RobotTrajectory.standing(
        scene.robot.joint_names,
        scene.stand_ctrl,
        int(round(seconds * 30)) + 1,
        30.0,
        root_pos=scene.data.xpos[scene.robot.root_body].copy(),
        robot=robot or scene.config.robot,
    )


def _world_planes(model: mujoco.MjModel) -> list[int]:
    return [
        g for g in range(model.ngeom) if model.geom_bodyid[g] == 0 and model.geom_type[g] == mujoco.mjtGeom.mjGEOM_PLANE
    ]


# -- the reference models, unmodified ------------------------------------------------------
@pytest.mark.parametrize("model", list(FEET), ids=lambda p: f"{p.parent.name}/{p.name}")
def test_reference_model_stands_through_the_check(model):
    """The stand pose held 2 s: the check runs, finds the right feet, has one floor, and
    passes (standing still breaks nothing), saying what it could not check."""
    _need(model)
    scene = Scene(SceneConfig(robot=str(model)))
    m = scene.model
    assert len(_world_planes(m)) == 1 and m.geom(scene.floor_geom).name == "floor"
    left, right = FEET[model]
    assert [(f.side, m.body(f.body).name) for f in scene.robot.feet] == [("left", left), ("right", right)]
    assert abs(scene.lowest_robot_point()) < 2e-3  # standing on the floor, not above or in it

    result = check_trajectory(_standing(scene), CheckConfig())
    assert result.passed, result.failures
    assert result.metrics["feet"] == {"left": [left], "right": [right]}
    assert result.metrics["max_tilt_deg"] < 5 and result.metrics["min_com_margin_m"] > 0.01
    # published models carry no servo speed: the speed test says it did not run
    assert "speed_limit" in result.not_checked and "any joint" in result.not_checked["speed_limit"]
    assert "speed_limit" in result.summary()["not_checked"]
    assert "Not checked" in markdown(result) and "servo_no_load_speed" in markdown(result)


def test_op3_reference_gets_a_derived_standing_pose_and_limits_from_its_servos():
    """No keyframe and no joint ranges: the standing pose is derived (joints at 0, feet on
    the floor) and the position servos' ctrlrange stands in for the missing ranges, said so."""
    scene = Scene(SceneConfig(robot=str(_need(OP3_DIR / "op3.xml"))))
    r = scene.robot
    assert scene.stand_source == "derived"
    assert np.allclose(scene.stand_ctrl, 0.0) and np.allclose(r.joint_positions(scene.data), 0.0)
    assert 0.48 < scene.robot_height < 0.54  # the real OP3 is 0.51 m
    assert set(r.limit_source) == {"ctrlrange"} and np.allclose(r.upper, 3.141592)
    assert np.allclose(r.stall_torque, 5.0)  # the actuators' forcerange
    result = check_trajectory(_standing(scene, 1.0), CheckConfig())
    assert any("ctrlrange" in n for n in result.notes) and any("derived" in n for n in result.notes)
    assert result.metrics["joint_limit_source"]["l_knee"] == "ctrlrange"


def test_g1_force_limits_come_from_its_joints():
    """The G1 declares torque limits on the joints (actuatorfrcrange), none on its actuators."""
    scene = Scene(SceneConfig(robot=str(_need(G1_DIR / "g1.xml"))))
    r = scene.robot
    stall = dict(zip(r.joint_names, r.stall_torque))
    assert (
        stall["left_hip_pitch_joint"] == 88 and stall["left_knee_joint"] == 139 and stall["left_wrist_yaw_joint"] == 5
    )
    assert r.unchecked("torque_saturation") == ()
    assert scene.stand_source == "keyframe" and 1.25 < scene.robot_height < 1.4
    # the joint clamps what the position servo (kp 500) asks for: torque as the joint gets it
    asked = np.zeros(scene.model.nu)
    asked[r.actuator_ids] = 1000.0
    assert np.allclose(r.joint_torques(asked), r.torque_upper) and r.torque_upper[0] == 88


def test_limits_for_unranged_joints_come_from_the_robot_folder(tmp_path):
    """A robot folder around the published OP3 (profile.yaml naming the model, a hardware
    config): the profile's joint_limits, then the hardware config's servo limits, fill the
    unranged joints; the hardware config's servo model gives those servos' speed."""
    model = _need(OP3_DIR / "op3.xml")
    (tmp_path / "profile.yaml").write_text(
        textwrap.dedent(f"""\
        mjcf: {model}
        joint_limits:
          l_knee: [-2.2, 0.0]
          r_knee: [0.0, 2.2]
        """)
    )
    (tmp_path / "hardware.yaml").write_text(
        textwrap.dedent("""\
        robot: my_op3
        servo_defaults: {model: XM430-W350}
        buses:
          - name: body
            port: /dev/ttyUSB0
            baud: 2000000
            protocol: "2.0"
            servos:
              - {id: 19, joint: head_pan, limits: [-1.5, 1.5]}
              - {id: 20, joint: head_tilt, limits: [-0.5, 1.0]}
              - {id: 14, joint: l_knee, limits: [-2.0, 0.0]}
        """)
    )
    scene = Scene(SceneConfig(robot=str(tmp_path)))
    r = scene.robot
    src = dict(zip(r.joint_names, r.limit_source))
    lim = {j: (lo, hi) for j, lo, hi in zip(r.joint_names, r.lower, r.upper)}
    assert src["l_knee"] == "profile" and lim["l_knee"] == (-2.2, 0.0)  # the profile before the hardware config
    assert src["head_tilt"] == "hardware" and lim["head_tilt"] == (-0.5, 1.0)
    assert src["l_el"] == "ctrlrange"
    speed = dict(zip(r.joint_names, r.no_load_speed))
    assert speed["head_pan"] == pytest.approx(46 * 2 * np.pi / 60) and not np.isfinite(speed["l_el"])

    # given limits come first; a command past them fails on joint_limit, naming the joint
    q = np.zeros((31, r.n))
    q[:, r.joint_names.index("head_pan")] = np.linspace(0.0, 0.6, 31)
    traj = RobotTrajectory(
        r.joint_names,
        q,
        np.tile(scene.data.xpos[r.root_body], (31, 1)),
        np.tile([1.0, 0, 0, 0], (31, 1)),
        30.0,
        str(tmp_path),
    )
    result = check_trajectory(traj, CheckConfig(), joint_limits={"head_pan": (-0.4, 0.4)})
    assert result.reason == "joint_limit" and "head_pan" in result.failures[0].detail
    assert "[-0.400, 0.400]" in result.failures[0].detail
    assert result.metrics["joint_limit_source"]["head_pan"] == "given"
    assert "head_pan" not in result.not_checked.get("speed_limit", "")
    assert "l_el" in result.not_checked["speed_limit"]


def test_virtual_robot_moves_a_published_model_with_unranged_joints():
    """Unranged joints read as [0, 0] would pin every goal to 0; the sim transport follows."""
    vr = VirtualRobot(VirtualRobotConfig(robot=str(_need(OP3_DIR / "op3.xml")), clock="lockstep"))
    vr.open()
    try:
        goal = vr.read_state().position
        vr.write_goal(goal)
        vr.set_torque(True)
        j = vr.joint_names.index("head_pan")
        goal[j] = 0.6
        for _ in range(100):
            vr.write_goal(goal)
        assert vr.read_state().position[j] == pytest.approx(0.6, abs=0.05)
    finally:
        vr.close()


# -- small hand-written models --------------------------------------------------------------
def _twin_arms(tmp_path: Path, ctrlrange: bool = False, forcerange: bool = False, speed: bool = False) -> Path:
    """A fixed torso with two hanging arms on x-axis hinges (no range), all geoms unnamed,
    an unnamed floor plane. Swinging the arms inwards makes their capsules collide."""
    ctrl = ' ctrlrange="-1 1"' if ctrlrange else ""
    force = ' forcerange="-2 2"' if forcerange else ""
    custom = '<custom><numeric name="servo_no_load_speed" data="6"/></custom>' if speed else ""
    path = tmp_path / "twin_arms.xml"
    path.write_text(
        textwrap.dedent(f"""\
        <mujoco model="twin arms">
          {custom}
          <worldbody>
            <geom type="plane" size="2 2 0.1"/>
            <body name="torso" pos="0 0 0.5">
              <geom type="box" size="0.03 0.1 0.05"/>
              <body name="left_arm" pos="0 0.07 -0.08">
                <joint name="left_swing" axis="1 0 0"/>
                <geom type="sphere" size="0.01" contype="0" conaffinity="0" mass="0.01"/>
                <geom type="capsule" fromto="0 0 0 0 0 -0.2" size="0.02"/>
              </body>
              <body name="right_arm" pos="0 -0.07 -0.08">
                <joint name="right_swing" axis="1 0 0"/>
                <geom type="capsule" fromto="0 0 0 0 0 -0.2" size="0.02"/>
              </body>
            </body>
          </worldbody>
          <actuator>
            <position joint="left_swing" kp="20"{ctrl}{force}/>
            <position joint="right_swing" kp="20"{ctrl}{force}/>
          </actuator>
        </mujoco>
        """)
    )
    return path


def _swing(path: Path, angle: float, seconds: float = 1.5) -> RobotTrajectory:
    t = np.arange(int(seconds * 30) + 1) / 30.0
    a = angle * np.clip(t / (seconds * 0.6), 0.0, 1.0)
    q = np.stack([-a, a], axis=1)  # left arm swings towards -y, right towards +y
    n = len(t)
    return RobotTrajectory(
        ("left_swing", "right_swing"),
        q,
        np.tile([0.0, 0.0, 0.5], (n, 1)),
        np.tile([1.0, 0, 0, 0], (n, 1)),
        30.0,
        str(path),
    )


def test_unnamed_geoms_are_named_by_their_body_in_a_self_collision(tmp_path):
    path = _twin_arms(tmp_path, ctrlrange=True, forcerange=True, speed=True)
    result = check_trajectory(_swing(path, 0.6), CheckConfig(mode="fixed"))
    assert result.reason == "self_collision", result.failures
    detail = result.failures[0].detail
    # the left arm's capsule is its second geom (after a visual-only sphere)
    assert "geom 0 of right_arm / geom 1 of left_arm" in detail, detail
    assert "( / )" not in detail
    assert result.metrics["self_collision_pairs"] == ["geom 0 of right_arm / geom 1 of left_arm"]
    assert result.not_checked == {}  # every test had its data


def test_a_check_without_data_says_what_it_did_not_check(tmp_path):
    """Unranged joints nobody gives a limit, no force limit, no servo speed: each listed as
    not checked (with the joints and the fix), never read as a [0, 0] range."""
    path = _twin_arms(tmp_path)
    scene = Scene(SceneConfig(robot=str(path)))
    assert scene.model.geom(scene.floor_geom).name == "floor" and len(_world_planes(scene.model)) == 1
    assert not scene.floating and scene.robot.feet == ()
    assert np.all(np.isinf(scene.robot.lower)) and np.all(np.isinf(scene.robot.upper))
    result = check_trajectory(_swing(path, 0.2), CheckConfig(mode="fixed"))
    assert result.passed, result.failures  # 0.2 rad is past [0, 0], but no limit is known
    nc = result.not_checked
    assert set(nc) == {"joint_limit", "speed_limit", "torque_saturation"}
    assert nc["joint_limit"].startswith("limits not checked for joints left_swing, right_swing")
    assert "servo_no_load_speed" in nc["speed_limit"] and "forcerange" in nc["torque_saturation"]
    md = markdown(result)
    assert "**PASS**" in md and "- joint_limit: limits not checked for joints left_swing, right_swing" in md
    # the same model with limits given: judged against them
    limited = check_trajectory(
        _swing(path, 0.2),
        CheckConfig(mode="fixed"),
        joint_limits={"left_swing": (-0.1, 0.1), "right_swing": (-0.1, 0.1)},
    )
    assert limited.reason == "joint_limit" and "joint_limit" not in limited.not_checked


def test_a_floor_that_is_not_level_at_zero_is_refused(tmp_path):
    path = _twin_arms(tmp_path)
    path.write_text(
        path.read_text().replace(
            '<geom type="plane" size="2 2 0.1"/>', '<geom name="ground" type="plane" size="2 2 0.1" pos="0 0 -0.3"/>'
        )
    )
    with pytest.raises(SimError, match=r"floor plane 'ground' is not horizontal at z = 0"):
        Scene(SceneConfig(robot=str(path)))


def test_an_unfinished_hardware_config_is_left_out_with_a_note(tmp_path):
    """A robot folder whose hardware.yaml is still a skeleton: the check runs on the MJCF
    alone and says the config was left out."""
    folder = tmp_path / "arms"
    folder.mkdir()
    _twin_arms(folder, ctrlrange=True, forcerange=True, speed=True)
    (folder / "hardware.yaml").write_text("robot: arms\nbuses: FILL_ME_IN\n")
    scene = Scene(SceneConfig(robot=str(folder)))
    assert len(scene.facts.notes) == 1 and scene.facts.notes[0].startswith("hardware config left out:")
    result = check_trajectory(_swing(folder / "twin_arms.xml", 0.2), CheckConfig(mode="fixed"), robot=str(folder))
    assert result.passed and any("hardware config left out" in n for n in result.notes)
