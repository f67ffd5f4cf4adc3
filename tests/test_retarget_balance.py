"""Balance-aware streaming retargeting (StreamingConfig.balance) and the support-polygon helpers.

The clips are built here from the SMPL rest pose: a person standing with arms down who
sways, waves, leans, or steps in place; they go through StreamingRetargeter.run (scaling,
ground calibration, contacts detected) onto the bundled op3, and the free-standing result is
played in MuJoCo by sim's check.
"""

import math

import numpy as np
import pytest
from scipy.spatial import ConvexHull

from dualflow.motion import REST_POSE, Motion
from dualflow.motion.skeleton import JOINT_NAMES
from retarget import RetargetError
from retarget.robot import load_robot
from retarget.streaming import StreamingConfig, StreamingRetargeter
from retarget.support import (
    closest_point,
    com_margins,
    convex_hull,
    double_support_points,
    halfplanes,
    level_footprint,
    margin,
    shrink_footprint,
    stance_points,
)

FPS = 30.0
J = {n: i for i, n in enumerate(JOINT_NAMES)}
UPPER = [
    J[n]
    for n in (
        "pelvis",
        "left_hip",
        "right_hip",
        "spine1",
        "spine2",
        "spine3",
        "neck",
        "left_collar",
        "right_collar",
        "head",
        "left_shoulder",
        "right_shoulder",
        "left_elbow",
        "right_elbow",
        "left_wrist",
        "right_wrist",
    )
]


