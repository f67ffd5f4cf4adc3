"""Offline retargeting with IPOPT: round trip, seamless windows, hard contacts, balance, errors.

Problems here are small and solved without C compilation (CasADi's virtual machine), so the
suite needs no compiler; the compiled path is exercised by bench/retarget_speed.py and the
slow CMU test."""

import re

import numpy as np
import pytest
from retarget_toy import toy_robot
from test_retarget_streaming import op3_for_round_trip, robot_clip

from dualflow.errors import DualFlowError
from dualflow.motion import REST_POSE, Motion
from retarget import RetargetError
from retarget.offline import OfflineConfig, OfflineRetargeter
from retarget.report import configurations, evaluate
from retarget.targets import KeypointScaler, human_from_keypoints, make_targets

# lead_in=None: these test the window solver on the clip's own frames (the lead-in: test_retarget_lead_in.py)
FAST = dict(compile=False, self_collision=False, lead_in=None)


def test_round_trip_recovers_joint_angles_across_windows():
    rb = op3_for_round_trip()
    X = robot_clip(rb, T=45, seed=5)
    motion = human_from_keypoints(rb, rb.evaluate(X)["keypoints"], fps=30.0)
    cfg = OfflineConfig(
        window=24,
        overlap=8,
        accel_weight=0.0,
        jerk_weight=0.0,
        contacts=False,
        tol=1e-9,
        ipopt_options=(("acceptable_tol", 1e-9),),
        **FAST,
    )
    traj = OfflineRetargeter(rb, cfg).retarget(motion, contacts=np.zeros((45, 2), bool), scaler=KeypointScaler(rb))
    assert traj.meta["windows"] >= 2
    assert len(traj.meta["ipopt_status"]) == traj.meta["windows"]
    assert set(traj.meta["ipopt_status"]) <= {"Solve_Succeeded", "Solved_To_Acceptable_Level"}
    assert np.abs(traj.joint_pos - X[:, rb.n_root :]).max() < 2e-3


def _noisy_walk(T=70, seed=0):
    """A person swaying and stepping in place with 5 mm of marker noise (m, 30 fps)."""
    t = np.arange(T) / 30.0
    pos = np.repeat(REST_POSE[None], T, axis=0).copy()
    pos[:, :, 0] += 0.1 * t[:, None]
    pos[:, 16:, 2] -= 0.25 * (1 + np.sin(2 * np.pi * 0.8 * t))[:, None] * (np.arange(16, 22) >= 18)[None]
    lift = np.clip(np.sin(2 * np.pi * 0.7 * t), 0, None) * 0.08
    pos[:, [4, 7, 10], 2] += lift[:, None] * np.array([0.5, 1.0, 1.0])
    pos += np.random.default_rng(seed).normal(scale=0.005, size=pos.shape)
    return Motion(pos, fps=30.0, name="noisy_walk")


def test_windows_blend_without_a_velocity_jump_at_the_seams():
    rb = toy_robot()
    motion = _noisy_walk()
    whole = OfflineRetargeter(rb, OfflineConfig(window=0, contacts=False, **FAST)).retarget(motion)
    win_r = OfflineRetargeter(rb, OfflineConfig(window=24, overlap=8, contacts=False, **FAST))
    windowed = win_r.retarget(motion)
    assert windowed.meta["windows"] >= 4 and whole.meta["windows"] == 1
    q_w, q_a = windowed.joint_pos, whole.joint_pos
    # the stitched solution is the whole-clip solution (up to solver tolerance) ...
    assert np.abs(q_w - q_a).max() < 0.03
    # ... and its acceleration at each seam is no different from anywhere else
    acc = np.abs(np.diff(q_w, n=2, axis=0)).max(axis=1)
    hop = 24 - 8
    seams = [s + 3 - 1 for s in range(hop, len(q_w) - 1, hop)]  # first frame solved by the next window
    interior = np.median(acc)
    for s in seams:
        assert acc[s - 1 : s + 2].max() < 4 * interior + 1e-3, (s, acc[s - 1 : s + 2], interior)
    vel_jump = np.abs(np.diff(q_w - q_a, axis=0)).max()
    assert vel_jump < 0.01


@pytest.fixture(scope="module")
def toy_with_contacts():
    rb = toy_robot()
    motion = _noisy_walk(T=60, seed=1)
    cfg = OfflineConfig(window=30, overlap=10, balance=True, balance_margin=0.005, zmp=False, **FAST, engine="ipopt")
    traj = OfflineRetargeter(rb, cfg).retarget(motion)
    return rb, motion, traj


