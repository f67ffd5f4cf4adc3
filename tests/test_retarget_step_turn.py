"""How far a step may turn a foot against the other (retarget.step_turn) and the planner using it.

Real parts: the bundled op3's MJCF and profile, CasADi's kinematics, MuJoCo's own box distance,
the streaming retargeter with balance and steps on a synthetic turning leader.
"""

import mujoco
import numpy as np
import pytest

from retarget.robot import load_robot
from retarget.step_turn import leg_yaw_joints, step_turn_limits
from retarget.streaming import StreamingConfig, StreamingRetargeter

FPS = 30.0


@pytest.fixture(scope="module")
def op3():
    return load_robot("op3")


def _turned(robot, rel):
    """The stand pose with the left foot's heading minus the right's = rel (rad; + toes out),
    each leg's yaw hinge turned by half of it."""
    (jl, sl), (jr, sr) = leg_yaw_joints(robot)
    x = np.asarray(robot.x_stand, float).ravel().copy()
    x[jl] += sl * rel / 2
    x[jr] -= sr * rel / 2
    return x


def _off_feet_rows(robot):
    feet = {f.body for f in robot.feet}
    return [
        k
        for k, (a, b) in enumerate(robot.collision_pairs)
        if robot.capsules[a].body not in feet and robot.capsules[b].body not in feet
    ]


def test_the_leg_yaw_hinges_are_the_hip_yaws_and_turn_the_feet_the_named_way(op3):
    joints = leg_yaw_joints(op3)
    assert [op3.joint_names[j - op3.n_root] for j, _ in joints] == ["l_hip_yaw", "r_hip_yaw"]
    # +0.3 rad is toes out: the left toe turns to +y (counter-clockwise), the right toe to -y
    ev = op3.evaluate(np.stack([op3.x_stand.ravel(), _turned(op3, 0.3)]))["keypoints"]
    names = op3.keypoint_names
    for side, sign in (("left", 1.0), ("right", -1.0)):
        toe = ev[:, names.index(f"{side}_foot"), 0:2] - ev[:, names.index(f"{side}_ankle"), 0:2]
        heading = np.arctan2(toe[:, 1], toe[:, 0])
        assert sign * (heading[1] - heading[0]) == pytest.approx(0.15, abs=0.03)


def test_the_limits_are_where_the_legs_own_capsules_meet(op3):
    """At each limit every capsule pair off the feet is clear; a little further one is not
    (toes out: the hip-servo blocks' faces), or the limit is the cap."""
    out, toe_in = step_turn_limits(op3, 0.6)
    assert 0.3 <= out < 0.6
    assert toe_in == pytest.approx(0.6)
    rows = _off_feet_rows(op3)
    at, past = op3.evaluate(np.stack([_turned(op3, out), _turned(op3, out + 0.03)]))["collision"][:, rows]
    assert at.min() >= 0.0
    assert past.min() < 0.0
    labels = [f"{op3.collision_pairs[k][0]}/{op3.collision_pairs[k][1]}" for k in rows]
    assert "hip" in labels[int(np.argmin(past))]
    # a cap below what the legs allow is the limit on both sides
    assert step_turn_limits(op3, 0.2) == pytest.approx((0.2, 0.2))
    # with room to spare, the limits are closer in and every pair keeps that room at them
    spare = 0.003
    out3, in3 = step_turn_limits(op3, 0.6, spare)
    assert out3 < out and in3 <= toe_in
    radii = np.array([op3.capsules[a].radius + op3.capsules[b].radius for a, b in op3.collision_pairs])[rows]
    r = radii + op3.profile.collision_margin
    for rel in (out3, -in3):
        row = op3.evaluate(_turned(op3, rel)[None])["collision"][0, rows]
        assert (np.sqrt(row + r**2) - r).min() >= spare - 1e-9


def test_the_profiles_hip_block_rows_are_faithful_to_the_mjcf_boxes(op3):
    """MuJoCo's own distance between the hip-servo boxes: clear at the toes-out limit (the rows
    are not optimistic) and at most 15 mm at it (they are not the bounding capsule, which
    stopped the toes 0.19 rad out with the boxes 20 mm apart)."""
    m = op3.kin.model
    d = mujoco.MjData(m)
    gl, gr = (mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, n) for n in ("l_hip_servos", "r_hip_servos"))
    out, _ = step_turn_limits(op3, 0.6)
    d.qpos[:] = op3.kin.qpos_from_x(_turned(op3, out))
    mujoco.mj_kinematics(m, d)
    gap = mujoco.mj_geomDistance(m, d, gl, gr, 0.1, None)
    assert 0.0 < gap < 0.015, gap


