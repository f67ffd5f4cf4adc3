"""The lead-in of a clip that starts mid-motion (retarget.lead_in) and how the offline
retargeter applies and reports it, on the bundled op3.

The clips are SYNTHETIC, made here from REST_POSE: a person caught mid-step (the right foot
up and behind, the body walking forward) and a person standing still."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dualflow.motion import REST_POSE, Motion
from retarget.lead_in import LeadInConfig, lead_in, lead_in_of, needs_lead_in, standing_pose
from retarget.offline import OfflineConfig, OfflineRetargeter
from retarget.report import configurations, evaluate
from retarget.robot import load_robot
from retarget.schedule import StepConfig, foot_poses
from retarget.targets import make_targets

FPS = 30.0
L_ANK, R_ANK, L_TOE, R_TOE = 7, 8, 10, 11


def standing_clip(seconds: float = 1.0) -> Motion:
    T = int(seconds * FPS)
    c = np.ones((T, 4), dtype=bool)
    return Motion(np.repeat(REST_POSE[None], T, axis=0), fps=FPS, contacts=c, name="standing")


def mid_step_clip(seconds: float = 1.2, speed: float = 0.25) -> Motion:
    """Walking forward (+x) at ``speed`` m/s; the right foot starts 0.12 m behind and 0.06 m up,
    swings to 0.12 m ahead and lands at 0.4 s, then stands; the left foot stays down."""
    T = int(seconds * FPS)
    t = np.arange(T) / FPS
    p = np.repeat(REST_POSE[None], T, axis=0).copy()
    p[:, :, 0] += speed * t[:, None]
    for j in (L_ANK, L_TOE, 4):  # the left leg's foot stays where it stood in the first frame
        p[:, j, 0] = REST_POSE[j, 0]
    land = int(0.4 * FPS)
    s = np.clip(t / 0.4, 0.0, 1.0)
    right = REST_POSE[R_ANK, 0] + np.where(t < 0.4, -0.12 + 0.24 * s, 0.12)
    for j in (R_ANK, R_TOE, 5):
        p[:, j, 0] = REST_POSE[j, 0] + (right - REST_POSE[R_ANK, 0])
        p[:, j, 2] += np.where(t < 0.4, 0.06 * np.sin(math.pi * (0.5 + 0.5 * s)), 0.0)
    c = np.ones((T, 4), dtype=bool)
    c[:land, 2:4] = False
    return Motion(p, fps=FPS, contacts=c, name="mid_step")


def stance(robot, keypoints: np.ndarray) -> np.ndarray:
    """The feet relative to each other in the first frame of ``keypoints`` (T, K, 3): the
    left ankle from the right in the left foot's heading frame (m) and their heading difference (rad)."""
    ank, head = foot_poses(robot, keypoints)
    h = head[0, 0]
    c, s = math.cos(-h), math.sin(-h)
    d = np.array([[c, -s], [s, c]]) @ (ank[0, 0] - ank[0, 1])
    return np.array([d[0], d[1], head[0, 0] - head[0, 1]])


@pytest.fixture(scope="module")
def op3():
    return load_robot("op3")


# -- the person's lead-in -------------------------------------------------------------
def test_the_lead_in_and_the_swing_clearance_are_on_by_default():
    assert OfflineConfig().lead_in == LeadInConfig() and StepConfig().swing_clearance == 0.02


def test_a_standing_clip_gets_no_lead_in():
    m = standing_clip()
    assert needs_lead_in(m) == ""
    out, info = lead_in(m)
    assert info is None and out is m


