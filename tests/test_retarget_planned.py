"""Offline retargeting by the step planner (retarget.planned): which robots it takes, what the
look-ahead changes, and what it reports."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from retarget import RetargetError
from retarget.offline import OfflineConfig, OfflineRetargeter
from retarget.report import evaluate
from retarget.robot import load_robot
from retarget.targets import make_targets

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.stepping_leaders import pivot_turn, walking_leader  # noqa: E402

FPS = 30.0


@pytest.fixture(scope="module")
def op3():
    return load_robot("op3")


def test_auto_plans_a_free_standing_robot_and_optimises_any_other(op3):
    assert OfflineRetargeter(op3, OfflineConfig(balance=True, zmp=True)).engine == "planner"
    assert OfflineRetargeter(op3, OfflineConfig(balance=False)).engine == "ipopt"
    assert OfflineRetargeter(op3, OfflineConfig(balance=True, engine="ipopt")).engine == "ipopt"
    fixed = load_robot("op3", fixed_base=True)
    assert OfflineRetargeter(fixed, OfflineConfig(balance=True)).engine == "ipopt"
    with pytest.raises(RetargetError, match=r"OfflineConfig.engine: .*use engine='ipopt'"):
        OfflineRetargeter(fixed, OfflineConfig(balance=True, engine="planner"))
    with pytest.raises(RetargetError, match=r"OfflineConfig.engine: 'qp' is not one of auto, planner, ipopt"):
        OfflineRetargeter(op3, OfflineConfig(balance=True, engine="qp"))
    for bad in (float("nan"), -0.1, 2.0):
        with pytest.raises(RetargetError, match=r"OfflineConfig.lookahead: .* give 0 to 1 s"):
            OfflineRetargeter(op3, OfflineConfig(balance=True, lookahead=bad))


def test_the_planner_refuses_a_clip_at_another_frame_rate(op3):
    """The step timings and speed limits are per frame: a 120 fps clip through a 30 fps planner
    would step and move 4x too fast. It once ran silently; the streamed run already refused."""
    from retarget.planned import planned_trajectory
    from retarget.streaming import StreamingConfig, StreamingRetargeter

    clip = walking_leader(seconds=2.0, fps=FPS)
    fast = clip.replace(fps=120.0)
    stream = StreamingRetargeter(op3, FPS, StreamingConfig(balance=True, steps=True))
    for run in (stream.run, lambda m: planned_trajectory(stream, m)):
        with pytest.raises(RetargetError, match=r"is 120 fps but this retargeter runs at 30; resample the motion"):
            run(fast)


def _lift_delays(person, robot) -> list[int]:
    """Frames from each lift of a robot foot back to the person's last lift of that foot."""
    up_p, up_r = ~np.asarray(person, dtype=bool), ~np.asarray(robot, dtype=bool)
    out = []
    for s in range(2):
        lifts_p = np.flatnonzero(up_p[1:, s] & ~up_p[:-1, s]) + 1
        for f in np.flatnonzero(up_r[1:, s] & ~up_r[:-1, s]) + 1:
            before = lifts_p[lifts_p <= f]
            if len(before):
                out.append(int(f - before[-1]))
    return out


def test_the_look_ahead_lifts_the_robot_foot_with_the_person_s(op3):
    """Streamed, the robot decides to step when the person's foot lifts, and its own foot leaves
    the floor step_shift (0.17 s, 5 frames) later, once its weight is over the other foot.
    Offline the planner sees the person's contacts lookahead (0.1 s, 3 frames) early: where its
    pace allows, its foot lifts that much sooner, 2 frames after the person's."""
    m = walking_leader(6.0, 0.3, 0.0)
    person = make_targets(op3, m).contacts
    delays = {}
    for ahead in (0.0, 0.1):
        traj = OfflineRetargeter(op3, OfflineConfig(balance=True, zmp=True, lookahead=ahead)).retarget(m)
        assert traj.meta["engine"] == "planner" and traj.meta["lookahead_s"] == pytest.approx(ahead)
        delays[ahead] = _lift_delays(person, traj.meta["contacts"])
    assert len(delays[0.0]) >= 8 and min(delays[0.0]) == 5, delays
    assert min(delays[0.1]) == 2 and np.mean(delays[0.1]) < np.mean(delays[0.0]), delays


def test_the_planner_keeps_the_limits_and_reports_what_it_changed(op3):
    """A person turning 2.5 times on the spot at 0.8 rad/s without stepping: the robot turns by
    steps of its own, within every joint and speed limit, and the trajectory says which seconds
    it did something else than the person and why; the report carries them."""
    m = pivot_turn(0.8, 2.5)
    traj = OfflineRetargeter(op3, OfflineConfig(balance=True, zmp=True)).retarget(m)
    assert traj.meta["mode"] == "offline" and traj.n_frames == m.n_frames
    assert np.asarray(traj.meta["contacts"]).shape == (m.n_frames, 2)
    assert traj.meta["steps"]["person"] == 0 and traj.meta["steps"]["robot"] >= 10
    rep = evaluate(op3, traj, make_targets(op3, m))
    assert rep.limit_violations == 0 and rep.velocity_violations == 0
    # (since its steps may turn each foot as far as the hip-servo blocks allow, 0.45 rad out, the
    # robot keeps within the "own pace" pose threshold of the person; its steps' hip yaws run at
    # the servos' speed limit, and that is what it reports)
    whats = {c["what"] for c in traj.meta["changes"]}
    assert whats and whats <= {"own pace", "own place", "speed-limited"}, whats
    assert all(0 <= c["start_s"] < c["end_s"] <= m.n_frames / FPS + 1e-9 for c in traj.meta["changes"])
    assert all(w in rep.changes_text() for w in whats)


