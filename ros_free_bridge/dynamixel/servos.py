"""The servos of one Dynamixel bus as joints: config ↔ ticks, limits in force, the state block.

:class:`ServoSet` holds, in joint order, each servo's config and model, the joint ↔ tick
mapping (servo_rad = direction · joint_rad + zero_offset; tick = center + servo_rad ·
ticks_per_rad), the limits in force (the config's, narrowed to the EEPROM's at ``open``),
and the state block that readings land in (position, velocity, effort, temperature,
voltage rows). No I/O. :func:`servo_register_settings` / :func:`servo_tick_limits` turn a
servo's config into control-table values; the ``servo`` commands use them too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from firmware_cfg.config import BusConfig, ServoConfig
from firmware_cfg.servo_models import _RPM_TO_RAD_S, Register, ServoModel, load_servo_model
from ros_free_bridge.errors import BridgeError
from ros_free_bridge.transports.base import ImuReading, JointState

#: Profile Acceleration unit of X-series servos: 214.577 rev/min² in rad/s².
ACCEL_UNIT_RAD_S2 = 214.577 * 2.0 * math.pi / 3600.0


def servo_register_settings(servo: ServoConfig, model: ServoModel) -> dict[str, int]:
    """The control-table values a servo's config implies, register name → raw value.

    EEPROM: return delay, temperature and voltage limits, position limits (the joint
    limits mapped to ticks, rounded inwards). RAM: status return level (EEPROM on 1.0),
    PID gains, profile velocity/acceleration, bus watchdog. Registers a model lacks are
    skipped."""
    out: dict[str, int] = {}

    def put(name: str, value: int | None) -> None:
        if value is not None and model.has(name):
            out[name] = int(value)

    put(
        "return_delay_time",
        None if servo.return_delay_us is None else round(servo.return_delay_us / model.return_delay_us),
    )
    put("temperature_limit", servo.temperature_limit_c)
    if servo.voltage_limits_v is not None:
        put("min_voltage_limit", math.ceil(servo.voltage_limits_v[0] / model.voltage_v - 1e-9))
        put("max_voltage_limit", math.floor(servo.voltage_limits_v[1] / model.voltage_v + 1e-9))
    lo_t, hi_t = servo_tick_limits(servo, model)
    if model.has("min_position_limit"):
        put("min_position_limit", lo_t)
        put("max_position_limit", hi_t)
    elif model.has("cw_angle_limit"):
        put("cw_angle_limit", lo_t)
        put("ccw_angle_limit", hi_t)
    put("status_return_level", servo.status_return_level)
    _put_gains(servo, model, put)
    if servo.profile_velocity is not None and model.has("profile_velocity"):
        put("profile_velocity", model.rad_s_to_velocity(servo.profile_velocity))
    if servo.profile_acceleration is not None and model.has("profile_acceleration"):
        put("profile_acceleration", round(servo.profile_acceleration / ACCEL_UNIT_RAD_S2))
    if servo.bus_watchdog_ms is not None:
        put("bus_watchdog", servo.bus_watchdog_ms // 20)
    return out


def _put_gains(servo: ServoConfig, model: ServoModel, put) -> None:
    """The PID gains: X series' position P/I/D, or the protocol 1.0 P/I/D (capped to range)."""
    if servo.pid is None:
        return
    if model.has("position_p_gain"):
        put("position_p_gain", servo.pid.p)
        put("position_i_gain", servo.pid.i)
        put("position_d_gain", servo.pid.d)
        return
    for name, v in (("p_gain", servo.pid.p), ("i_gain", servo.pid.i), ("d_gain", servo.pid.d)):
        if model.has(name):
            rng = model.register(name).range
            put(name, min(v, rng[1]) if rng else v)


def servo_tick_limits(servo: ServoConfig, model: ServoModel) -> tuple[int, int]:
    """The joint limits in the servo's ticks, rounded inwards (never wider than the config)."""
    lo, hi = servo.servo_limits()
    c, k = model.position.center_tick, model.ticks_per_rad
    return (
        max(model.position.min_tick, math.ceil(c + lo * k - 1e-6)),
        min(model.position.max_tick, math.floor(c + hi * k + 1e-6)),
    )


@dataclass
class Servo:
    """One servo: its config, model, the registers of every cycle, the settings the config
    implies (register → raw value) and how often it was rebooted this session."""

    cfg: ServoConfig
    model: ServoModel
    goal: Register
    present: Register
    torque: Register
    settings: dict[str, int]
    reboots: int = 0


