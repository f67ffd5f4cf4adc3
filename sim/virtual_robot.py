"""The virtual robot: a MuJoCo robot that behaves like a servo bus.

Method names mirror ``ros_free_bridge.transports.base.Transport`` so the bridge wraps it as
its sim transport; readings are :class:`firmware_cfg.readings.JointState` (IMU sample
included; units rad, rad/s, N m, deg C, V; arrays (n,) in the robot's joint order).
``clock="realtime"`` follows the wall clock, ``"lockstep"`` advances one control period per
write. Servo temperatures and faults are modelled. Reference: docs/simulation.md.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from firmware_cfg.readings import ImuReading, JointState
from sim.errors import SimError

STOP_POLICIES = ("hold", "limp")


class ImuProbe:
    """Reads a robot's body IMU from a compiled model (see the module docstring for which
    site and sensors). ``site`` is -1 when the root body's own frame stands in for it."""

    def __init__(self, model, root_body: int):
        import mujoco

        from sim.stabilizer import imu_site

        self._mj = mujoco
        self.model, self.root = model, int(root_body)
        self.site = imu_site(model, root_body)
        self._gyro = self._accel = self._quat = None
        for s in range(model.nsensor):
            if model.sensor_objtype[s] != mujoco.mjtObj.mjOBJ_SITE or model.sensor_objid[s] != self.site:
                continue
            adr = slice(int(model.sensor_adr[s]), int(model.sensor_adr[s]) + int(model.sensor_dim[s]))
            kind = model.sensor_type[s]
            if kind == mujoco.mjtSensor.mjSENS_GYRO and self._gyro is None:
                self._gyro = adr
            elif kind == mujoco.mjtSensor.mjSENS_ACCELEROMETER and self._accel is None:
                self._accel = adr
            elif kind == mujoco.mjtSensor.mjSENS_FRAMEQUAT and self._quat is None:
                self._quat = adr
        self._res = np.zeros(6)

    def read(self, data, stamp: float = 0.0) -> ImuReading:
        mj, m = self._mj, self.model
        if self.site >= 0:
            R = data.site_xmat[self.site].reshape(3, 3)
            objtype, obj = mj.mjtObj.mjOBJ_SITE, self.site
        else:  # the body's own frame: mjOBJ_BODY would give the rate in its principal-inertia frame
            R = data.xmat[self.root].reshape(3, 3)
            objtype, obj = mj.mjtObj.mjOBJ_XBODY, self.root
        if self._quat is not None:
            quat = data.sensordata[self._quat].copy()
        else:
            quat = np.zeros(4)
            mj.mju_mat2Quat(quat, R.reshape(9).copy())
        if self._gyro is not None:
            gyro = data.sensordata[self._gyro].copy()
        else:
            mj.mj_objectVelocity(m, data, objtype, obj, self._res, 1)
            gyro = self._res[:3].copy()
        accel = data.sensordata[self._accel].copy() if self._accel is not None else R.T @ np.array([0.0, 0.0, 9.81])
        return ImuReading(gyro, accel, quat, stamp)


@dataclass(frozen=True)
class VirtualRobotConfig:
    robot: str = "op3"
    fixed_base: bool | None = None
    physics_hz: float = 500.0
    clock: str = "realtime"  # "realtime" | "lockstep"
    control_hz: float = 100.0  # lockstep: physics advanced per write_goal = 1 / control_hz
    speed: float = 1.0  # realtime: multiple of real time
    max_catchup_s: float = 0.1
    voltage: float = 11.1
    ambient_c: float = 25.0
    stall_current_a: float = 2.1
    thermal_resistance_k_per_w: float = 5.0
    thermal_time_constant_s: float = 120.0
    max_temperature_c: float = 80.0
    stop_policy: str = "hold"

    def validate(self) -> None:
        if self.clock not in ("realtime", "lockstep"):
            raise SimError(f"virtual robot: clock must be 'realtime' or 'lockstep', got {self.clock!r}")
        for name in (
            "physics_hz",
            "control_hz",
            "speed",
            "max_catchup_s",
            "voltage",
            "stall_current_a",
            "thermal_resistance_k_per_w",
            "thermal_time_constant_s",
        ):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v > 0):
                raise SimError(f"virtual robot: {name} must be > 0, got {v!r}")
        if self.stop_policy not in STOP_POLICIES:
            raise SimError(f"virtual robot: stop_policy must be one of {STOP_POLICIES}, got {self.stop_policy!r}")


