"""Retarget profiles: loading, validation against the MJCF (errors name the field), automatic scales."""

import numpy as np
import pytest
import yaml
from retarget_toy import TOY_PROFILE, toy_robot

from dualflow.motion import REST_POSE, Motion
from firmware_cfg.registry import resolve
from retarget import RetargetError
from retarget.profile import RetargetProfile
from retarget.robot import load_robot
from retarget.targets import KeypointScaler, detect_contacts, make_targets


def _with(path, value):
    """TOY_PROFILE with the nested field ``path`` (a tuple of keys) set to ``value``."""
    import copy

    data = copy.deepcopy(TOY_PROFILE)
    node = data
    for k in path[:-1]:
        node = node[k]
    node[path[-1]] = value
    return data


@pytest.mark.parametrize(
    "path, value, match",
    [
        (("keypoints", "left_knee"), {"body": "no_such_body"}, r"keypoints\.left_knee\.body.*no body 'no_such_body'"),
        (("keypoints", "left_knee"), {"site": "no_such_site"}, r"keypoints\.left_knee\.site.*no site 'no_such_site'"),
        (("keypoints", "left_knee"), {"site": "l_knee", "body": "l_shin"}, r"keypoints\.left_knee: give exactly one"),
        (("feet", "left"), {"body": "nobody", "geom": "l_foot_g"}, r"feet\.left\.body.*no body 'nobody'"),
        (("capsules", "torso"), {"geom": "ghost"}, r"capsules\.torso\.geom.*no geom 'ghost'"),
        (("collision_pairs",), [["torso", "nose"]], r"collision_pairs\[0\].*'nose' is not a capsule"),
        (("joint_limits",), {"r_knee": [-1.0, 2.0]}, r"joint_limits\.r_knee.*wider than the MJCF"),
        (("joint_limits",), {"no_joint": [0.0, 1.0]}, r"joint_limits\.no_joint.*no hinge joint"),
        (("velocity_limits",), {"default": -1}, r"velocity_limits\.default.*> 0"),
        (("posture_weight",), "heavy", r"posture_weight.*number"),
        (("streaming_steps",), "yes", r"streaming_steps.*true or false"),
        (("step_pace",), 0.1, r"step_pace: must be within 0.5-4"),
        (("step_pace",), "slow", r"step_pace: give a number"),
    ],
)
def test_bad_profiles_name_the_field(path, value, match):
    with pytest.raises(RetargetError, match=match) as err:
        toy_robot(**_with(path, value))
    assert "toy.yaml" in str(err.value)


def test_unknown_fields_and_joints_are_rejected():
    with pytest.raises(RetargetError, match="unknown field"):
        RetargetProfile.from_dict(dict(TOY_PROFILE, rotation_offsets={}), "p.yaml")
    with pytest.raises(RetargetError, match=r"keypoints\.left_toe.*not an SMPL-22 joint"):
        RetargetProfile.from_dict(_with(("keypoints", "left_toe"), {"site": "l_toe"}), "p.yaml")


