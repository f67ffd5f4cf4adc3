"""The balance stabilizer (sim/stabilizer.py): legs found from the model, bounded corrections,
push recovery in real MuJoCo, and the same component in the check and in the bridge's loop."""

import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from sim.stabilizer import Stabilizer, StabilizerGains, balance_model

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))


class _Imu:
    def __init__(self, quat, gyro=(0.0, 0.0, 0.0)):
        self.quat = np.asarray(quat, float)
        self.gyro = np.asarray(gyro, float)
        self.accel = np.full(3, np.nan)


def _pitched(angle: float) -> np.ndarray:
    """wxyz of a rotation by ``angle`` rad about y (positive: the top of the body tips forward, +x)."""
    return np.array([np.cos(angle / 2), 0.0, np.sin(angle / 2), 0.0])


@pytest.fixture(scope="module")
def op3():
    from sim.scene import Scene

    scene = Scene()
    return scene, balance_model(scene=scene)


def test_the_op3s_legs_are_found_with_their_ankle_and_hip_joints(op3):
    scene, model = op3
    names = scene.robot.joint_names
    roles = {
        leg.side: {k: names[getattr(leg, k)] for k in ("ankle_pitch", "ankle_roll", "hip_pitch", "hip_roll")}
        for leg in model.legs
    }
    assert roles["right"] == {
        "ankle_pitch": "r_ank_pitch",
        "ankle_roll": "r_ank_roll",
        "hip_pitch": "r_hip_pitch",
        "hip_roll": "r_hip_roll",
    }
    assert roles["left"]["ankle_pitch"] == "l_ank_pitch" and roles["left"]["hip_roll"] == "l_hip_roll"
    assert 3.0 < model.mass < 3.3 and 0.15 < model.com_height < 0.35


def test_a_fixed_base_robot_gets_no_stabilizer():
    assert balance_model("ub14") is None


def test_a_body_tipped_backwards_is_pitched_forward_by_the_ankles_only(op3):
    scene, model = op3
    stab = Stabilizer(model)
    q = scene.stand_ctrl.copy()
    names = scene.robot.joint_names
    for _ in range(50):  # the reference attitude's low-pass settles on the standing pose
        stab.step(q, q, _Imu(_pitched(0.0)), 0.01)
    out = q
    for _ in range(30):
        out = stab.step(q, q, _Imu(_pitched(-0.1)), 0.01)  # measured: 0.1 rad back
    c = out - q
    moved = {names[j] for j in np.flatnonzero(np.abs(c) > 1e-6)}
    assert moved == {"r_ank_pitch", "l_ank_pitch"}
    # the ankles turn the shank (and the body on it) forward over the planted feet: the body's
    # forward rotation is -axis . dq; each ankle pitch axis in the root frame decides the sign
    for leg in model.legs:
        from sim.stabilizer import _leg_frames

        axis = np.array(_leg_frames(leg, q.tolist())[2][leg.ankle_pitch])
        body_turn = -axis * c[leg.ankle_pitch]
        assert body_turn[1] > 0.02  # about +y: the top of the body moves forward


def _rolled(angle: float) -> np.ndarray:
    """wxyz of a rotation by ``angle`` rad about x (positive: the top of the body tips to the left, +y)."""
    return np.array([np.cos(angle / 2), np.sin(angle / 2), 0.0, 0.0])


def _one_foot_up(scene, model, q: np.ndarray) -> np.ndarray:
    """``q`` with the right foot lifted clear of the stance band (hip and knee bent, as a swing)."""
    from sim.stabilizer import _leg_frames

    names = list(scene.robot.joint_names)
    q = q.copy()
    right = next(leg for leg in model.legs if leg.side == "right")
    left = next(leg for leg in model.legs if leg.side == "left")
    for _ in range(40):
        up, sole_r, _ = _leg_frames(right, q.tolist())
        _, sole_l, _ = _leg_frames(left, q.tolist())
        if np.dot(up, np.subtract(sole_r, sole_l)) > 1.5 * model.gains.stance_band:
            return q
        q[names.index("r_knee")] += 0.05 * np.sign(q[names.index("r_knee")] or -1.0)
        q[names.index("r_hip_pitch")] -= 0.025 * np.sign(q[names.index("r_knee")])
    raise AssertionError("could not lift the right foot")


