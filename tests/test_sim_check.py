"""The physical check: good motion passes, each kind of bad motion fails with the
right reason, bad input is one clear SimError, reports are complete."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dualflow.motion import REST_POSE, Motion
from firmware_cfg.registry import joint_names
from retarget import RobotTrajectory
from sim import SimError
from sim.check import HUMAN_DISTANCE_CAP, CheckConfig, check_trajectory, resample
from sim.human_figure import People, Placement
from sim.report import write_report
from sim.scene import Scene, SceneConfig

FPS = 30.0


@pytest.fixture(scope="module")
def stand() -> np.ndarray:
    return Scene(SceneConfig(robot="op3")).stand_ctrl


def make(q_of_t, duration: float, robot: str = "op3", root_z: float = 0.27) -> RobotTrajectory:
    names = joint_names(robot)
    t = np.arange(int(round(duration * FPS)) + 1) / FPS
    q = np.array([q_of_t(tt) for tt in t])
    n = len(t)
    return RobotTrajectory(names, q, np.tile([0.0, 0.0, root_z], (n, 1)), np.tile([1.0, 0, 0, 0], (n, 1)), FPS, robot)


def idx(name: str, robot: str = "op3") -> int:
    return joint_names(robot).index(name)


def ramp(tt: float, duration: float) -> float:
    """0 -> 1 smoothly over ``duration`` seconds."""
    x = min(max(tt / duration, 0.0), 1.0)
    return x * x * (3 - 2 * x)


def test_slow_in_limit_dance_passes(stand):
    def q(tt):
        out = stand.copy()
        out[idx("r_sho_pitch")] -= 0.6 * np.sin(0.8 * tt) ** 2
        out[idx("l_sho_pitch")] -= 0.6 * np.sin(0.8 * tt + 1.0) ** 2
        out[idx("l_el")] += 0.4 * np.sin(0.9 * tt) ** 2
        out[idx("head_pan")] = 0.5 * np.sin(0.5 * tt)
        out[idx("head_tilt")] = 0.2 * np.sin(0.7 * tt)
        return out

    result = check_trajectory(make(q, 5.0), CheckConfig(interpolation="cubic"))
    assert result.passed, result.failures
    assert result.reason == "ok" and result.first_failure_time is None
    m = result.metrics
    assert max(m["tracking_max_rad"].values()) < 0.1
    assert m["min_com_margin_m"] > 0.01
    assert m["self_collision_ticks"] == 0 and max(m["foot_slip_m"]) < 0.005
    assert sum(m["speed_limit_hits"].values()) == 0
    # the entry transition from the standing pose (0.5 s: the first frame is the stand) comes first
    assert result.entry_transition_s == pytest.approx(0.5)
    assert result.series["q"].shape == (551, 20) and result.series["t"][50] == pytest.approx(0.0)


@pytest.mark.slow  # matplotlib draws 40 small axes: a few seconds, more on a busy machine
def test_report_files_are_complete(stand, tmp_path):
    def q(tt):
        out = stand.copy()
        out[idx("r_sho_pitch")] = -0.8 * np.sin(2 * np.pi * 2.0 * tt) ** 2
        return out

    result = check_trajectory(make(q, 1.0))
    paths = write_report(result, tmp_path, "fast_arm")
    summary = json.loads(paths["json"].read_text())
    assert summary["passed"] is False and summary["reason"] == "speed_limit"
    assert summary["joint_names"] == list(joint_names("op3"))
    assert summary["failures"][0]["time"] == pytest.approx(result.first_failure_time)
    md = paths["markdown"].read_text()
    assert "FAIL: speed_limit" in md and "fast_arm_joints.png" in md and md.count("| r_sho_pitch |") == 1
    for key in ("joints_png", "torque_png", "balance_png"):
        assert paths[key].stat().st_size > 5000
    assert not list(tmp_path.glob("*partial*"))


def test_too_fast_fails_on_speed_limit(stand):
    def q(tt):
        out = stand.copy()
        out[idx("r_sho_pitch")] = -0.8 * np.sin(2 * np.pi * 2.0 * tt) ** 2  # peak 10 rad/s
        return out

    result = check_trajectory(make(q, 2.0))
    assert not result.passed
    assert result.reason == "speed_limit"
    assert "r_sho_pitch" in result.failures[0].detail
    assert 0.0 <= result.first_failure_time < 0.2
    assert result.metrics["speed_limit_hits"]["r_sho_pitch"] > 0
    assert result.metrics["speed_limit_hits"]["l_sho_pitch"] == 0


def test_self_collision_fails_with_its_reason(stand):
    def q(tt):  # both legs adduct until the feet hit each other (torso bolted: no balance confound)
        out = stand.copy()  # ROBOTIS's axes: adduction is left +, right -
        out[idx("l_hip_roll")] = 0.5 * ramp(tt, 2.0)
        out[idx("r_hip_roll")] = -0.5 * ramp(tt, 2.0)
        return out

    # the servos press the soles together at stall torque: the contact holds them about a
    # millimetre deep, under the default 2 mm tolerance (which published models' resting
    # hull overlaps need), so the mechanism is tested with no tolerance
    result = check_trajectory(make(q, 3.0, root_z=0.4), CheckConfig(mode="fixed", self_collision_depth=0.0))
    assert result.reason == "self_collision", result.failures
    assert "l_foot / r_foot" in result.failures[0].detail
    assert 0.3 < result.first_failure_time < 2.0
    assert result.metrics["self_collision_pairs"] == ["l_foot / r_foot"]
    default = check_trajectory(make(q, 3.0, root_z=0.4), CheckConfig(mode="fixed"))
    assert "self_collision" not in [f.reason for f in default.failures]


def test_leaning_over_the_toes_warns_on_balance_then_falls(stand):
    def q(tt):  # ankles tip the whole body forward (toes up relative to the shin: left +, right -)
        out = stand.copy()
        out[idx("l_ank_pitch")] += 0.5 * ramp(tt, 3.0)
        out[idx("r_ank_pitch")] += -0.5 * ramp(tt, 3.0)
        return out

    result = check_trajectory(make(q, 4.0))
    # the margins are warnings; the outcome, the fall, is the failure
    assert result.reason == "fall", result.failures
    kinds = {w.kind: w.time for w in result.warnings}
    assert kinds["zmp_near_edge"] < result.first_failure_time
    assert kinds["com_outside_support"] < result.first_failure_time
    assert result.metrics["min_com_margin_m"] < 0


def test_after_a_fall_the_ticks_never_sent_are_not_judged_for_speed(stand):
    """A fast lean that falls with the stabilizer at its limit: the check stops
    stop_after_fall_s after the fall, and the commands it never played (where the corrected
    command would jump back to the plan) are not read as a servo commanded past its speed."""

    def q(tt):
        out = stand.copy()
        out[idx("l_ank_pitch")] += 1.0 * ramp(tt, 1.5)
        out[idx("r_ank_pitch")] += -1.0 * ramp(tt, 1.5)
        return out

    result = check_trajectory(make(q, 3.0))
    assert result.reason == "fall", result.failures
    assert [f.reason for f in result.failures] == ["fall"], result.failures


def test_robot_entering_the_human_fails(stand):
    pos = np.tile(REST_POSE, (61, 1, 1))
    actor = Motion(pos, 30.0, name="overlapping person")
    # a person scaled to the robot's size standing where the robot stands
    result = check_trajectory(make(lambda tt: stand, 2.0), people=People(actor, Placement("robot", (0.02, 0, 0))))
    assert result.reason == "human_penetration"
    assert result.metrics["min_human_distance_m"] < -0.005
    far = check_trajectory(
        make(lambda tt: stand, 1.0), people=People(Motion(pos[:31], 30.0), Placement("robot", (0.6, 0, 0)))
    )
    assert far.passed and far.metrics["min_human_distance_m"] == pytest.approx(HUMAN_DISTANCE_CAP)


def test_command_outside_joint_limits_fails(stand):
    def q(tt):
        out = stand.copy()
        out[idx("head_pan")] = 1.8 * ramp(tt, 1.0)  # beyond +0.5 pi
        return out

    result = check_trajectory(make(q, 1.5))
    assert result.failures[0].reason == "joint_limit"
    assert "head_pan" in result.failures[0].detail


def test_fixed_base_upper_body_robot_checks():
    names = joint_names("ub14")
    stand = Scene(SceneConfig(robot="ub14")).stand_ctrl

    def q(tt):
        out = stand.copy()
        out[names.index("waist_yaw")] = 0.4 * np.sin(0.6 * tt)
        out[names.index("l_sho_pitch")] = -1.0 * np.sin(0.5 * tt) ** 2
        out[names.index("r_el")] = 0.3 + 0.8 * np.sin(0.7 * tt) ** 2
        return out

    result = check_trajectory(make(q, 4.0, robot="ub14", root_z=0.0), CheckConfig(mode="fixed"))
    assert result.passed, result.failures
    assert result.metrics["min_com_margin_m"] is None  # no balance judged for a bolted base


def test_wrong_joint_count_is_a_sim_error(stand):
    names = joint_names("op3")[:19]
    traj = RobotTrajectory(
        names, np.tile(stand[:19], (10, 1)), np.zeros((10, 3)), np.tile([1.0, 0, 0, 0], (10, 1)), 30.0, "op3"
    )
    with pytest.raises(SimError, match="has 19 joints but robot 'op3' has 20"):
        check_trajectory(traj)


def _write_npz(path, joint_pos, fps):
    header = json.dumps({"joint_names": list(joint_names("op3")), "robot": "op3", "meta": {}})
    n = len(joint_pos)
    np.savez(
        path,
        joint_pos=joint_pos,
        root_pos=np.zeros((n, 3)),
        root_quat=np.tile([1.0, 0, 0, 0], (n, 1)),
        fps=np.float64(fps),
        header=np.array(header),
    )
    return path


def test_nan_and_zero_fps_files_are_sim_errors(stand, tmp_path):
    q = np.tile(stand, (10, 1))
    q[4, 3] = np.nan
    with pytest.raises(SimError, match="NaN"):
        check_trajectory(_write_npz(tmp_path / "nan.npz", q, 30.0))
    with pytest.raises(SimError, match="fps must be > 0"):
        check_trajectory(_write_npz(tmp_path / "fps0.npz", np.tile(stand, (10, 1)), 0.0))
    with pytest.raises(SimError, match="not found"):
        check_trajectory(tmp_path / "missing.npz")


@pytest.mark.parametrize(
    "config, match",
    [
        (CheckConfig(control_hz=0), "control_hz must be > 0"),
        (CheckConfig(physics_hz=450), "whole multiple"),
        (CheckConfig(interpolation="spline"), "interpolation"),
        (CheckConfig(mode="floating"), "mode"),
    ],
)
def test_bad_config_is_a_sim_error(stand, config, match):
    with pytest.raises(SimError, match=match):
        check_trajectory(make(lambda tt: stand, 0.5), config)


def test_resample_linear_and_cubic_hit_the_samples():
    times = np.arange(5) / 10.0
    values = np.stack([np.sin(times), times**2], axis=1)
    for kind in ("linear", "cubic"):
        out = resample(times, values, times, kind)
        assert np.allclose(out, values)
    mid = resample(times, values, np.array([0.05, 1.0]), "linear")
    assert np.allclose(mid[0], (values[0] + values[1]) / 2)
    assert np.allclose(mid[1], values[-1])  # clamped past the end


def test_cmu_actor_is_placed_and_measured(cmu_pair_paths, stand):
    """Real two-person capture: the actor placed relative to the robot standing in for
    the reactor is measured at a distance; moved onto the robot it is a penetration."""
    from dualflow.motion.io import load_pair
    from sim.human_figure import estimate_height

    pair = load_pair(*cmu_pair_paths, fps=30)
    actor, reactor = pair.actor.slice(0, 45), pair.reactor.slice(0, 45)
    height = Scene(SceneConfig(robot="op3")).robot_height
    scale = height / estimate_height(reactor)
    assert 0.2 < scale < 0.4  # an adult scaled to a 0.51 m robot
    pelvis = reactor.positions[0, 0]
    apart = Placement(scale, (-scale * pelvis[0], -scale * pelvis[1], 0.0))
    ok = check_trajectory(make(lambda tt: stand, 1.4), people=People(actor, apart))
    assert ok.passed, ok.failures
    assert ok.metrics["min_human_distance_m"] == pytest.approx(HUMAN_DISTANCE_CAP)  # over 0.1 m away
    on_top = Placement(scale, (-scale * actor.positions[0, 0, 0], -scale * actor.positions[0, 0, 1], 0.0))
    hit = check_trajectory(make(lambda tt: stand, 1.4), people=People(actor, on_top))
    assert hit.reason == "human_penetration"