def _rot_x(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def person(seconds=4.0, sway=0.0, lean=(0.0, 0.0), wave=0.0, lift=None, seed=0, right_lift=None) -> Motion:
    """A standing person (T, 22, 3), arms down: the upper body ``sway``s sideways (m, 0.6 Hz),
    ``lean``s by (x, y) m (ramped in over the first second), the arms ``wave`` (rad, 0.8 Hz);
    ``lift`` = (t0, t1) s lifts the left foot 8 cm off the ground, weight on the right
    (``right_lift``: the right foot, weight on the left)."""
    rng = np.random.default_rng(seed)
    T = int(seconds * FPS)
    t = np.arange(T) / FPS
    pos = np.repeat(REST_POSE[None].astype(np.float64), T, axis=0)
    for side, sign in (("left", 1.0), ("right", -1.0)):
        sh = J[f"{side}_shoulder"]
        angle = sign * (1.25 + wave * np.sin(2 * np.pi * 0.8 * t + rng.uniform(0, 6)))
        for name in ("elbow", "wrist"):
            k = J[f"{side}_{name}"]
            rel = REST_POSE[k] - REST_POSE[sh]
            pos[:, k] = REST_POSE[sh] + np.einsum("tij,j->ti", np.stack([_rot_x(-a) for a in angle]), rel)
    ramp = np.clip(t, 0.0, 1.0)[:, None]
    shift = np.zeros((T, 3))
    shift[:, 0:2] = ramp * np.asarray(lean)[None]
    shift[:, 1] += sway * np.sin(2 * np.pi * 0.6 * t)
    lifts = [(span, side, sign) for span, side, sign in ((lift, "left", -1.0), (right_lift, "right", 1.0)) if span]
    for span, _, sign in lifts:  # weight over the other foot while one is up
        w = np.clip(np.minimum(t - span[0] + 0.5, span[1] + 0.5 - t) / 0.5, 0.0, 1.0)
        shift[:, 1] += sign * 0.09 * w
    pos[:, UPPER] += shift[:, None, :]
    pos[:, [J["left_knee"], J["right_knee"]]] += 0.5 * shift[:, None, :]
    for span, side, _ in lifts:
        up = ((t >= span[0]) & (t < span[1])).astype(float)
        up = np.convolve(up, np.ones(5) / 5, mode="same")
        for name, h in ((f"{side}_ankle", 0.08), (f"{side}_foot", 0.08), (f"{side}_knee", 0.05)):
            pos[:, J[name], 2] += h * up
    return Motion(pos, fps=FPS, name="standing person")


@pytest.fixture(scope="module")
def op3():
    return load_robot("op3")


def stream(robot, motion, balance=True, **kw):
    s = StreamingRetargeter(robot, FPS, StreamingConfig(balance=balance, **kw))
    planted = []
    traj_x = []
    from retarget.targets import make_targets

    tg = make_targets(robot, motion)
    s.reset()
    for t in range(motion.n_frames):
        traj_x.append(s.step(tg.keypoints[t], tg.contacts[t]))
        planted.append(s.planted.copy() if s.balance else tg.contacts[t])
    return s, np.stack(traj_x), np.array(planted)


def feet_local(robot):
    return [f.corners for f in robot.feet]


# -- the support-polygon helpers --------------------------------------------------
def test_hull_and_halfplanes_match_scipy():
    rng = np.random.default_rng(1)
    for _ in range(20):
        pts = rng.normal(size=(9, 2))
        hull = convex_hull(pts)
        ref = ConvexHull(pts)
        assert len(hull) == len(ref.vertices)
        assert np.isclose(
            abs(np.sum(hull[:, 0] * np.roll(hull[:, 1], -1) - np.roll(hull[:, 0], -1) * hull[:, 1])) / 2, ref.volume
        )
        A, b = halfplanes(hull)
        for q in rng.normal(size=(30, 2)) * 1.5:
            inside = np.all(ref.equations[:, :2] @ q + ref.equations[:, 2] <= 0)
            m = margin(q, A, b)
            assert (m >= 0) == inside
            if inside:  # inside, the margin is the distance to the nearest edge
                assert np.isclose(m, -np.max(ref.equations[:, :2] @ q + ref.equations[:, 2]))
            else:  # outside, the closest point of the polygon is on its boundary
                c = closest_point(q, hull)
                assert abs(margin(c, A, b)) < 1e-9 and np.linalg.norm(c - q) >= -m - 1e-9


def test_level_footprint_keeps_size_centre_and_heading_of_a_tilted_sole(op3):
    local = op3.feet[0].corners
    x = op3.x_stand.copy()
    x[3], x[4], x[5] = 0.4, 0.15, -0.1  # yaw, and a pitched and rolled body: the sole is tilted
    world = op3.evaluate(x[None])["sole"][0, 0:4]
    fp = level_footprint(world, local)
    side = [np.linalg.norm(local[i] - local[(i + 1) % 4]) for i in range(4)]
    assert np.allclose([np.linalg.norm(fp[i] - fp[(i + 1) % 4]) for i in range(4)], side)
    assert np.allclose(fp.mean(axis=0), world[:, :2].mean(axis=0))
    d = fp[0] - fp[1]
    w = world[0, :2] - world[1, :2]
    assert abs(np.arctan2(d[1], d[0]) - np.arctan2(w[1], w[0])) < 1e-9
    small = shrink_footprint(fp, 0.01)
    assert np.allclose([np.linalg.norm(small[i] - small[(i + 1) % 4]) for i in range(4)], np.array(side) - 0.02)


def test_a_sole_narrower_than_twice_the_margin_keeps_an_area():
    """A 6 cm wide sole (the Unitree G1's) shrunk by a 3 cm stance margin used to collapse to a
    line, and building the single-support region then raised 'a polygon needs 3 vertices'."""
    narrow = np.array([[0.1, 0.03], [-0.1, 0.03], [-0.1, -0.03], [0.1, -0.03]])
    small = shrink_footprint(narrow, 0.03)
    assert np.ptp(small[:, 1]) == pytest.approx(0.2 * 0.06) and np.ptp(small[:, 0]) == pytest.approx(0.14)
    other = narrow + [0.0, 0.2]
    A, b = halfplanes(convex_hull(stance_points(narrow, other, 0.03)))
    assert margin(narrow.mean(axis=0) + [0.0, 0.003], A, b) > 0  # the inner half keeps room for the CoM


def test_double_support_region_lies_between_the_feet(op3):
    sole = op3.evaluate(op3.x_stand[None])["sole"][0]
    prints = [level_footprint(sole[4 * f : 4 * f + 4], op3.feet[f].corners) for f in range(2)]
    pts = double_support_points(prints, 0.02, 0.01)
    centres = [p.mean(axis=0) for p in prints]
    # laterally inside the feet's centres by the inset; lengthwise inside toe and heel by the margin
    assert np.all(pts[:, 1] <= centres[0][1] - 0.01 + 1e-12) and np.all(pts[:, 1] >= centres[1][1] + 0.01 - 1e-12)
    assert pts[:, 0].max() <= sole[:, 0].max() - 0.02 + 1e-12 and pts[:, 0].min() >= sole[:, 0].min() + 0.02 - 1e-12


# -- balance in the streaming retargeter --------------------------------------------
@pytest.mark.slow
def test_the_balance_rows_measure_the_zmp_and_capture_point_of_the_next_frame(op3):
    """The rows' affine maps of the next frame's CoM c are the ZMP c - (h/g) c'' and the capture
    point c + c'/omega, with c'' and c' from c and the two frames already emitted (a sign error
    in the ZMP once pushed c + (h/g) c'' into the support region instead)."""
    s, X, _ = stream(op3, person(seconds=1.0, sway=0.05))
    pl = s.planner
    c1, c2 = np.asarray(pl._c1), np.asarray(pl._c2)
    assert np.linalg.norm(c1 - c2) > 1e-5  # the CoM is moving: the acceleration terms count
    c = c1 + np.array([0.003, -0.002])
    pl.set_points(False)  # the rows for the frame after the last one emitted
    points = np.asarray(s._pbuf[s._p_points]).reshape(3, 3, order="F")  # columns com, dcm, zmp
    mapped = [points[0, i] * c + points[1:3, i] for i in range(3)]
    h_over_g = pl._zmp_k / FPS**2
    acc = (c - 2 * c1 + c2) * FPS**2
    vel = (c - c1) * FPS
    np.testing.assert_allclose(mapped[0], c)
    np.testing.assert_allclose(mapped[1], c + vel * pl._dcm_k / FPS, rtol=1e-9)
    np.testing.assert_allclose(mapped[2], c - h_over_g * acc, rtol=1e-9, atol=1e-12)


def test_near_standing_person_keeps_op3_on_its_feet_in_physics(op3):
    """Arms waving, the body swaying: streamed with balance, the free-standing op3 passes sim's check."""
    from sim.check import CheckConfig, check_trajectory

    motion = person(seconds=4.0, sway=0.05, wave=0.5)
    s = StreamingRetargeter(op3, FPS, StreamingConfig(balance=True))
    traj = s.run(motion)
    result = check_trajectory(traj, CheckConfig(mode="free"))
    reasons = [f.reason for f in result.failures]
    assert "fall" not in reasons and "balance" not in reasons, result.failures
    assert result.passed, result.failures
    # it really played the motion: the arms moved by tens of degrees
    arm = [op3.joint_names.index(n) for n in ("l_sho_roll", "r_sho_roll", "l_sho_pitch", "r_sho_pitch")]
    assert np.ptp(traj.joint_pos[:, arm], axis=0).max() > 0.3


def test_leaning_person_keeps_the_com_inside_the_support_polygon(op3):
    """A lean far past the toes: without balance the CoM leaves the feet; with it, it stays
    inside the planted footprints' hull by about the margin, feet flat and put."""
    motion = person(seconds=2.5, lean=(0.45, 0.15))
    cfg = StreamingConfig(balance=True)
    _, X_off, on_off = stream(op3, motion, balance=False)
    ev = op3.evaluate(X_off)
    off = com_margins(ev["com"][:, :2], ev["sole"], feet_local(op3), np.ones_like(on_off, bool))
    assert np.nanmin(off) < -0.01  # the clip does lean past the feet

    s, X, planted = stream(op3, motion)
    assert planted.all()  # a lean is no step: both feet stay down
    ev = op3.evaluate(X)
    m = com_margins(ev["com"][:, :2], ev["sole"], feet_local(op3), planted)
    assert np.nanmin(m) > 0.5 * cfg.balance_margin, np.nanmin(m)
    sole = ev["sole"]
    assert np.abs(sole[..., 2]).max() < 1e-3  # soles flat on the ground
    assert np.abs(sole[:, :, 0:2] - sole[:1, :, 0:2]).max() < 2e-3  # and where they were put


def _cart_table_zmp(robot, X):
    """The kinematic ZMP c − (h/g) c̈ (T − 2, 2) of the robot's CoM, c̈ by central differences."""
    ev = robot.evaluate(X)
    com = ev["com"]
    h = float(robot.evaluate(robot.x_stand[None])["com"][0, 2])
    acc = (com[2:, :2] - 2 * com[1:-1, :2] + com[:-2, :2]) * FPS**2
    return com[1:-1, :2] - h / 9.81 * acc


def test_a_step_shifts_the_weight_lifts_the_foot_clear_and_lands_flat(op3):
    """With steps on, the robot decides to step when the person lifts a foot; the ZMP plan moves
    the weight over the stance foot and the foot lifts step_shift later, with the kinematic ZMP
    inside the stance foot's footprint for the whole swing (a lift with the CoM between the
    feet stays loaded on soft servos and drags); the sole rises to swing_clearance, the swing
    lasts min_swing to max_swing and the foot comes back down flat."""
    cfg = StreamingConfig(balance=True, steps=True)
    motion = person(seconds=4.0, lift=(1.2, 1.55))
    s, X, planted = stream(op3, motion, steps=True)
    up = ~planted[:, 0]
    assert planted[:, 1].all() and up.any()
    first = int(np.argmax(up))
    assert abs(first - round((1.2 + cfg.step_shift) * FPS)) <= 3, first  # after the weight shift, not at once
    n_up = int(up.sum())
    assert round(cfg.min_swing * FPS) <= n_up <= round(cfg.max_swing * FPS) + 1, n_up
    ev = op3.evaluate(X)
    assert ev["sole"][up, 0:4, 2].min(axis=1).max() > 0.8 * cfg.swing_clearance  # cleared the floor
    zmp = np.full((len(X), 2), np.nan)
    zmp[1:-1] = _cart_table_zmp(op3, X)
    right_only = np.zeros((len(X), 2), bool)
    right_only[:, 1] = True
    m = com_margins(zmp, ev["sole"], feet_local(op3), right_only)
    # the ZMP over the stance foot all through the swing (the last frame's central difference
    # reaches into the touch-down, where the landing foot takes its share)
    assert m[up][:-1].min() > 0.0, m[up]
    assert np.abs(ev["sole"][-1, :, 2]).max() < 1e-3  # and it came back down flat
    # a person standing on one leg for long: the robot steps in place, never longer than max_swing
    s, X, planted = stream(op3, person(seconds=4.0, lift=(1.0, 3.0)), steps=True)
    runs = np.diff(np.flatnonzero(np.diff(np.r_[1, planted[:, 0].astype(int), 1])))[::2]
    assert len(runs) >= 2 and runs.max() <= round(cfg.max_swing * FPS) + 1, runs
    downs = np.diff(np.flatnonzero(np.diff(np.r_[0, planted[:, 0].astype(int), 0])))[1::2]
    assert downs[:-1].min() >= round(cfg.min_double * FPS), downs  # double support between the steps


@pytest.mark.slow
def test_with_steps_op3_really_steps_in_place_with_the_person_in_physics(op3):
    """The person steps in place, left then right: the streamed op3 takes the steps in MuJoCo (its
    feet leave the floor: sim's stances), and stays up."""
    from sim.check import CheckConfig, check_trajectory, lift_offs

    motion = person(seconds=4.5, lift=(1.0, 1.35), right_lift=(2.2, 2.55))
    s = StreamingRetargeter(op3, FPS, StreamingConfig(balance=True, steps=True))
    traj = s.run(motion)
    result = check_trajectory(traj, CheckConfig(mode="free"))
    assert result.passed, result.failures
    assert lift_offs(result.metrics) >= 2, result.metrics["stances"]


def _sole_headings(robot, X):
    """(T, 2) rad: each sole's heading, heel to toe (the sole's long edge, towards the toe keypoint)."""
    ev = robot.evaluate(X)
    names = robot.keypoint_names
    out = np.zeros((len(X), 2))
    for s, side in enumerate(("left", "right")):
        corners = ev["sole"][:, 4 * s : 4 * s + 4, 0:2]
        d = corners - corners.mean(axis=1, keepdims=True)
        toe = (
            ev["keypoints"][:, names.index(f"{side}_foot"), 0:2] - ev["keypoints"][:, names.index(f"{side}_ankle"), 0:2]
        )
        for t in range(len(X)):
            axis = np.linalg.eigh(d[t].T @ d[t])[1][:, 1]
            axis = -axis if axis @ toe[t] < 0 else axis
            out[t, s] = np.arctan2(axis[1], axis[0])
    return out


def test_a_fast_turn_keeps_each_foot_heading_and_the_feet_within_max_step_turn(op3):
    """Two turns at 2 rad/s: the robot turns by stepping, its record of each planted foot's
    heading stays that foot's (it once flipped by π after a fast turn, and the next step turned
    the other foot 2 rad the wrong way), and the feet never stand turned further apart than
    max_step_turn."""
    from bench.stepping_leaders import turning_leader
    from retarget.targets import make_targets

    cfg = StreamingConfig(balance=True, steps=True)
    motion = turning_leader(2.0, 2.0)
    s = StreamingRetargeter(op3, FPS, cfg)
    tg = make_targets(op3, motion)
    s.reset()
    X, refs, planted = [], [], []
    for t in range(motion.n_frames):
        X.append(s.step(tg.keypoints[t], tg.contacts[t]))
        refs.append(list(s.planner._head_ref))
        planted.append(s.planted.copy())
    X, refs, planted = np.array(X), np.array(refs), np.array(planted)
    actual = _sole_headings(op3, X)
    wrap = lambda a: (a + np.pi) % (2 * np.pi) - np.pi  # noqa: E731
    for side in range(2):
        off = np.abs(wrap(refs[planted[:, side], side] - actual[planted[:, side], side]))
        assert off.max() < 0.2, off.max()
    both = planted.all(axis=1)
    apart = np.abs(wrap(actual[both, 0] - actual[both, 1]))
    assert apart.max() < cfg.max_step_turn + 0.15, apart.max()
    # it did turn, by stepping (about 1 rad/s at most: it lags the person's 2 rad/s, and past a
    # lag of π it turns the shorter way towards the person's heading)
    assert np.unwrap(actual[:, 0])[-1] - actual[0, 0] > 1.0


def _hip_yaw(robot, keypoints):
    """(T,) rad: the facing direction of the hips (left hip to right hip, turned a quarter)."""
    names = robot.keypoint_names
    across = keypoints[:, names.index("left_hip"), 0:2] - keypoints[:, names.index("right_hip"), 0:2]
    return np.arctan2(-across[:, 0], across[:, 1])


def test_the_body_turns_ahead_of_the_feet_within_body_twist(op3):
    """A person turning at 0.9 rad/s: the robot's feet turn by stepping and lag, and its body
    above the knees turns towards the person's heading ahead of them (body_twist), never further
    from the planted feet than body_twist allows. Without the twist the whole body lagged with
    the feet (about 45 degrees on average on this clip)."""
    from bench.stepping_leaders import turning_leader
    from retarget.targets import make_targets

    motion = turning_leader(2.0, -0.9)
    tg = make_targets(op3, motion)
    wrap = lambda a: (a + np.pi) % (2 * np.pi) - np.pi  # noqa: E731
    lag = {}
    for twist in (0.0, 0.8):
        _, X, planted = stream(op3, motion, steps=True, body_twist=twist)
        robot_yaw = _hip_yaw(op3, op3.evaluate(X)["keypoints"])
        lag[twist] = np.abs(wrap(robot_yaw - _hip_yaw(op3, tg.keypoints)))
        feet = _sole_headings(op3, X)
        both = planted.all(axis=1)
        mean_feet = np.arctan2(np.sin(feet).sum(axis=1), np.cos(feet).sum(axis=1))
        twisted = np.abs(wrap(robot_yaw[both] - mean_feet[both]))
        assert twisted.max() < twist + 0.35, (twist, twisted.max())
    # (0.60 against 0.78 rad: the twist is soft and the feet's lag changes with every step)
    assert lag[0.8].mean() < 0.85 * lag[0.0].mean(), (lag[0.8].mean(), lag[0.0].mean())


def test_the_body_twist_does_not_flip_where_the_lag_wraps_around(op3):
    """A lag just under +π and just over −π is almost the same turn: the body's targets must be
    almost the same too (the twist once flipped from one side to the other there, 1.6 rad in one
    frame, and drove the hip yaw joints at their speed limit)."""
    from retarget.targets import make_targets

    s = StreamingRetargeter(op3, FPS, StreamingConfig(balance=True, steps=True, body_twist=0.8))
    tg = make_targets(op3, person(seconds=1.0))
    s.reset()
    for t in range(5):
        s.step(tg.keypoints[t], tg.contacts[t])
    out = {}
    for psi in (np.pi - 0.01, -np.pi + 0.01):
        s.planner.psi = psi
        out[psi] = s.planner.anchor(tg.keypoints[5].copy(), (False, False), False)  # no foot to re-anchor on
    a, b = out.values()
    assert np.abs(a - b).max() < 0.01, np.abs(a - b).max()


def test_a_person_standing_with_a_foot_turned_out_does_not_make_the_robot_march(op3):
    """The person stands still, the left toe turned 1 rad out: more than a step may turn the
    robot's foot from the other (max_step_turn). The robot takes at most one step towards it
    and then stands (it used to re-step every min_stance, for ever)."""
    motion = person(seconds=4.0)
    pos = motion.positions.copy()
    ankle, toe = J["left_ankle"], J["left_foot"]
    c, sn = np.cos(1.0), np.sin(1.0)
    rel = pos[:, toe] - pos[:, ankle]
    pos[:, toe, 0] = pos[:, ankle, 0] + c * rel[:, 0] - sn * rel[:, 1]
    pos[:, toe, 1] = pos[:, ankle, 1] + sn * rel[:, 0] + c * rel[:, 1]
    contacts = np.ones((motion.n_frames, 2), bool)
    s = StreamingRetargeter(op3, FPS, StreamingConfig(balance=True, steps=True))
    from retarget.targets import make_targets

    tg = make_targets(op3, Motion(pos, fps=FPS, name="toe out"), contacts)
    s.reset()
    planted = []
    for t in range(motion.n_frames):
        s.step(tg.keypoints[t], tg.contacts[t])
        planted.append(s.planted.copy())
    planted = np.array(planted)
    lifts = int(np.sum(planted[:-1] & ~planted[1:]))
    assert lifts <= 1, lifts


def test_a_step_longer_than_the_robot_can_take_lands_at_its_stride_limit(op3):
    """A person's left foot put down half a metre ahead: the robot's left foot lands at most
    stride_limit x its leg length from where it stood (without the limit it goes further)."""

    def landing(**kw):
        motion = person(seconds=3.0, lift=(1.0, 1.5))
        pos = motion.positions.copy()
        t = np.arange(motion.n_frames) / FPS
        ahead = np.clip((t - 1.0) / 0.4, 0.0, 1.0)[:, None] * np.array([0.5, 0.0, 0.0])
        for name in ("left_ankle", "left_foot"):
            pos[:, J[name]] += ahead
        s, X, planted = stream(op3, Motion(pos, fps=FPS, name="long step"), steps=True, **kw)
        assert (~planted[:, 0]).any() and planted[-1].all()
        sole = op3.evaluate(X)["sole"]
        return float(np.linalg.norm(sole[-1, 0:4, 0:2].mean(axis=0) - sole[0, 0:4, 0:2].mean(axis=0)))

    cfg = StreamingConfig(balance=True, steps=True)
    stand = op3.evaluate(op3.x_stand[None])["keypoints"][0]
    names = op3.keypoint_names
    leg = stand[names.index("left_hip"), 2] - stand[names.index("left_ankle"), 2]
    limited, free = landing(), landing(stride_limit=10.0)
    assert limited <= cfg.stride_limit * leg + 0.01, (limited, cfg.stride_limit * leg)
    assert free > limited + 0.01, (free, limited)


@pytest.mark.slow
def test_without_steps_a_person_stepping_in_place_leaves_op3_standing_in_physics(op3):
    """With steps off both feet stay down when the person steps; the free-standing op3 passes sim's check."""
    from sim.check import CheckConfig, check_trajectory

    s = StreamingRetargeter(op3, FPS, StreamingConfig(balance=True, steps=False))
    traj = s.run(person(seconds=3.5, lift=(1.2, 2.2)))
    assert s.planted.all()
    result = check_trajectory(traj, CheckConfig(mode="free"))
    assert result.passed, result.failures


def test_fixed_base_robots_ignore_balance():
    motion = person(seconds=1.0, wave=0.5)
    for name, fixed in (("ub14", False), ("op3", True)):
        rb = load_robot(name, fixed_base=fixed)
        runs = [StreamingRetargeter(rb, FPS, StreamingConfig(balance=b, compile=False)) for b in (False, True)]
        assert not runs[1].balance
        a, b = (r.run(motion).joint_pos for r in runs)
        assert np.array_equal(a, b)


def test_balance_needs_ankle_keypoints():
    import yaml

    from firmware_cfg.registry import resolve
    from retarget.kinematics import RobotKinematics
    from retarget.profile import RetargetProfile
    from retarget.robot import RetargetRobot

    data = yaml.safe_load(resolve("op3").profile.read_text())
    del data["keypoints"]["left_ankle"]
    rb = RetargetRobot(RobotKinematics.from_xml(resolve("op3").mjcf), RetargetProfile.from_dict(data, "op3.yaml"))
    StreamingRetargeter(rb, FPS, StreamingConfig(balance=False))  # fine without balance
    with pytest.raises(RetargetError, match="left_ankle"):
        StreamingRetargeter(rb, FPS, StreamingConfig(balance=True))


def test_bridge_retarget_stage_balances_free_standing_robots_only(op3):
    from ros_free_bridge.partner.retarget_stage import RetargetStage

    assert RetargetStage(op3, FPS).streamer.balance
    assert not RetargetStage(load_robot("ub14"), FPS).streamer.balance
    # a live stream with no contact labels still starts with both feet planted
    stage = RetargetStage(op3, FPS)
    motion = person(seconds=0.5, sway=0.03)
    for t in range(motion.n_frames):
        stage.step(motion.positions[t], None)
    assert stage.streamer.planted.all()


def test_a_person_hopping_away_is_not_chased_by_leaning(op3):
    """The whole person leaves the floor for 0.5 s and lands 0.8 m further on (a generated
    partner's hop): its travel in the air is not followed, so the robot, feet down, does not
    lean after targets out of reach (it pitched 10° here, and 43° and fell on the demo's
    partner standing on one foot); the hop is reported as a flight."""
    T = 120
    t = np.arange(T) / FPS
    s = np.clip((t - 1.0) / 0.5, 0.0, 1.0)
    pos = np.repeat(REST_POSE[None], T, axis=0).copy()
    pos[:, :, 0] += 0.8 * (s * s * (3 - 2 * s))[:, None]
    pos[:, :, 2] += (np.where((t > 1.0) & (t < 1.5), np.sin(np.pi * s), 0.0) * 0.12)[:, None]
    traj = StreamingRetargeter(op3, FPS, StreamingConfig(balance=True)).run(Motion(pos, FPS, name="hop"))
    pitch = np.degrees(np.abs(2 * np.arctan2(traj.root_quat[:, 2], traj.root_quat[:, 0])))
    assert pitch.max() < 6.0, pitch.max()
    assert any(c["what"] == "flight" for c in traj.meta["changes"])


def test_a_quick_side_stepper_is_not_chased_by_pitching(op3):
    """Side-stepping 0.18 m at 130 bpm, the person puts a foot down while the robot's same foot
    is still in the air and lifts the other: no foot is down and planted for a few frames each
    step. The person's travel then is not followed (as in the air), so the robot, which has
    nothing to lean forward for, stays upright (it pitched 7.2 deg after the running targets)."""
    from bench.stepping_leaders import sidestep_leader
    from retarget.targets import make_targets

    motion = sidestep_leader(6.0, 0.18, bpm=130.0)
    st = StreamingRetargeter(op3, FPS, StreamingConfig(balance=True))
    tg = make_targets(op3, motion)
    unshared, xs = 0, []
    for t in range(motion.n_frames):
        down = np.asarray(tg.contacts[t], bool)
        unshared += int(t > 0 and down.any() and not (down & st.planted).any())
        xs.append(st.step(tg.keypoints[t], tg.contacts[t]))
    assert unshared >= 5  # the case this is about happens
    _, quat = op3.kin.root_pose(np.array(xs))
    pitch = np.degrees(np.abs(2 * np.arctan2(quat[:, 2], quat[:, 0])))
    assert pitch.max() < 4.0, pitch.max()


def test_step_timing_that_cannot_work_is_one_error_naming_the_field(op3):
    for kw, field in (
        ({"swing_speed": 0.0}, "swing_speed"),
        ({"min_swing": 0.03}, "min_swing"),
        ({"max_swing": 0.1}, "max_swing"),
        ({"step_preview": 0.0}, "step_preview"),
        ({"body_twist": float("nan")}, "body_twist"),
        ({"body_twist": -0.5}, "body_twist"),
        ({"pace_floor": 0.0}, "pace_floor"),
        ({"pace_floor": 1.5}, "pace_floor"),
        ({"pace_floor": float("nan")}, "pace_floor"),
    ):
        with pytest.raises(RetargetError, match=field):
            StreamingRetargeter(op3, FPS, StreamingConfig(balance=True, **kw))


def test_steps_follow_the_robot_profile_unless_the_config_says():
    """StreamingConfig.steps None takes the profile's streaming_steps (robot init writes false
    for a robot the step timing was not measured on); True or False overrides it."""
    import dataclasses

    from retarget.robot import RetargetRobot

    op3 = load_robot("op3")
    assert op3.profile.streaming_steps  # the bundled op3 steps (bench/stepping.py)
    planted = RetargetRobot(op3.kin, dataclasses.replace(op3.profile, streaming_steps=False))
    motion = person(seconds=3.0, lift=(1.0, 1.4))
    for robot, cfg, lifts in (
        (op3, StreamingConfig(balance=True), True),
        (planted, StreamingConfig(balance=True), False),
        (planted, StreamingConfig(balance=True, steps=True), True),
    ):
        s, X, held = stream(robot, motion, steps=cfg.steps)
        assert s.config.steps is lifts and bool((~held).any()) is lifts


def test_the_profiles_step_pace_lengthens_the_steps_unless_the_config_says():
    """StreamingConfig.step_pace None takes the profile's step_pace (robot init measures it):
    at 2 the phases are twice as long and the swing half as fast, so a foot the person lifts
    for 0.4 s lifts later on the robot and lands later; a given pace overrides the profile."""
    import dataclasses

    from retarget.robot import RetargetRobot
    from retarget.streaming import paced

    op3 = load_robot("op3")
    slow = RetargetRobot(op3.kin, dataclasses.replace(op3.profile, step_pace=2.0))
    base = StreamingConfig()
    motion = person(seconds=3.0, lift=(1.0, 1.4))
    runs = {}
    for name, robot, pace in (("op3", op3, None), ("slow", slow, None), ("slow at 1", slow, 1.0)):
        s, X, held = stream(robot, motion, steps=True, step_pace=pace)
        up = np.flatnonzero(~held[:, 0])
        assert len(up), name  # the robot steps with the person's lifted foot
        runs[name] = (s.config, int(up[0]), int(up[-1]))
    cfg = runs["slow"][0]
    assert cfg.step_pace == 2.0 and cfg.min_swing == pytest.approx(2 * base.min_swing)
    assert cfg.step_shift == pytest.approx(2 * base.step_shift)
    assert cfg.swing_speed == pytest.approx(base.swing_speed / 2)
    assert runs["slow at 1"][0].min_swing == pytest.approx(base.min_swing)
    assert runs["slow at 1"][1:] == runs["op3"][1:]
    assert runs["slow"][1] > runs["op3"][1]  # the weight shift before the lift takes longer
    assert runs["slow"][2] > runs["op3"][2]  # ... and it lands later
    with pytest.raises(RetargetError, match="step_pace"):
        paced(base, 0.0)


def test_a_brief_jitter_of_a_still_person_does_not_set_the_robots_com_swinging(op3):
    """The whole person shifts 1 cm sideways for 0.1 s and stands still again. The smoothing
    row holds the CoM to a prediction of its own motion; when that prediction kept the
    velocity, the jitter set the CoM swinging like an undamped mass on a weak spring (tracking
    is the only pull back): 11.8 mm out 1.3 s later. A generated partner standing still for
    0.5 s drifted 5.4 cm to the edge of its feet that way and fell in physics. With the
    velocity decaying (com_velocity_decay) the CoM moves about as far as the person did."""
    from retarget.targets import make_targets

    motion = person(seconds=3.0)
    tg = make_targets(op3, motion)
    K = tg.keypoints.copy()
    K[5:8, :, 1] += 0.01
    swing = {}
    for tau in (math.inf, StreamingConfig.com_velocity_decay):
        s = StreamingRetargeter(op3, FPS, StreamingConfig(balance=True, steps=True, com_velocity_decay=tau))
        s.reset()
        X = [s.step(K[t], tg.contacts[t]) for t in range(len(K))]
        com = op3.evaluate(np.array(X))["com"][:, 0:2]
        swing[tau] = np.linalg.norm(com - com[0], axis=1).max()
    assert swing[StreamingConfig.com_velocity_decay] < 0.005, swing
    assert swing[math.inf] > 0.01, swing  # the mechanism, as it was