def test_a_mid_step_clip_starts_standing_at_rest_on_both_feet():
    m = mid_step_clip()
    why = needs_lead_in(m)
    assert "right foot is in the air" in why and "pelvis moves" in why
    ext, info = lead_in(m)
    n = info.frames
    assert n > 0 and info.held == ("right",) and info.ease_s == 0.0
    p, c = ext.positions, ext.contacts
    # it starts at rest: the hold frames are identical, both feet down
    hold = int(round(LeadInConfig().hold_s * FPS))
    assert np.abs(np.diff(p[:hold], axis=0)).max() < 1e-12
    assert c[:hold].all()
    # ... in a standing stance: feet side by side (no stagger along the heading), turned out
    # symmetrically about the heading (+x here, REST_POSE's), on the floor
    first = p[0]
    assert abs(first[L_ANK, 0] - first[R_ANK, 0]) < 1e-6
    yaw = [math.atan2(*(first[t, 1::-1] - first[a, 1::-1])) for a, t in ((L_ANK, L_TOE), (R_ANK, R_TOE))]
    assert abs(yaw[0] + yaw[1]) < 1e-6 and abs(yaw[0]) < 0.15
    assert abs(first[L_ANK, 2] - first[R_ANK, 2]) < 1e-6
    # the lead-in ends at rest on both feet in the first frame: the left foot where it is there,
    # the right (in the air there) on the floor below it, the body the clip's
    assert c[n - 1].all() and c[n].all()
    np.testing.assert_allclose(p[n, [L_ANK, L_TOE]], m.positions[0, [L_ANK, L_TOE]], atol=1e-9)
    np.testing.assert_allclose(p[n, [R_ANK, R_TOE], 0:2], m.positions[0, [R_ANK, R_TOE], 0:2], atol=1e-6)
    assert abs(p[n, R_ANK, 2] - p[n, L_ANK, 2]) < 1e-6  # on the floor, as the left
    np.testing.assert_allclose(p[n, 0], m.positions[0, 0], atol=1e-9)
    v = np.linalg.norm(np.diff(p, axis=0), axis=-1).max(axis=1) * FPS  # (T'-1,) fastest joint, m/s
    assert v[: n - 1].max() < 1.5 and v[n - 2] < 0.05  # never a jump; at rest into the first frame
    # a foot is up in the lead-in only while it steps: here the right, to the floor below its place
    assert info.steps == ("right",)
    up = ~c[:n, [0, 2]]
    assert not (up[:, 0] & up[:, 1]).any()


def test_a_held_foot_swings_to_where_the_person_lands_it_with_the_weight_over_the_other():
    m = mid_step_clip()
    ext, info = lead_in(m)
    n, p, c = info.frames, ext.positions, ext.contacts
    land_person = int(np.flatnonzero(m.contacts[:, 2])[0])  # the person's right foot lands (0.4 s)
    right = c[n:, 2]
    lift = int(np.flatnonzero(~right)[0])
    land = lift + int(np.flatnonzero(right[lift:])[0])
    k_swing = int(round(LeadInConfig().swing_s * FPS))
    assert right[:lift].all() and 0 < lift and land >= land_person
    assert land - lift == k_swing or land == land_person
    assert info.swing_from_s[0] == pytest.approx(lift / FPS, abs=1e-6)
    # on the floor until the lift, then at the person's landing place when it lands
    np.testing.assert_allclose(p[n : n + lift, R_ANK], np.repeat(p[n : n + 1, R_ANK], lift, axis=0), atol=1e-9)
    np.testing.assert_allclose(p[n + land, R_ANK], m.positions[land, R_ANK], atol=1e-9)
    # the left foot (stance) stays down through the swing, and the body is over it: the pelvis
    # nearer the left ankle than the person's
    assert c[n + lift : n + land, 0].all()
    gap = lambda f: np.linalg.norm(f[0, :2] - f[L_ANK, :2])  # noqa: E731
    mid = (lift + land) // 2
    assert gap(p[n + mid]) < 0.5 * gap(m.positions[mid])
    # after the landing and the weight coming back, the clip as it is
    k = land + int(round(LeadInConfig().double_s * FPS)) + 1
    np.testing.assert_allclose(p[n + k :], m.positions[k:], atol=1e-9)
    assert (c[n + k :] == m.contacts[k:]).all()