def test_profile_file_errors(tmp_path):
    with pytest.raises(RetargetError, match="not found"):
        RetargetProfile.load(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("robot: [unclosed\n")
    with pytest.raises(RetargetError, match="not valid YAML"):
        RetargetProfile.load(bad)
    good = tmp_path / "good.yaml"
    good.write_text(yaml.safe_dump(TOY_PROFILE))
    assert RetargetProfile.load(good).robot == "toy"


def test_narrower_limits_apply_and_velocity_defaults():
    rb = toy_robot(joint_limits={"r_knee": [0.1, 2.0]}, velocity_limits={"default": 3.0, "l_knee": 2.0})
    i = rb.n_root + rb.joint_names.index("r_knee")
    assert (rb.x_lower[i], rb.x_upper[i]) == (0.1, 2.0)
    assert rb.velocity_limits[rb.joint_names.index("l_knee")] == 2.0
    assert rb.velocity_limits[rb.joint_names.index("r_knee")] == 3.0


def test_sole_corners_come_from_the_foot_box_and_lie_flat_in_the_stand_pose():
    rb = toy_robot()
    sole = rb.evaluate(rb.x_stand[None])["sole"][0]
    assert sole.shape == (8, 3)
    assert np.ptp(sole[:4, 2]) < 1e-3 and np.ptp(sole[4:, 2]) < 1e-3  # flat
    left, right = sole[:4], sole[4:]
    assert left[:, 1].min() > right[:, 1].max()  # left foot at +Y
    assert np.ptp(left[:, 0]) == pytest.approx(0.10, abs=1e-3) and np.ptp(left[:, 1]) == pytest.approx(0.05, abs=1e-3)


def test_scales_follow_rest_bone_lengths_and_the_clips_own_person():
    rb = toy_robot()
    rest = KeypointScaler(rb)
    k = rb.keypoint_names.index("left_knee")
    human_thigh = np.linalg.norm(REST_POSE[4] - REST_POSE[1])
    assert rest.bone_scales[k] == pytest.approx(rb.bone_lengths[k] / human_thigh)
    # a 10 % taller person gets 10 % smaller scales everywhere
    tall = KeypointScaler(rb, (REST_POSE * 1.1)[None])
    assert np.allclose(
        np.delete(tall.bone_scales, rb.root_keypoint) * 1.1, np.delete(rest.bone_scales, rb.root_keypoint)
    )
    assert tall.root_scale * 1.1 == pytest.approx(rest.root_scale)
    # overrides win
    over = toy_robot(scale={"left_knee": 0.5, "root": 0.3})
    sc = KeypointScaler(over)
    assert sc.bone_scales[k] == 0.5 and sc.root_scale == 0.3


def test_rest_pose_maps_onto_the_robot_rest_pose():
    """The human rest pose, scaled, lands on the robot's own zero-pose keypoints (no offsets tuned)."""
    rb = toy_robot()
    m = Motion(np.repeat(REST_POSE[None], 3, axis=0), fps=30.0)
    tg = make_targets(rb, m, contacts=np.zeros((3, 4), bool))
    x0 = np.zeros(rb.nx)
    rest = rb.evaluate(x0[None])["keypoints"][0]
    ground = rb.evaluate(x0[None])["sole"][0][:, 2].min()
    rest[:, 2] -= ground
    legs = [rb.keypoint_names.index(n) for n in ("left_hip", "left_knee", "right_knee", "pelvis")]
    assert np.abs(tg.keypoints[0, legs] - rest[legs]).max() < 0.02


def test_contacts_are_detected_from_foot_height_and_speed():
    T = 40
    pos = np.repeat(REST_POSE[None], T, axis=0).copy()
    pos[15:25, [7, 10], 2] += 0.15  # left foot lifted for 10 frames
    c = detect_contacts(Motion(pos, fps=30.0))
    assert c[:14, 0].all() and not c[16:24, 0].any() and c[:, 2].all()


def test_contacts_are_measured_from_the_clips_own_floor():
    """A capture whose floor is not at z = 0 (or whose skeleton's ankles sit higher or lower
    than SMPL's) has the contacts it would have on z = 0: 6 cm up, every frame read as in the
    air and the robot stood through the clip as through a flight, never stepping (CMU 18_01 on
    a platform: 0 steps; 3 now, as on the floor). A jump stays a jump."""
    T = 60
    pos = np.repeat(REST_POSE[None], T, axis=0).copy()
    pos[15:25, [7, 10], 2] += 0.15  # the left foot lifted
    pos[35:45, [8, 11], 2] += 0.08  # the right foot lifted low: 4 cm on a floor 4 cm down
    on_floor = detect_contacts(Motion(pos, fps=30.0))
    assert not on_floor[36:44, 2:].any()
    for floor in (0.06, -0.04):
        assert np.array_equal(detect_contacts(Motion(pos + [0.0, 0.0, floor], fps=30.0)), on_floor), floor
    jump = pos.copy()
    jump[48:56, :, 2] += 0.3  # the whole body in the air: no foot on the floor
    c = detect_contacts(Motion(jump, fps=30.0))
    assert not c[49:55].any() and c[:14].all()


def test_a_capture_above_the_floor_is_stepped_as_on_it():
    """The CMU clip 18_01 lifted 6 cm: the streamed op3 steps as it does on the floor."""
    from conftest import CMU_DIR, _require

    from dualflow.motion.io import load_motion
    from retarget.schedule import count_steps
    from retarget.streaming import StreamingConfig, StreamingRetargeter

    motion = load_motion(_require(CMU_DIR / "18_01.bvh")).resample(30.0)
    op3 = load_robot("op3")
    steps = []
    for floor in (0.0, 0.06):
        lifted = Motion(motion.positions + [0.0, 0.0, floor], 30.0)
        traj = StreamingRetargeter(op3, 30.0, StreamingConfig(balance=True, steps=True)).run(lifted)
        steps.append(count_steps(np.array(traj.meta["contacts"], dtype=bool)))
    assert steps[0] >= 2 and steps[1] == steps[0], steps


def test_bundled_profiles_load():
    for name in ("op3", "ub14"):
        rb = load_robot(name)
        assert rb.n_keypoints >= 9 and np.all(np.isfinite(rb.velocity_limits))
        assert rb.profile.source == str(resolve(name).profile)
    with pytest.raises(RetargetError, match="unknown robot"):
        load_robot("no_such_robot")


def test_an_mjcf_path_never_picks_up_a_bundled_profile(tmp_path):
    """A user's model called op3.xml outside a robot folder is not the bundled op3: it has no
    profile until one is written (issue: `--robot path/op3.xml` silently used the bundled one)."""
    user = tmp_path / "op3.xml"
    user.write_text(resolve("op3").mjcf.read_text())
    with pytest.raises(RetargetError, match="no retarget profile"):
        load_robot(user)
    # in a robot folder of its own, the folder's profile is used, whatever the folder is called
    folder = tmp_path / "op3"
    folder.mkdir()
    (folder / "op3.xml").write_text(resolve("op3").mjcf.read_text())
    (folder / "profile.yaml").write_text(resolve("op3").profile.read_text())
    rb = load_robot(folder)
    assert rb.profile.source == str(folder / "profile.yaml") and rb.ref == str(folder)