class ServoSet:
    """The servos of ``bus`` for ``joint_names`` (default: the config's order); see the
    module docstring. A joint without a servo, or servos placing Goal/Present Position at
    different addresses, is a BridgeError."""

    def __init__(self, bus: BusConfig, joint_names: tuple[str, ...] | None = None) -> None:
        by_joint = {s.joint: s for s in bus.servos}
        names = tuple(joint_names) if joint_names is not None else tuple(s.joint for s in bus.servos)
        missing = [j for j in names if j not in by_joint]
        if missing:
            raise BridgeError(f"Dynamixel bus {bus.name!r}: joints {missing} have no servo in the hardware config")
        self.joint_names = names
        self.servos: list[Servo] = []
        for j in names:
            s = by_joint[j]
            m = load_servo_model(s.model)
            self.servos.append(
                Servo(
                    s,
                    m,
                    m.register("goal_position"),
                    m.register("present_position"),
                    m.register("torque_enable"),
                    servo_register_settings(s, m),
                )
            )
        first = self.servos[0]
        for sv in self.servos[1:]:
            if (sv.goal.address, sv.goal.size, sv.present.address, sv.present.size) != (
                first.goal.address,
                first.goal.size,
                first.present.address,
                first.present.size,
            ):
                raise BridgeError(
                    f"Dynamixel bus {bus.name!r}: {sv.model.name} and {first.model.name} place Goal/Present "
                    "Position at different addresses; put them on separate buses"
                )
        n = len(self.servos)
        self.ids = [s.cfg.id for s in self.servos]
        self.lower = np.array([s.cfg.lower for s in self.servos], float)
        self.upper = np.array([s.cfg.upper for s in self.servos], float)
        self.half_tick = np.array([0.5 / s.model.ticks_per_rad for s in self.servos])
        tick_limits = np.array([servo_tick_limits(s.cfg, s.model) for s in self.servos], dtype=float)
        self.tick_lo, self.tick_hi = tick_limits[:, 0], tick_limits[:, 1]
        self.center = np.array([s.model.position.center_tick for s in self.servos], float)
        self.tpr = np.array([s.model.ticks_per_rad for s in self.servos])
        self.dir = np.array([s.cfg.direction for s in self.servos], float)
        self.off = np.array([s.cfg.zero_offset for s in self.servos])
        # position, velocity, effort, temperature, voltage: one block, so a reading copies it once
        self.block = np.full((5, n), np.nan)
        self.state = JointState(*self.block, np.zeros(n, bool), 0.0)
        self.torque_on = np.zeros(n, bool)  # last known state on the servo
        self.torque_cmd = np.zeros(n, bool)  # what the host asked for
        self._goal_cache: tuple | None = None
        self._joint_rows = tuple(zip(self.center.tolist(), self.tpr.tolist(), self.off.tolist(), self.dir.tolist()))
        self._status_rows = [_status_scales(sv) for sv in self.servos]

    def __len__(self) -> int:
        return len(self.servos)

    def label(self, i: int) -> str:
        return f"servo ID {self.ids[i]} ({self.joint_names[i]})"

    # ------------------------------------------------------------------ joint ↔ ticks
    def to_ticks(self, q: np.ndarray) -> np.ndarray:
        """Joint rad (n,) → goal ticks (n,) int64: round(center + (direction · q + offset) ·
        ticks_per_rad), then clipped to each servo's tick limits (the config's limits rounded
        inwards): a goal exactly at a limit must not round one tick beyond it."""
        ticks = np.rint(self.center + (self.dir * q + self.off) * self.tpr)
        return np.clip(ticks, self.tick_lo, self.tick_hi).astype(np.int64)

    def to_joint(self, ticks: np.ndarray) -> np.ndarray:
        """Present ticks (n,) → joint rad: direction · ((ticks − center) / ticks_per_rad − offset)."""
        return self.dir * ((ticks - self.center) / self.tpr - self.off)

    def present_goal(self) -> np.ndarray:
        """Goal ticks (n,) that hold the present positions, clipped to the limits in force."""
        return self.to_ticks(np.clip(self.state.position, self.lower, self.upper))

    def _goal_rows(self) -> tuple:
        """Per servo, the floats and ints :meth:`goal_ticks` needs, made from the limits in
        force (:meth:`narrow`, the only place that changes them, drops the cache)."""
        if self._goal_cache is None:
            self._goal_cache = tuple(
                zip(
                    (self.lower - self.half_tick).tolist(),
                    (self.upper + self.half_tick).tolist(),
                    self.lower.tolist(),
                    self.upper.tolist(),
                    self.center.tolist(),
                    self.dir.tolist(),
                    self.off.tolist(),
                    self.tpr.tolist(),
                    [int(v) for v in self.tick_lo],
                    [int(v) for v in self.tick_hi],
                )
            )
        return self._goal_cache

    def goal_ticks(self, q: list[float]) -> list[int]:
        """Joint rad (a list of n floats) → goal ticks (n ints): the limit check, the clip and
        :meth:`to_ticks` with Python floats, element by element. The same IEEE operations
        in the same order as the numpy form (``round`` is ``rint``'s round half to even), so
        the same ticks (tested); for 20 servos a few Python steps each cost less than a
        dozen numpy calls. A goal outside a joint's limits (by more than the half tick of
        slack the EEPROM's limits, rounded inwards, leave), NaN or inf is a BridgeError
        naming the servo, and nothing is sent."""
        out = []
        put = out.append
        for x, (lo_ok, hi_ok, lo, hi, center, d, off, tpr, t_lo, t_hi) in zip(q, self._goal_cache or self._goal_rows()):
            if not lo_ok <= x <= hi_ok:  # NaN fails both comparisons
                raise BridgeError(
                    f"{self.label(len(out))}: goal {x:.4f} rad is outside the joint limits "
                    f"[{lo:.4f}, {hi:.4f}]; refusing to send"
                )
            x = lo if x < lo else hi if x > hi else x
            tick = round(center + (d * x + off) * tpr)
            put(t_lo if tick < t_lo else t_hi if tick > t_hi else tick)
        return out

    def set_position(self, ticks) -> None:
        """Present ticks (a tuple of n ints, or an array) → the state's joint positions, rad.
        A tuple takes :meth:`to_joint`'s operations with Python floats (same values)."""
        if isinstance(ticks, np.ndarray):
            self.state.position[:] = self.to_joint(ticks)
            return
        self.state.position[:] = [d * ((t - c) / r - o) for t, (c, r, o, d) in zip(ticks, self._joint_rows)]

    def narrow(self, i: int, lo_t: int, hi_t: int) -> str | None:
        """Narrow servo ``i``'s limits to its EEPROM position limits [lo_t, hi_t] ticks;
        returns a note when they changed. Limits that do not overlap are a BridgeError."""
        sv = self.servos[i]
        a, b = (sv.cfg.to_joint(sv.model.ticks_to_rad(t)) for t in (lo_t, hi_t))
        lo, hi = max(self.lower[i], min(a, b)), min(self.upper[i], max(a, b))
        if lo >= hi:
            raise BridgeError(
                f"{self.label(i)}: EEPROM position limits [{lo_t}, {hi_t}] ticks do not overlap "
                f"the config limits [{sv.cfg.lower:.3f}, {sv.cfg.upper:.3f}] rad; "
                "run `dualflow-bridge servo provision`"
            )
        note = None
        if (lo, hi) != (self.lower[i], self.upper[i]):
            note = f"{self.label(i)}: limits narrowed to the EEPROM's [{lo:.4f}, {hi:.4f}] rad"
        self.lower[i], self.upper[i] = lo, hi
        self.tick_lo[i] = max(self.tick_lo[i], lo_t)
        self.tick_hi[i] = min(self.tick_hi[i], hi_t)
        self._goal_cache = None
        return note

    # ------------------------------------------------------------------ status units
    def apply_units(self, i: int, val: dict[str, int]) -> None:
        """Servo ``i``'s status registers (raw values by field: velocity, current,
        voltage, temperature) into the state, in joint units, with the model's factors
        (Python floats in the servo model's order of operations)::

            velocity rad/s = direction · units · rpm_per_unit · 2π/60
            effort N·m     = direction · units · mA_per_unit / 1000 · torque constant
                             (load-reporting models: direction · units · %/unit / 100 · stall torque)
            voltage V      = units · V_per_unit;  temperature °C = units · °C_per_unit
        """
        d, rpm, ma, kt, load, stall, volt, degc = self._status_rows[i]
        st = self.state
        if "velocity" in val:
            st.velocity[i] = d * (val["velocity"] * rpm * _RPM_TO_RAD_S)
        if "current" in val:
            if ma is not None:
                st.effort[i] = d * (val["current"] * ma / 1000.0) * kt
            elif load is not None:
                st.effort[i] = d * val["current"] * load / 100.0 * stall
        if "voltage" in val:
            st.voltage[i] = val["voltage"] * volt
        if "temperature" in val:
            st.temperature[i] = val["temperature"] * degc

    def reading(self, imu: ImuReading | None) -> JointState:
        """The state as the caller's own copy (one copy of the state block), with ``imu``."""
        st = self.state
        b = self.block.copy()
        return JointState(b[0], b[1], b[2], b[3], b[4], self.torque_on.copy(), st.stamp, dict(st.errors), imu)


def _status_scales(sv: Servo) -> tuple:
    """Servo ``sv``'s unit factors for :meth:`ServoSet.apply_units`, as Python floats (None
    where the model lacks the quantity): (direction, velocity rpm per unit, current mA per
    unit, torque constant N·m/A, load % per unit, stall torque N·m, V per unit, °C per unit)."""
    m = sv.model
    return (
        float(sv.cfg.direction),
        m.velocity_rpm,
        m.current_ma,
        m.torque_constant_nm_per_a if m.current_ma is not None else None,
        m.load_percent,
        m.ratings.stall_torque_nm,
        m.voltage_v,
        m.temperature_c,
    )