def _sole_headings(robot, X):
    """(T, 2) rad: each sole's heading, from its heel corners' middle to its toe corners' middle."""
    sole = robot.evaluate(X)["sole"][..., 0:2].reshape(len(X), 2, 4, 2)
    along = sole[:, :, 0:2].mean(axis=2) - sole[:, :, 2:4].mean(axis=2)
    return np.arctan2(along[..., 1], along[..., 0])


@pytest.mark.parametrize("rate", [2.0, -2.0])
def test_a_fast_turn_never_plants_the_feet_turned_further_apart_than_the_legs_allow(op3, rate):
    """A person turning at 2 rad/s either way: the robot turns by stepping, and with both feet
    down they never stand toed out or in past the limits (the solver could reach a further
    turned landing only by leaning the trunk: a generated partner's robot leaned 30° back and
    fell). The trunk stays within 15° of upright (without the limits: 16-18°)."""
    from bench.stepping_leaders import turning_leader
    from retarget.targets import make_targets

    cfg = StreamingConfig(balance=True, steps=True)
    out, toe_in = step_turn_limits(op3, cfg.max_step_turn, cfg.step_turn_clearance)
    motion = turning_leader(2.0, rate)
    s = StreamingRetargeter(op3, FPS, cfg)
    tg = make_targets(op3, motion)
    s.reset()
    X, planted = [], []
    for t in range(motion.n_frames):
        X.append(s.step(tg.keypoints[t], tg.contacts[t]))
        planted.append(s.planted.copy())
    X, planted = np.array(X), np.array(planted)
    heads = _sole_headings(op3, X)
    rel = (heads[:, 0] - heads[:, 1] + np.pi) % (2 * np.pi) - np.pi  # + toes out
    both = planted.all(axis=1)
    assert rel[both].max() < out + 0.1, (rel[both].max(), out)
    assert rel[both].min() > -toe_in - 0.1, (rel[both].min(), toe_in)
    tilt = np.degrees(np.abs(X[:, 4:6])).max()
    assert tilt < 15.0, tilt
    yaw = np.unwrap(np.arctan2(np.sin(heads).sum(1), np.cos(heads).sum(1)))
    assert np.sign(rate) * (yaw[-1] - yaw[0]) > 1.0  # it did turn, lagging the person


def _toy_with_waist(unnamed_right_hip_yaw: bool):
    """The toy humanoid with a waist yaw hinge above both legs (and optionally an unnamed right
    hip yaw)."""
    from retarget_toy import TOY_PROFILE, TOY_XML

    from retarget.profile import RetargetProfile
    from retarget.robot import robot_from_xml_string

    xml = TOY_XML.replace(
        '<body name="r_hip_yaw_link"',
        '<body name="waist" pos="0 0 0"><joint name="waist_yaw" axis="0 0 1" range="-1 1"/><body name="r_hip_yaw_link"',
        1,
    )
    end = xml.index("</body>\n    </body>\n  </worldbody>")
    xml = (
        xml[:end]
        + "</body>\n</body>\n    </body>\n  </worldbody>"
        + xml[end + len("</body>\n    </body>\n  </worldbody>") :]
    )
    xml = xml.replace("0 1.2 -0.3  0 0 -0.2", "0 1.2 -0.3  0  0 0 -0.2")  # the waist's angle in the stand key
    if unnamed_right_hip_yaw:
        xml = xml.replace('<joint name="r_hip_yaw" ', "<joint ")
    return robot_from_xml_string(xml, RetargetProfile.from_dict(dict(TOY_PROFILE), source="toy.yaml"))


@pytest.mark.parametrize("unnamed", [False, True])
def test_a_waist_yaw_above_both_legs_is_not_a_legs_yaw(unnamed):
    """A waist turns both legs together (it once was taken as each leg's yaw: the two half-turns
    cancelled on one joint and the limits came out as the cap); an unnamed hinge is found too."""
    robot = _toy_with_waist(unnamed)
    assert "waist_yaw" in robot.joint_names
    found = [robot.joint_names[j - robot.n_root] for j, _ in leg_yaw_joints(robot)]
    right = "r_hip_yaw" if not unnamed else next(n for n in robot.joint_names if n.startswith("joint"))
    assert found == ["l_hip_yaw", right]
    out, toe_in = step_turn_limits(robot, 0.6)
    assert 0.0 < out <= 0.6 and 0.0 < toe_in <= 0.6


def test_a_cap_below_the_grid_is_the_limit(op3):
    assert step_turn_limits(op3, 0.005) == (0.005, 0.005)
    assert step_turn_limits(op3, 0.0) == (0.0, 0.0)