def _correction(model, q: np.ndarray, quat: np.ndarray) -> np.ndarray:
    stab = Stabilizer(model)
    for _ in range(50):  # the reference attitude's low-pass settles on the pose
        stab.step(q, q, _Imu(_rolled(0.0)), 0.01)
    for _ in range(30):
        out = stab.step(q, q, _Imu(quat), 0.01)
    return out - q


def test_a_roll_is_corrected_by_the_ankles_on_one_foot_and_left_to_the_stance_on_two(op3):
    """Standing on two feet, the body's roll is held by the feet standing apart; an ankle-roll
    correction there tips the robot onto one foot and lifts the other (measured on stepping
    clips: about 10 % more lift-offs than planned steps, the landed foot lifting again 6-10 mm).
    So a roll gets no ankle-roll correction on two feet, and the stance ankle's on one."""
    scene, model = op3
    names = list(scene.robot.joint_names)
    q = scene.stand_ctrl.copy()
    # what the roll adds to the correction of the upright body (the stand pose's own pitch)
    two = _correction(model, q, _rolled(0.1)) - _correction(model, q, _rolled(0.0))
    assert np.abs(two).max() < 0.002  # (second-order cross-talk on the pitch joints only)
    q1 = _one_foot_up(scene, model, q)
    one = _correction(model, q1, _rolled(0.1)) - _correction(model, q1, _rolled(0.0))
    assert abs(one[names.index("l_ank_roll")]) > 0.02  # the stance foot's ankle acts
    assert abs(one[names.index("r_ank_roll")]) < 1e-6  # the lifted foot's does not
    # and a pitch on two feet is still the ankles' (both turn alike; the op3's mirrored axes
    # give them opposite signs)
    pitch = _correction(model, q, _pitched(-0.1)) - _correction(model, q, _pitched(0.0))
    left, right = pitch[names.index("l_ank_pitch")], pitch[names.index("r_ank_pitch")]
    assert abs(left) > 0.02 and abs(left) == pytest.approx(abs(right), rel=0.05)


def test_corrections_stay_bounded_in_size_rate_and_joint_limits(op3):
    scene, model = op3
    gains = StabilizerGains(kp=50.0, kd=5.0, max_correction=0.2, max_rate=2.0)
    stab = Stabilizer(model.with_gains(gains))
    q = scene.stand_ctrl.copy()
    rng = np.random.default_rng(0)
    prev = np.zeros_like(q)
    for _k in range(200):
        imu = _Imu(_pitched(rng.uniform(-1.0, 1.0)), gyro=rng.normal(0, 5, 3))
        out = stab.step(q, q + rng.normal(0, 0.05, q.size), imu, 0.01)
        c = out - q
        assert np.all(np.abs(c) <= 0.2 + 1e-9)
        assert np.all(np.abs(c - prev) <= 2.0 * 0.01 + 1e-9)
        assert np.all((out >= model.lower - 1e-9) & (out <= model.upper + 1e-9))
        prev = c


def test_without_an_imu_and_with_the_default_gains_the_reference_passes_unchanged(op3):
    scene, model = op3
    stab = Stabilizer(model)
    q = scene.stand_ctrl.copy()
    assert np.array_equal(stab.step(q, q - 0.05, None, 0.01), q)


@pytest.mark.slow
def test_the_standing_op3_survives_a_lean_it_falls_to_open_loop(op3):
    """A 3.75 N push backwards on the torso for 2.5 s topples the servos alone (measured: they
    survive 3.25 N) and not the stabilized robot (it survives 4.25 N); readings one tick old."""
    from stabilizer import survives

    scene, _ = op3
    assert not survives(scene, -3.75, 0, False, duration=2.5)
    assert survives(scene, -3.75, 0, True, duration=2.5)