class VirtualRobot:
    """A simulated servo bus; see the module docstring for time, figures and faults."""

    def __init__(self, config: VirtualRobotConfig | None = None, clock=time.monotonic):
        self.config = config = config or VirtualRobotConfig()
        config.validate()
        from firmware_cfg.registry import joint_names
        from sim.scene import robot_model_path

        self.joint_names: tuple[str, ...] = joint_names(robot_model_path(config.robot))
        self._clock = clock
        self._scene = None
        self._opened = False

    # -- Transport-like interface --------------------------------------------
    def open(self) -> None:
        """Build the scene, stand the robot in its "stand" pose, torque off."""
        if self._opened:
            return
        from sim.scene import Scene, SceneConfig

        cfg = self.config
        self._scene = sc = Scene(SceneConfig(robot=cfg.robot, fixed_base=cfg.fixed_base, timestep=1.0 / cfg.physics_hz))
        r, m = sc.robot, sc.model
        self._n = r.n
        self._gain = m.actuator_gainprm[r.actuator_ids, 0].copy()
        self._bias = m.actuator_biasprm[r.actuator_ids, 1].copy()
        self._force = m.actuator_forcerange[r.actuator_ids].copy()
        self._force_limited = m.actuator_forcelimited[r.actuator_ids].copy()
        self._joint_ids = np.array([m.actuator_trnid[a, 0] for a in r.actuator_ids])
        self._range = m.jnt_range[self._joint_ids].copy()  # the model's own, restored by clear_faults
        self._limited = m.jnt_limited[self._joint_ids].copy()
        # goals are clamped to the limits the check uses: the MJCF range, else the profile's or
        # hardware config's (an unranged joint of a published MJCF), else unclamped (RobotIndex)
        self._goal_range = np.stack([r.lower, r.upper], axis=1)
        self._stall = r.stall_torque.copy()  # N m; +inf without a force limit (then no heating)
        self._enabled = np.zeros(self._n, bool)
        self._temp = np.full(self._n, cfg.ambient_c)
        self._errors: dict[str, str] = {}
        self._stuck = np.zeros(self._n, bool)
        self._started = r.fixed_base  # a free robot rests on its stand until torque comes on
        self._sim_t = 0.0
        self._wall0 = self._clock()
        self._goal = sc.stand_ctrl.copy()
        for j in range(self._n):
            self._apply_torque(j, False)
        sc.data.ctrl[r.actuator_ids] = self._goal
        self._imu = ImuProbe(m, r.root_body)
        self._opened = True

    def read_state(self) -> JointState:
        self._require_open()
        self._advance_realtime()
        r, d = self._scene.robot, self._scene.data
        n = self._n
        stamp = self._clock()
        return JointState(
            position=d.qpos[r.qpos_adr].copy(),
            velocity=d.qvel[r.dof_adr].copy(),
            effort=d.actuator_force[r.actuator_ids].copy(),
            temperature=self._temp.copy(),
            voltage=np.full(n, self.config.voltage),
            torque_enabled=self._enabled.copy(),
            stamp=stamp,
            errors=dict(self._errors),
            imu=self._imu.read(d, stamp),
        )

    def write_goal(self, positions) -> None:
        """Goal positions (n,) rad; clamped to the joint limits like a servo's position limits
        (the MJCF range, else the robot folder's limits: :class:`sim.robot_index.RobotIndex`)."""
        self._require_open()
        q = np.asarray(positions, dtype=np.float64)
        if q.shape != (self._n,):
            raise SimError(
                f"virtual robot: write_goal needs {self._n} positions ({', '.join(self.joint_names)}), "
                f"got shape {q.shape}"
            )
        if not np.all(np.isfinite(q)):
            raise SimError("virtual robot: write_goal got NaN or inf; send finite angles in radians")
        self._goal = np.clip(q, self._goal_range[:, 0], self._goal_range[:, 1])
        self._scene.data.ctrl[self._scene.robot.actuator_ids] = self._goal
        if self.config.clock == "lockstep":
            self.step(1.0 / self.config.control_hz)
        else:
            self._advance_realtime()

    def set_torque(self, enabled: bool) -> None:
        self._require_open()
        for j in range(self._n):
            if enabled and self.joint_names[j] in self._errors:
                continue  # a servo in an error state stays off until reboot
            self._apply_torque(j, bool(enabled))
        if enabled and not self._started:
            self._started = True
            self._wall0 = self._clock() - self._sim_t / self.config.speed

    def safe_stop(self, policy: str = "hold") -> None:
        self._require_open()
        if policy not in STOP_POLICIES:
            raise SimError(f"virtual robot: stop policy must be one of {STOP_POLICIES}, got {policy!r}")
        if policy == "hold":
            present = self._scene.data.qpos[self._scene.robot.qpos_adr].copy()
            self._goal = np.clip(present, self._goal_range[:, 0], self._goal_range[:, 1])
            self._scene.data.ctrl[self._scene.robot.actuator_ids] = self._goal
            self.set_torque(True)
        else:
            self.set_torque(False)

    def close(self) -> None:
        if not self._opened:
            return
        try:
            self.safe_stop(self.config.stop_policy)
        finally:
            self._opened = False
            self._scene = None

    # -- simulation ------------------------------------------------------------
    @property
    def scene(self):
        """The underlying :class:`sim.scene.Scene` (for rendering or inspection)."""
        self._require_open()
        return self._scene

    @property
    def sim_time(self) -> float:
        return self._sim_t

    def step(self, seconds: float) -> None:
        """Advance physics by ``seconds`` (rounded to whole physics steps)."""
        self._require_open()
        if not self._started:
            return  # resting on its stand: the simulation clock has not started
        import mujoco

        m, d, r = self._scene.model, self._scene.data, self._scene.robot
        n_steps = int(round(seconds * self.config.physics_hz))
        dt = 1.0 / self.config.physics_hz
        for _ in range(n_steps):
            mujoco.mj_step(m, d)
            self._heat(d.actuator_force[r.actuator_ids], dt)
        self._sim_t += n_steps * dt

    def _advance_realtime(self) -> None:
        if self.config.clock != "realtime" or not self._started:
            return
        target = (self._clock() - self._wall0) * self.config.speed
        lag = target - self._sim_t
        if lag > self.config.max_catchup_s:  # the caller stalled: skip ahead rather than freeze
            self._sim_t = target - self.config.max_catchup_s
            lag = self.config.max_catchup_s
        if lag >= 1.0 / self.config.physics_hz:
            self.step(lag)

    def _heat(self, torque: np.ndarray, dt: float) -> None:
        cfg = self.config
        current = np.abs(torque) / self._stall * cfg.stall_current_a
        resistance = cfg.voltage / cfg.stall_current_a
        power = current**2 * resistance
        self._temp += (
            dt / cfg.thermal_time_constant_s * (power * cfg.thermal_resistance_k_per_w - (self._temp - cfg.ambient_c))
        )
        hot = (self._temp > cfg.max_temperature_c) & self._enabled
        for j in np.flatnonzero(hot):
            self._errors[self.joint_names[j]] = "overheating"
            self._apply_torque(int(j), False)

    def _apply_torque(self, j: int, on: bool) -> None:
        m, a = self._scene.model, self._scene.robot.actuator_ids[j]
        m.actuator_gainprm[a, 0] = self._gain[j] if on else 0.0
        m.actuator_biasprm[a, 1] = self._bias[j] if on else 0.0
        self._enabled[j] = on

    # -- faults ----------------------------------------------------------------
    def inject_fault(self, joint: str, kind: str, value: float | None = None) -> None:
        """``kind`` "stuck" (lock the joint where it is) or "torque_limit" (limit to ``value`` N m)."""
        self._require_open()
        j = self._index(joint)
        m, d, r = self._scene.model, self._scene.data, self._scene.robot
        if kind == "stuck":
            q = float(d.qpos[r.qpos_adr[j]])
            m.jnt_range[self._joint_ids[j]] = (q - 1e-4, q + 1e-4)
            m.jnt_limited[self._joint_ids[j]] = 1
            self._stuck[j] = True
        elif kind == "torque_limit":
            if value is None or not np.isfinite(value) or value < 0:
                raise SimError(f"virtual robot: torque_limit fault needs value >= 0 N m, got {value!r}")
            m.actuator_forcerange[r.actuator_ids[j]] = (-float(value), float(value))
            m.actuator_forcelimited[r.actuator_ids[j]] = 1
        else:
            raise SimError(f"virtual robot: unknown fault {kind!r}; use 'stuck' or 'torque_limit'")

    def clear_faults(self) -> None:
        self._require_open()
        m, r = self._scene.model, self._scene.robot
        m.jnt_range[self._joint_ids] = self._range
        m.jnt_limited[self._joint_ids] = self._limited
        m.actuator_forcerange[r.actuator_ids] = self._force
        m.actuator_forcelimited[r.actuator_ids] = self._force_limited
        self._stuck[:] = False

    def reboot(self, joint: str) -> None:
        """Clear a servo's error (like the Dynamixel Reboot instruction); torque stays off."""
        self._require_open()
        self._errors.pop(self.joint_names[self._index(joint)], None)

    def _index(self, joint: str) -> int:
        try:
            return self.joint_names.index(joint)
        except ValueError:
            raise SimError(
                f"virtual robot: unknown joint {joint!r}; joints are {', '.join(self.joint_names)}"
            ) from None

    def _require_open(self) -> None:
        if not self._opened:
            raise SimError("virtual robot: call open() first (or it was closed)")

    def __enter__(self) -> VirtualRobot:
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()