def test_steps_faster_than_the_robot_s_pace_are_reported_skipped(op3):
    """The generated partner orbiting its actor steps 3.5 times a second, about twice the robot's
    pace: the steps it does not take are reported one by one (which seconds, why); a walk at
    the robot's pace skips none."""
    from dualflow.synthetic import make_duet

    off = OfflineRetargeter(op3, OfflineConfig(balance=True, zmp=True))
    fast = off.retarget(make_duet("orbit", seconds=10.0, fps=FPS, seed=1).reactor)
    skipped = [c for c in fast.meta["changes"] if c["what"] == "step skipped"]
    steps = fast.meta["steps"]
    assert steps["robot"] < 0.7 * steps["person"], steps
    assert abs(len(skipped) - (steps["person"] - steps["robot"])) <= 3, (len(skipped), steps)
    assert all("faster than the robot's pace" in c["why"] and c["end_s"] > c["start_s"] for c in skipped)
    walk = off.retarget(walking_leader(6.0, 0.3, 0.0))
    assert walk.meta["steps"]["robot"] == walk.meta["steps"]["person"]
    assert not [c for c in walk.meta["changes"] if c["what"] == "step skipped"]


def test_each_robot_lift_answers_the_swing_it_belongs_to():
    """Skipped steps name the right seconds: with the person's left foot up over frames 10-19 and
    25-34 and one robot lift at 30, the second swing was answered (late) and the first skipped;
    a robot lifting 12 frames early (a 0.4 s look-ahead) answers the swings it anticipated."""
    from retarget.planned import skipped_steps
    from retarget.streaming import StreamingConfig

    cfg = StreamingConfig()
    person = np.ones((60, 2), bool)
    person[10:20, 0] = person[25:35, 0] = False
    robot = np.ones((60, 2), bool)
    robot[30:38, 0] = False
    out = skipped_steps(person, robot, FPS, cfg)
    assert [(c.start_s, c.end_s) for c in out] == [(round(10 / FPS, 3), round(20 / FPS, 3))]
    early = np.ones((60, 2), bool)
    early[0:6, 0] = early[13:21, 0] = False  # the lifts 10 and 12 frames before the person's
    # without the look-ahead the second lift is taken for a late answer to the first swing
    assert [c.start_s for c in skipped_steps(person, early, FPS, cfg)] == [round(25 / FPS, 3)]
    assert skipped_steps(person, early, FPS, cfg, ahead=12) == []


def test_the_streamed_trajectory_says_what_it_changed_too(op3):
    """retarget-check --retargeter streaming and retarget --mode streaming show the same kinds of
    change as the offline planner: the fast orbiting partner's skipped steps among them."""
    from dualflow.synthetic import make_duet
    from retarget.schedule import count_steps
    from retarget.streaming import StreamingConfig, StreamingRetargeter

    m = make_duet("orbit", seconds=10.0, fps=FPS, seed=1).reactor
    traj = StreamingRetargeter(op3, FPS, StreamingConfig(balance=True)).run(m)
    whats = [c["what"] for c in traj.meta["changes"]]
    person, robot = count_steps(make_targets(op3, m).contacts), count_steps(np.array(traj.meta["contacts"], bool))
    assert robot < 0.7 * person and "own pace" in whats, (person, robot, whats)
    assert abs(whats.count("step skipped") - (person - robot)) <= 3, (whats.count("step skipped"), person, robot)


def test_a_long_swing_keeps_the_weight_on_the_stance_foot():
    """While a lifted foot waits up for the person's, the planner's ZMP preview plans the
    landing when the person's own last swing says (or by max_swing), not a fall's length from
    now, frame after frame: that plan for an imminent landing, put off every frame, left the
    CoM between the feet through the swing, and CMU 19_01 planned with 2 mm of marker noise fell
    in MuJoCo at 1.4 s (the planned ZMP 5 mm outside the stance foot). It stands now."""
    from conftest import CMU_DIR, _require

    from dualflow.motion import Motion
    from dualflow.motion.io import load_motion
    from retarget.planned import planned_trajectory
    from retarget.streaming import StreamingConfig, StreamingRetargeter
    from ros_free_bridge.robots import bridge_check_config, planning_robot
    from sim.check import check_trajectory

    motion = load_motion(_require(CMU_DIR / "19_01.bvh")).resample(30.0)
    noisy = Motion(motion.positions + np.random.default_rng(1).normal(0.0, 0.002, motion.positions.shape), 30.0)
    robot = planning_robot("op3")
    traj = planned_trajectory(StreamingRetargeter(robot, 30.0, StreamingConfig(balance=True)), noisy)
    result = check_trajectory(traj, bridge_check_config("op3", mode="free"), robot="op3")
    assert result.passed, result.failures
    assert result.metrics["max_tilt_deg"] < 30