def test_an_eased_in_clip_joins_the_lead_in_smoothly():
    m = mid_step_clip()
    ext, info = lead_in(m, LeadInConfig(ease_s=0.8))
    n, p = info.frames, ext.positions
    assert info.delay_s == pytest.approx(0.4)
    v = np.linalg.norm(np.diff(p, axis=0), axis=-1).max(axis=1) * FPS  # (T'-1,) fastest joint, m/s
    assert v[n - 1 : n + 1].max() < 0.05, v[n - 3 : n + 3]  # the steps into and out of the first frame
    clip_v = np.linalg.norm(np.diff(m.positions, axis=0), axis=-1).max(axis=1) * FPS
    assert clip_v[0] > 0.2  # ... where the clip itself starts at full speed
    # after the ease-in the clip plays as is, delay_s later
    k = n + int(round((info.ease_s + 0.5) * FPS))
    np.testing.assert_allclose(p[k], m.positions[k - n - int(round(info.delay_s * FPS))], atol=1e-9)
    tc = float(info.clip_time(k / FPS))
    assert abs(tc - (k / FPS - info.t0_s - info.delay_s)) < 1e-9
    assert info.clip_time(0.0) < 0 and abs(float(info.clip_time(info.t0_s))) < 1e-12


def test_a_foot_down_elsewhere_steps_there():
    m = mid_step_clip()
    p = m.positions.copy()
    p[:, [L_ANK, L_TOE, 4], 0] += 0.15  # the left foot stands 15 cm ahead of a standing stance
    m2 = Motion(p, fps=FPS, contacts=m.contacts, name="staggered")
    ext, info = lead_in(m2)
    assert info.steps == ("left", "right")  # the right, in the air, steps to the floor below it
    left = ext.contacts[: info.frames, 0]
    assert left[0] and not left.all() and left[-1]  # down, a swing, down again
    assert abs(ext.positions[info.frames - 1, L_ANK, 0] - p[0, L_ANK, 0]) < 1e-6


def test_the_standing_pose_keeps_the_bone_lengths():
    m = mid_step_clip()
    s = standing_pose(m.positions[0], np.array([REST_POSE[L_ANK, 2], REST_POSE[L_TOE, 2]]))
    from dualflow.motion.skeleton import bone_lengths

    np.testing.assert_allclose(bone_lengths(s)[[3, 4, 6, 7]], bone_lengths(m.positions[0])[[3, 4, 6, 7]], atol=1e-6)


def test_the_check_keeps_the_partner_away_from_where_the_robot_is_in_clip_time():
    """The physics check's face-to-face partner is posed in clip time; the robot's root path it
    keeps its distance from must be too: after a 1 s lead-in standing at x = 0 the robot walks
    +x at 0.5 m/s, so the path's first point is the clip's first frame (x = 0) and its point at
    clip time 1 s is x = 0.5 m, not the trajectory's (x = 0, still in the lead-in)."""
    from retarget import RobotTrajectory
    from retarget.lead_in import LeadIn
    from sim.check import CheckConfig, _actor_placement

    lead = LeadIn(30, FPS, 0.0, (), (), "the pelvis moves")
    t = np.arange(90) / FPS
    root = np.zeros((90, 3))
    root[:, 0] = 0.5 * np.maximum(t - lead.t0_s, 0.0)
    names = ("a", "b")
    meta = {"lead_in": lead.to_dict(), "t0_s": lead.t0_s}
    traj = RobotTrajectory(names, np.zeros((90, 2)), root, np.tile([1.0, 0, 0, 0], (90, 1)), FPS, "op3", meta)
    path = np.asarray(_actor_placement(traj, CheckConfig(mode="free"), None).path)
    assert len(path) == 60  # the clip's 2 s (frames 0..59 of clip time)
    assert path[0, 0] == pytest.approx(0.0) and path[30, 0] == pytest.approx(0.5, abs=1e-6)
    plain = RobotTrajectory(names, np.zeros((90, 2)), root, np.tile([1.0, 0, 0, 0], (90, 1)), FPS, "op3")
    assert len(_actor_placement(plain, CheckConfig(mode="free"), None).path) == 90  # no lead-in: as it is