def test_feet_in_contact_stay_put_on_the_ground(toy_with_contacts):
    rb, motion, traj = toy_with_contacts
    tg = make_targets(rb, motion)
    assert tg.contacts.any(axis=0).all() and not tg.contacts.all()
    sole = rb.evaluate(configurations(rb, traj))["sole"]
    for side in range(2):
        c = tg.contacts[:, side]
        z = sole[c, 4 * side : 4 * side + 4, 2]
        assert np.abs(z).max() < 1e-4  # flat on the ground
        both = c[1:] & c[:-1]
        slide = np.linalg.norm(np.diff(sole[:, 4 * side : 4 * side + 4, :2], axis=0), axis=-1).max(axis=1)
        assert slide[both].max() < 5e-4  # no sliding (a window seam is held by a stiff penalty: ~0.1 mm)
    assert sole[..., 2].min() > -1e-5  # nothing below the ground
    rep = evaluate(rb, traj, tg)
    assert rep.skate_share == 0.0 and rep.penetration_mm < 0.01
    assert rep.limit_violations == 0 and rep.velocity_violations == 0


def _inside(p, poly):
    """Point (2,) inside convex polygon (n, 2) given in any order (with a tolerance)."""
    from scipy.spatial import ConvexHull

    hull = ConvexHull(poly)
    return np.all(hull.equations[:, :2] @ p + hull.equations[:, 2] <= 1e-6)


def _shrunk_soles(ev, contacts, t, margin):
    """Corners (k, 2) of the soles in contact at frame ``t``, each shrunk by ``margin`` (m)."""
    pts = []
    for side in range(2):
        if contacts[t, side]:
            c = ev["sole"][t, 4 * side : 4 * side + 4, :2]
            centre = c.mean(axis=0)
            pts.append(centre + (c - centre) * (1 - 2 * margin / np.ptp(c, axis=0).max()))
    return np.concatenate(pts)


def test_balance_keeps_the_com_over_the_shrunk_support_polygon(toy_with_contacts):
    rb, motion, traj = toy_with_contacts
    # the robot's schedule, which the rows follow: here the person's contacts except the last
    # 0.47 s, where the person's left foot lifts and does not land before the clip ends and the
    # robot keeps it down (retarget.schedule: an unfinished step)
    planned = np.asarray(traj.meta["contacts"], dtype=bool)
    assert [c["what"] for c in traj.meta["changes"]] == ["unfinished step"]
    ev = rb.evaluate(configurations(rb, traj))
    margin = 0.005
    for t in np.flatnonzero(planned.any(axis=1)):
        poly = _shrunk_soles(ev, planned, t, margin)
        assert _inside(ev["com"][t, :2], np.concatenate([poly, poly + 1e-9])), t


def test_zmp_balance_keeps_the_zmp_over_the_shrunk_support_polygon():
    """With ``zmp`` and ``zmp_model="cart-table"`` the point kept over the polygon is the ZMP of a
    point mass at the CoM, c_xy − c_z·c̈_xy / (c̈_z + g), which a swaying clip moves away from the
    CoM; checked on interior frames of each window, with the default swing clearance. The
    vertical acceleration counts: the swing clearance's vertical lift-off gives c̈_z ≈ 1 m/s² at
    the frame before it, where the linear form c_xy − (c_z/g)·c̈_xy lies ~6 mm beyond the point
    the rows hold (~4 mm outside the shrunk sole)."""
    rb = toy_robot()
    motion = _noisy_walk(T=30, seed=2)
    margin = 0.005
    cfg = OfflineConfig(
        window=0, balance=True, balance_margin=margin, zmp=True, zmp_model="cart-table", **FAST, engine="ipopt"
    )
    traj = OfflineRetargeter(rb, cfg).retarget(motion)
    ev = rb.evaluate(configurations(rb, traj))
    com = ev["com"]
    acc = np.diff(com, n=2, axis=0) * 30.0**2  # (T-2, 3), central differences
    zmp = com[1:-1, :2] - com[1:-1, 2:3] * acc[:, :2] / (9.81 + acc[:, 2:3])
    assert np.abs(zmp - com[1:-1, :2]).max() > 1e-3  # the acceleration term matters on this clip
    planned = np.asarray(traj.meta["contacts"], dtype=bool)  # the robot's schedule, which the rows follow
    assert (~planned).any(), "the clip has a swing (the lift-off and touch-down frames are checked)"
    for t in range(1, len(com) - 1):
        if not planned[t].any():
            continue
        poly = _shrunk_soles(ev, planned, t, margin)
        assert _inside(zmp[t - 1], np.concatenate([poly, poly + 1e-9])), t