@pytest.mark.slow
def test_the_check_runs_the_stabilizer_by_default_and_not_with_it_off():
    from retarget import RobotTrajectory
    from sim.check import CheckConfig, check_trajectory
    from sim.scene import Scene

    scene = Scene()
    n = scene.robot.n
    q = np.tile(scene.stand_ctrl, (150, 1))
    traj = RobotTrajectory(
        scene.robot.joint_names, q, np.zeros((150, 3)), np.tile([1.0, 0, 0, 0], (150, 1)), 50.0, "op3"
    )
    on = check_trajectory(traj, CheckConfig(), robot="op3")
    off = check_trajectory(traj, CheckConfig(stabilizer=False), robot="op3")
    assert on.passed and off.passed
    assert on.metrics["stabilizer"]["on"] and not off.metrics["stabilizer"]["on"]
    assert "no-stabilizer" in off.metrics["stabilizer"]["why_off"]
    assert np.abs(off.series["correction"]).max() == 0.0
    # standing still, the stabilizer only trims: corrections small, commands near the reference
    assert 0.0 < np.abs(on.series["correction"]).max() < 0.05
    assert on.series["correction"].shape == (len(on.series["t"]), n)


@pytest.mark.slow
def test_the_bridge_loop_stabilizes_through_the_safety_filter_and_records_the_correction(tmp_path):
    from ros_free_bridge.control.loop import ControlLoop, LoopConfig
    from ros_free_bridge.control.targets import TargetBuffer, TargetFrame
    from ros_free_bridge.robots import bridge_limits, resolve_robot
    from ros_free_bridge.telemetry.log import TelemetryWriter, read_telemetry
    from ros_free_bridge.transports.sim import SimTransport

    limits = bridge_limits(resolve_robot("op3").hardware_config())
    tr = SimTransport("op3", clock="lockstep")
    buf = TargetBuffer(30.0)
    tel = TelemetryWriter(tmp_path / "t.dftl", limits.names, 100.0)
    loop = ControlLoop(
        tr,
        limits,
        buf,
        LoopConfig(handle_signals=False, min_ramp=0.3),
        tel,
        balance=balance_model("op3", joint_names=tuple(limits.names)),
    )
    assert loop.stabilizer is not None

    names = list(limits.names)
    sway = [names.index(j) for j in ("l_hip_roll", "r_hip_roll", "l_ank_roll", "r_ank_roll")]

    def produce():  # standing, swaying sideways in 0.05 rad jumps every half second
        loop.ready.wait(10)
        base = loop.safety.last_command.copy()
        for k in range(90):
            q = base.copy()
            q[sway] += 0.05 if (k // 15) % 2 else -0.05
            buf.push(TargetFrame(k, q, time.monotonic()))
            time.sleep(1 / 30)
        buf.close()

    threading.Thread(target=produce, daemon=True).start()
    summary = loop.run()
    assert summary.end_state == "STOPPED"
    rec = read_telemetry(tmp_path / "t.dftl").records
    corr = rec["correction"].astype(float)
    assert np.abs(corr).max() > 0  # the IMU was read and used
    legs = {names.index(j) for j in ("r_ank_pitch", "l_ank_pitch", "r_ank_roll", "l_ank_roll")}
    others = [j for j in range(len(names)) if j not in legs]
    assert np.abs(corr[:, others]).max() == 0.0
    cmd = rec["command"].astype(float)
    assert np.all(cmd >= limits.lower - 1e-6) and np.all(cmd <= limits.upper + 1e-6)
    assert np.all(np.abs(np.diff(cmd, axis=0)) <= limits.max_velocity * 0.01 + 1e-5)
    events = [e["kind"] for e in read_telemetry(tmp_path / "t.dftl").events]
    assert "stabilizer" in events
    # ... and the IMU sample it used, each tick: the virtual robot standing upright
    quat, accel = rec["imu_quat"].astype(float), rec["imu_accel"].astype(float)
    assert np.allclose(np.linalg.norm(quat, axis=1), 1.0, atol=1e-4)
    assert np.all(np.abs(quat[:, 1:3]) < 0.1)  # tilted less than about 11 degrees
    assert abs(np.median(accel[:, 2]) - 9.81) < 0.5 and np.all(np.isfinite(rec["imu_gyro"]))
    # the check plays the same feedback as the loop did: its pre-stabilizer targets, readings as
    # old as the transport's (the virtual robot's are fresh), then the loop's safety filter
    from dataclasses import replace

    from sim.check import CheckConfig, check_trajectory

    targets, make_filter, age = read_telemetry(tmp_path / "t.dftl").loop_replay("op3")
    assert age == 0
    result = check_trajectory(
        targets, replace(CheckConfig(), reading_age=age, command_filter=make_filter, judge_reference=False), robot="op3"
    )
    k0 = int(np.searchsorted(result.series["t"], -1e-9))
    gap = np.abs(result.series["correction"][k0 : k0 + len(corr)] - corr).max(axis=1)
    # (the filtered open-loop commands with readings a tick old, the check before: 0.0077 rad)
    assert np.quantile(gap, 0.9) < 2e-3, np.quantile(gap, 0.9)


def test_a_robot_without_an_imu_site_reads_its_body_rate_in_the_body_frame():
    """With no IMU site the root body's own frame stands in for the IMU: a pitch rate must read
    as a pitch rate, also where the body's principal axes of inertia are turned (the published
    OP3's torso: a quarter turn about x; the rate came out as yaw, and the rate feedback then
    drove the ankles with the body's yaw rate while the robot walked)."""
    import mujoco

    from sim.virtual_robot import ImuProbe

    xml = """<mujoco><worldbody><body name="torso" pos="0 0 1"><freejoint/>
      <inertial pos="0 0 0" quat="0.7071068 0.7071068 0 0" mass="1" diaginertia="0.01 0.02 0.03"/>
      </body></worldbody></mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    d.qpos[3:7] = [np.cos(0.15), 0.0, 0.0, np.sin(0.15)]  # turned 0.3 rad about the vertical
    d.qvel[3:6] = [0.2, 1.0, -0.5]  # the free joint's angular velocity, body frame
    mujoco.mj_forward(m, d)
    probe = ImuProbe(m, 1)
    assert probe.site == -1
    reading = probe.read(d)
    np.testing.assert_allclose(reading.gyro, [0.2, 1.0, -0.5], atol=1e-9)
    np.testing.assert_allclose(reading.quat, d.qpos[3:7], atol=1e-9)
    np.testing.assert_allclose(reading.accel, [0.0, 0.0, 9.81], atol=1e-9)


@pytest.mark.slow
def test_a_recorded_demo_run_stays_up_where_a_one_centimetre_stance_band_fell():
    """tests/data/demo_shuffle_run.npz: the pre-stabilizer targets and safety-filter settings of
    a README demo run (bundled partner, op3) whose live robot fell at 9.9 s while shuffling back
    to its stance at 2.8 steps a second. Played as the demo's check plays a run (its targets,
    the check's stabilizer, the run's safety filter): with the default stance band (10 % of the
    robot's height) it stands; with the band at 2 %, as before, a foot the reference lifts by
    less than the stance leg sags gets no share of the correction, and it falls as it did live."""
    from retarget.trajectory import RobotTrajectory
    from ros_free_bridge.control.safety import JointLimits
    from ros_free_bridge.telemetry.log import LoopFilter
    from sim.check import CheckConfig, check_trajectory

    z = np.load(Path(__file__).parent / "data" / "demo_shuffle_run.npz", allow_pickle=False)
    names = tuple(str(n) for n in z["joint_names"])
    q = z["joint_pos"].astype(np.float64)
    traj = RobotTrajectory(
        names, q, np.tile(z["root_pos"], (len(q), 1)), np.tile(z["root_quat"], (len(q), 1)), float(z["fps"]), "op3"
    )
    limits = JointLimits(names, z["lower"], z["upper"], z["max_velocity"], z["max_acceleration"])

    def loop_filter(joint_names, start):
        assert tuple(joint_names) == tuple(names)
        return LoopFilter(float(z["filter_dt"]), z["filter_start"], limits, [])

    def check(gains=None):
        cfg = CheckConfig(
            control_hz=float(z["fps"]),
            stabilizer_gains=gains,
            reading_age=int(z["reading_age"]),
            command_filter=loop_filter,
            judge_reference=False,
        )
        return check_trajectory(traj, cfg, robot="op3")

    now = check()
    assert now.passed, (now.reason, now.first_failure_time)
    assert np.nanmax(now.series["tilt_deg"]) < 25.0
    from sim.scene import Scene

    before = check(StabilizerGains(stance_band=0.02 * Scene().robot_height))
    assert before.reason == "fall" and 9.0 < before.first_failure_time < 10.5