# -- the robot ------------------------------------------------------------------------------
@pytest.mark.slow
def test_offline_starts_a_mid_step_clip_from_the_standing_stance_and_reports_it(op3):
    m = mid_step_clip()
    # eased in, so that the joints' speed is continuous at the clip's start (the default plays the
    # clip at its own speed from the lead-in's rest)
    traj = OfflineRetargeter(
        op3, OfflineConfig(balance=True, zmp=True, lead_in=LeadInConfig(ease_s=0.8), engine="ipopt")
    ).retarget(m)
    info = lead_in_of(traj)
    assert info is not None and traj.meta["t0_s"] == pytest.approx(info.t0_s, abs=1e-6)
    n = info.frames
    X = configurations(op3, traj)
    # at rest at the start, and in the robot's own standing footprint (feet relative to each other)
    assert np.abs(np.diff(X[:5], axis=0)).max() * FPS < 0.05
    now = stance(op3, op3.evaluate(X[:1])["keypoints"])
    want = stance(op3, op3.evaluate(op3.x_stand[None])["keypoints"])
    # the person's standing stance at the robot's scale, not the robot's own footprint: within 8 mm
    np.testing.assert_allclose(now[:2], want[:2], atol=0.008)  # m
    assert abs(now[2] - want[2]) < 0.05  # rad (the sim check's entry moves the joints with both feet down)
    # joint velocities continuous at the clip's start: small on both sides of it
    v = np.abs(np.diff(X[:, op3.n_root :], axis=0)).max(axis=1) * FPS
    assert v[n - 2 : n + 2].max() < 0.5, v[n - 3 : n + 3]
    # reported: the lead-in before the clip, the ease-in at its start, clip times
    whats = [c["what"] for c in traj.meta["changes"]]
    assert whats[:3] == ["lead-in", "eased in", "held down"]
    lead = traj.meta["changes"][0]
    assert lead["start_s"] == pytest.approx(-info.t0_s, abs=1e-3) and lead["end_s"] == 0.0
    rep = evaluate(op3, traj, make_targets(op3, m))
    assert rep.lead_in["frames"] == n and "lead-in before the clip" in rep.to_markdown()
    assert rep.limit_violations == 0 and rep.velocity_violations == 0
    assert rep.keypoint_error_mean_mm < 60


@pytest.mark.slow
def test_offline_leaves_a_standing_clip_as_it_is(op3):
    m = standing_clip()
    traj = OfflineRetargeter(op3, OfflineConfig(balance=True, zmp=True, engine="ipopt")).retarget(
        m
    )  # the default lead-in
    assert lead_in_of(traj) is None and "t0_s" not in traj.meta
    assert traj.n_frames == m.n_frames
    assert not any(c["what"] in ("lead-in", "eased in") for c in traj.meta["changes"])


@pytest.mark.slow
def test_cmu_18_01_starts_mid_step_and_stays_up_offline(op3, cmu_pair_paths):
    """Real capture: 18_01 starts mid-step (its right foot up, the pelvis at 1 m/s). Offline with
    the lead-in and the swing clearance it gets a lead-in (reported) and passes the physics check
    (it falls 0.24 s into the clip without them); the check's times are clip times. Both are the
    defaults: the configuration retarget-check runs."""
    from dualflow.motion.io import load_any
    from sim.check import CheckConfig, check_trajectory

    m = load_any(cmu_pair_paths[0]).resample(30.0)
    traj = OfflineRetargeter(op3, OfflineConfig(balance=True, zmp=True, engine="ipopt")).retarget(m)
    info = lead_in_of(traj)
    assert info is not None and info.held == ("right",)
    assert traj.meta["changes"][0]["what"] == "lead-in"
    res = check_trajectory(traj, CheckConfig(mode="free"), robot="op3")
    assert res.passed, (res.reason, res.first_failure_time, res.failures[:1])
    assert res.series["t"][0] < -info.t0_s < 0 < res.series["t"][-1]


@pytest.mark.slow
def test_a_floor_clearance_no_swing_can_reach_is_dropped_window_by_window_and_reported(op3):
    """A swing clearance of half the robot's height cannot be met by any swing: the windows are
    solved with the feet only above the floor instead of failing, and the change says so."""
    from retarget.schedule import StepConfig

    m = mid_step_clip()
    cfg = OfflineConfig(balance=True, zmp=True, lead_in=None, steps=StepConfig(swing_clearance=0.5), engine="ipopt")
    traj = OfflineRetargeter(op3, cfg).retarget(m)
    dropped = [c for c in traj.meta["changes"] if c["what"] == "no floor clearance"]
    assert dropped and dropped[0]["start_s"] == 0.0 and "swing clearance" in dropped[0]["why"]
    sole = op3.evaluate(configurations(op3, traj))["sole"]
    assert sole[..., 2].min() > -1e-4  # the feet still stay above the floor