def test_fixed_base_keeps_the_root_still():
    rb = toy_robot(fixed_base=True)
    motion = _noisy_walk(T=30)
    traj = OfflineRetargeter(rb, OfflineConfig(window=0, **FAST)).retarget(motion)
    assert np.ptp(traj.root_pos, axis=0).max() == 0.0
    assert evaluate(rb, traj, make_targets(rb, motion)).limit_violations == 0


def test_an_unsolved_window_is_a_clear_error_offering_retiming():
    """When IPOPT stops with the hard constraints violated, the user hears which frames, what
    IPOPT said, and how to re-time (here forced with a one-iteration budget: the streaming
    warm start does not satisfy the hard contact constraints)."""
    rb = toy_robot()
    motion = _noisy_walk(T=20, seed=3).replace(name="stomp")
    r = OfflineRetargeter(rb, OfflineConfig(window=0, max_iter=1, **FAST))
    with pytest.raises(
        RetargetError, match=r"stomp: infeasible at its speed: frames 0\.\.19: IPOPT says .*retime=1\.5"
    ) as err:
        r.retarget(motion)
    # the moment of the worst violation, named in the message, in seconds into the clip
    frame = int(re.search(r"at frame (\d+)", str(err.value)).group(1))
    assert 0 <= frame <= 19 and err.value.time_s == round(frame / motion.fps, 3)


def test_a_solver_error_is_never_taken_for_a_solution():
    """IPOPT told to use a linear solver it does not have returns at once (Invalid_Option) with
    the warm start untouched. Here the warm start satisfies every constraint (no contacts), so
    only the status tells: it must be an error naming the status and the option, never a
    trajectory, and the next solve in the same process works."""
    rb = toy_robot()
    motion = _noisy_walk(T=20, seed=3)
    bad = OfflineRetargeter(
        rb, OfflineConfig(window=0, contacts=False, ipopt_options=(("linear_solver", "custom"),), **FAST)
    )
    with pytest.raises(
        RetargetError, match=r"IPOPT failed on frames 0\.\.19 with status Invalid_Option.*'linear_solver': 'custom'"
    ):
        bad.retarget(motion)
    traj = OfflineRetargeter(rb, OfflineConfig(window=0, contacts=False, **FAST)).retarget(motion)
    assert traj.meta["ipopt_status"][0] in ("Solve_Succeeded", "Solved_To_Acceptable_Level")


def test_an_unfinished_window_is_a_failed_retarget_even_when_feasible():
    """Stopped by the iteration budget at a point that satisfies the hard constraints: not a
    result (issue 23: a non-converged solve never passes). The error names the window's frames,
    IPOPT's status and the fix, and its time is the window's start; a later window is named by
    its own frames."""
    rb = toy_robot()
    motion = _noisy_walk(T=20, seed=3).replace(name="sway")
    r = OfflineRetargeter(rb, OfflineConfig(window=0, contacts=False, max_iter=2, **FAST))
    with pytest.raises(
        RetargetError,
        match=r"sway: retarget failed \(not converged\) at its speed: frames 0\.\.19: "
        r"IPOPT says Maximum_Iterations_Exceeded after 2 iterations.*max_iter, now 2",
    ) as err:
        r.retarget(motion)
    assert err.value.time_s == 0.0
    # with a budget that is enough, the same problem is solved and kept
    traj = OfflineRetargeter(rb, OfflineConfig(window=0, contacts=False, **FAST)).retarget(motion)
    assert set(traj.meta["ipopt_status"]) <= {"Solve_Succeeded", "Solved_To_Acceptable_Level"}
    rep = evaluate(rb, traj, make_targets(rb, motion))
    assert rep.limit_violations == 0 and rep.velocity_violations == 0


def test_retiming_plays_the_clip_slower_within_limits():
    rb = toy_robot()
    motion = _noisy_walk(T=20, seed=4)
    traj = OfflineRetargeter(rb, OfflineConfig(window=0, retime=2.0, **FAST)).retarget(motion)
    assert traj.meta["retime"] == 2.0 and traj.n_frames == 39 and traj.fps == 30.0
    q = traj.joint_pos
    assert np.all(np.abs(np.diff(q, axis=0)) * 30.0 <= rb.velocity_limits + 1e-9)


@pytest.mark.parametrize("frames, match", [(1, "1 frame"), (0, None)])
def test_short_clips_are_refused(frames, match):
    rb = toy_robot()
    if frames == 0:
        with pytest.raises(DualFlowError):
            Motion(np.zeros((0, 22, 3)))
        return
    with pytest.raises(RetargetError, match=match):
        OfflineRetargeter(rb, OfflineConfig(**FAST)).retarget(Motion(REST_POSE[None], fps=30.0))
