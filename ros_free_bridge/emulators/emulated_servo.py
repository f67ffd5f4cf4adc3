"""One emulated Dynamixel servo: its control-table memory, write rules and a motor model.

The bus emulator (:mod:`.dynamixel_bus`) owns a list of these and calls them from its
reader thread under one lock; they hold no lock of their own. Everything is in the
servo's own units (ticks, register units) from its :mod:`firmware_cfg.servo_models` table.
A write returns a :class:`WriteResult` (ok, or 'access' / 'length' / 'range' / 'limit',
all-or-nothing); the motor model (slew-limited position, current, temperature, hardware
errors with Shutdown, the Bus Watchdog) advances lazily to the present before every
access. The rules and equations are written out in docs/dynamixel.md.
"""

from __future__ import annotations

import math
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass

from firmware_cfg.servo_models import ServoModel

#: Hardware Error Status bits (X series, e-Manual "Shutdown(63)").
HW_INPUT_VOLTAGE = 0x01
HW_OVERHEATING = 0x04
HW_MOTOR_ENCODER = 0x08
HW_ELECTRICAL_SHOCK = 0x10
HW_OVERLOAD = 0x20

#: Protocol 1.0 status error bits that mirror hardware conditions.
_P1_HW_BITS = {HW_INPUT_VOLTAGE: 0x01, HW_OVERHEATING: 0x04, HW_OVERLOAD: 0x20}

_GOAL_REGISTERS = frozenset({"goal_pwm", "goal_current", "goal_velocity", "goal_position"})

_FORMATS = {(1, False): "<B", (2, False): "<H", (4, False): "<I", (1, True): "<b", (2, True): "<h", (4, True): "<i"}

#: The motor model skips updates shorter than this (s); time keeps accumulating, so
#: nothing is lost, and a 20-servo sync read does not recompute 20 models per packet.
MIN_STEP_S = 2e-4

THERMAL_TAU_S = 60.0
THERMAL_RISE_AT_STALL_K = 60.0
OVERLOAD_TIME_S = 1.0
CURRENT_SATURATION_TICKS = 128.0


@dataclass(frozen=True)
class GoalRecord:
    """A Goal Position value that reached a servo: when (``time.monotonic()`` s), what
    (ticks), through which instruction, and whether the servo accepted it."""

    stamp: float
    servo_id: int
    ticks: int
    accepted: bool
    instruction: str


@dataclass(frozen=True)
class WriteResult:
    """Outcome of a write: ``error`` is None, 'access', 'length', 'range' or 'limit'."""

    error: str | None = None

    @property
    def ok(self) -> bool:
        return self.error is None


_WRITE_OK = WriteResult(None)
_WRITE_RANGE = WriteResult("range")
_WRITE_LIMIT = WriteResult("limit")


@dataclass
class Faults:
    """Injected faults of one servo (see the bus emulator's fault API)."""

    drop_replies: int = 0  # replies to swallow; -1 = all until cleared
    corrupt_replies: int = 0  # replies to send with a broken CRC; -1 = all
    disconnected: bool = False  # neither hears nor answers
    stuck: bool = False  # motor cannot move
    injected_hw_error: int = 0  # Hardware Error Status bits forced on
    hw_error_survives_reboot: bool = False
    held_temperature_c: float | None = None
    supply_v: float | None = None  # None: the model's rated voltage

    def take(self, name: str) -> bool:
        """Consume one count of a counted fault; True if it applies to this reply."""
        n = getattr(self, name)
        if n == 0:
            return False
        if n > 0:
            setattr(self, name, n - 1)
        return True


class EmulatedServo:
    """A servo's state. ``servo_id`` is read from its ID register (it can be rewritten)."""

    def __init__(
        self,
        model: ServoModel,
        servo_id: int,
        position_ticks: float | None = None,
        *,
        clock: Callable[[], float] = time.monotonic,
        ambient_c: float = 25.0,
    ) -> None:
        self.model = model
        self.clock = clock
        self.ambient_c = ambient_c
        self.faults = Faults()
        self.goal_history: list[GoalRecord] = []
        self.allowed_range: tuple[int, int] | None = None
        self.violations: list[GoalRecord] = []
        self.booting_until = 0.0
        self._mem = bytearray(max(model.table_size, 1))
        # decoded register values, name -> int: every change of _mem drops what it touched
        # (set, write, the goal fast path) or everything (factory fill); registers never overlap
        self._cache: dict[str, int] = {}
        self._regs = model.registers
        # name -> (offset, struct packer or None for sign-magnitude, register): fast access
        self._acc = {
            r.name: (r.address, None if r.sign_bit is not None else struct.Struct(_FORMATS[(r.size, r.signed)]), r)
            for r in model.registers.values()
        }
        self._registered: tuple[int, bytes] | None = None
        self._baud_memo: tuple[int | None, int | None] = (None, None)
        self._spans: dict[tuple[int, int], tuple] = {}  # (start, end) -> registers in it (the table never changes)
        present, goal = model.registers["present_position"], model.registers["goal_position"]
        self._present_span = (present.address, present.end)
        self._goal_span = (goal.address, goal.end)
        self._has_mode = "operating_mode" in model.registers
        has = model.registers.__contains__
        self._vel_name = "present_velocity" if has("present_velocity") else "present_speed"
        self._volt_name = model.first_register("present_input_voltage", "present_voltage").name
        self._has_current = has("present_current") and bool(model.current_ma)
        self._has_load = has("present_load")
        self._has_trajectory = has("velocity_trajectory") and has("position_trajectory")
        self._has_threshold = has("moving_threshold")
        self._has_hw_register = has("hardware_error_status")
        self._has_tick = has("realtime_tick")
        self._has_voltage_limits = has("min_voltage_limit") and has("max_voltage_limit")
        self._has_temp_limit = has("temperature_limit")
        self._has_shutdown = has("shutdown")
        self._has_watchdog = has("bus_watchdog")
        self._last_heard = clock()
        self._torque_on_at = self._last_heard
        self._vel_units_per_tick_s = 60.0 / model.position.ticks_per_turn / model.velocity_rpm
        self._vel = 0.0
        self._cur = 0.0
        self._stale = True
        self._pos = float(model.position.center_tick if position_ticks is None else position_ticks)
        self._temp = ambient_c
        self._stall_time = 0.0
        self._hw_latched = 0
        self._last = clock()
        self._t0 = self._last
        self._factory_fill(keep=())
        self.set("id", servo_id)
        self.set("goal_position", int(round(self._pos)))
        self._sync_outputs(0.0, 0.0)

    # ------------------------------------------------------------------ raw access
    def has(self, name: str) -> bool:
        return name in self._regs

    def get(self, name: str) -> int:
        """A register's value as a READ would return it now, without advancing the motor
        model (call :meth:`advance` first for the present state)."""
        if self._stale:
            self._sync_outputs(self._vel, self._cur, self._last)
        return self._g(name)

    def _g(self, name: str) -> int:
        """Raw register value (internal: no refresh of the output registers), decoded once
        per change of its bytes (the bus asks for the same configuration registers for
        every packet)."""
        value = self._cache.get(name)
        if value is None:
            offset, packer, reg = self._acc[name]
            if packer is None:
                value = reg.decode(self._mem[offset : reg.end])
            else:
                value = packer.unpack_from(self._mem, offset)[0]
            self._cache[name] = value
        return value

    def set(self, name: str, value: int) -> None:
        """Set a register's value directly (back door for tests: no access rules)."""
        offset, packer, reg = self._acc[name]
        self._cache.pop(name, None)
        if packer is None or not reg.signed and value < 0:
            self._mem[offset : reg.end] = reg.encode(value)
        else:
            try:
                packer.pack_into(self._mem, offset, value)
            except struct.error:  # out of the register's width: wrap like the encoder does
                self._mem[offset : reg.end] = reg.encode(value)

    @property
    def servo_id(self) -> int:
        return self._g("id")

    @property
    def protocol(self) -> int:
        return self.model.protocol

    @property
    def torque_enabled(self) -> bool:
        return self._g("torque_enable") == 1

    @property
    def position(self) -> float:
        """Present position in ticks (float, before rounding into the register)."""
        return self._pos

    @property
    def temperature_c(self) -> float:
        return self._temp

    def return_delay_s(self) -> float:
        return self.model.return_delay_s(self._g("return_delay_time"))

    def status_return_level(self) -> int:
        return self._g("status_return_level") if self.has("status_return_level") else 2

    def baud(self) -> int | None:
        """The baud rate this servo listens at, from its Baud Rate register (the decoded
        value is kept until the register changes: the bus asks for every packet)."""
        raw = self._g("baud_rate")
        if raw != self._baud_memo[0]:
            try:
                self._baud_memo = (raw, self.model.register_to_baud(raw))
            except Exception:
                self._baud_memo = (raw, None)
        return self._baud_memo[1]

    def _factory_fill(self, keep: tuple[str, ...]) -> None:
        kept = {name: self._g(name) for name in keep if name in self._regs}
        self._mem[:] = bytes(len(self._mem))
        self._cache.clear()
        for r in self._regs.values():
            if r.initial is not None:
                self._mem[r.address : r.end] = r.encode(r.initial)
        for name, value in kept.items():
            self.set(name, value)

    # ------------------------------------------------------------------ hardware errors
    def hardware_error(self) -> int:
        """Current Hardware Error Status bits (computed + latched + injected)."""
        bits = self._hw_latched | self.faults.injected_hw_error
        if self._has_voltage_limits:
            volts = self.supply_voltage() / self.model.voltage_v
            if not self._g("min_voltage_limit") - 1e-9 <= volts <= self._g("max_voltage_limit") + 1e-9:
                bits |= HW_INPUT_VOLTAGE
        if self._has_temp_limit and self._temp >= self._g("temperature_limit"):
            bits |= HW_OVERHEATING
        return bits

    def supply_voltage(self) -> float:
        return self.model.ratings.rated_voltage_v if self.faults.supply_v is None else self.faults.supply_v

    def status_error(self) -> int:
        """Hardware part of a status packet's error byte: protocol 2.0 alert bit 0x80,
        or the protocol 1.0 voltage/overheat/overload bits."""
        bits = self.hardware_error()
        if self.model.protocol == 2:
            return 0x80 if bits else 0
        return sum(p1 for hw, p1 in _P1_HW_BITS.items() if bits & hw)

    def _shutdown_active(self) -> bool:
        mask = self._g("shutdown") if self._has_shutdown else 0
        return bool(mask and self.hardware_error() & mask)

    # ------------------------------------------------------------------ motor model
    def advance(self, now: float | None = None) -> None:
        """Bring the motor model and the read-only registers up to ``now``."""
        now = self.clock() if now is None else now
        deadline = self._watchdog_deadline()
        if deadline is not None and deadline <= now:
            if deadline > self._last:
                self._step(deadline)  # move until the watchdog fires...
            self._trip_watchdog()  # ...then stop
        self._step(now)

    def _step(self, now: float) -> None:
        dt = now - self._last
        if dt < MIN_STEP_S:
            return
        self._last = now
        m = self.model
        velocity_ticks_s = 0.0
        current_a = 0.0
        torque = self._g("torque_enable") == 1
        if torque and not self.faults.disconnected:
            mode = self._g("operating_mode") if self._has_mode else 3
            v_cap = self._max_speed_ticks_s()
            if mode == 1 and self.has("goal_velocity"):
                target_v = max(
                    -v_cap, min(v_cap, self._g("goal_velocity") * m.velocity_rpm * m.position.ticks_per_turn / 60.0)
                )
                step = 0.0 if self.faults.stuck else target_v * dt
                current_a = m.ratings.stall_current_a * (
                    1.0 if self.faults.stuck and target_v else abs(target_v) / max(v_cap, 1e-9) * 0.2
                )
            else:
                goal = self._g("goal_position")
                err = goal - self._pos
                step = 0.0 if self.faults.stuck else max(-v_cap * dt, min(v_cap * dt, err))
                residual = err - step
                current_a = m.ratings.stall_current_a * max(-1.0, min(1.0, residual / CURRENT_SATURATION_TICKS))
            if mode == 3:
                step = max(m.position.min_tick - self._pos, min(m.position.max_tick - self._pos, step))
            self._pos += step
            # the velocity at the end of the interval: zero if it arrived before the end
            arrived = mode != 1 and abs(step) < v_cap * dt * (1.0 - 1e-9)
            velocity_ticks_s = 0.0 if arrived else step / dt
        # overload: sustained stall current
        if abs(current_a) >= 0.95 * m.ratings.stall_current_a:
            self._stall_time += dt
            if self._stall_time >= OVERLOAD_TIME_S:
                self._hw_latched |= HW_OVERLOAD
        else:
            self._stall_time = 0.0
        # thermal first-order model (exact for piecewise-constant current)
        if self.faults.held_temperature_c is not None:
            self._temp = self.faults.held_temperature_c
        else:
            ratio = current_a / m.ratings.stall_current_a
            t_ss = self.ambient_c + THERMAL_RISE_AT_STALL_K * ratio * ratio
            self._temp = t_ss + (self._temp - t_ss) * math.exp(-dt / THERMAL_TAU_S)
        if torque and self._shutdown_active():
            self.set("torque_enable", 0)
        self._vel, self._cur, self._stale = velocity_ticks_s, current_a, True

    def _max_speed_ticks_s(self) -> float:
        m = self.model
        if self.has("profile_velocity"):
            limit = self._g("velocity_limit") if self.has("velocity_limit") else 0
            pv = self._g("profile_velocity")
            units = limit if pv == 0 else (min(pv, limit) if limit else pv)
            rpm = units * m.velocity_rpm if units else m.ratings.no_load_speed_rpm
        else:
            ms = self._g("moving_speed") & 0x3FF if self.has("moving_speed") else 0
            rpm = ms * m.velocity_rpm if ms else m.ratings.no_load_speed_rpm
        rpm = min(rpm, m.ratings.no_load_speed_rpm * self.supply_voltage() / m.ratings.rated_voltage_v)
        return rpm * m.position.ticks_per_turn / 60.0

    def _sync_outputs(self, velocity_ticks_s: float, current_a: float, now: float | None = None) -> None:
        """Write the model's state into the read-only registers."""
        self._stale = False
        m = self.model
        has = self._regs.__contains__
        setr = self.set
        self._vel, self._cur = velocity_ticks_s, current_a
        setr("present_position", int(round(self._pos)))
        vel_units = int(round(velocity_ticks_s * self._vel_units_per_tick_s))
        setr(self._vel_name, vel_units)
        if self._has_current:
            setr("present_current", int(round(current_a * 1000.0 / m.current_ma)))
        if self._has_load:
            setr("present_load", int(round(1000.0 * current_a / m.ratings.stall_current_a)))
        torque_on = self._g("torque_enable") == 1
        goal = self._g("goal_position")
        if self._has_trajectory:
            setr("velocity_trajectory", vel_units)
            setr("position_trajectory", goal if torque_on else int(round(self._pos)))
        setr(self._volt_name, int(round(self.supply_voltage() / m.voltage_v)))
        setr("present_temperature", int(round(self._temp / m.temperature_c)))
        moving = abs(vel_units) > (self._g("moving_threshold") if self._has_threshold else 0)
        setr("moving", int(moving))
        if has("moving_status"):
            setr("moving_status", int(abs(goal - self._pos) < 1.0) | (0x02 if moving else 0))
        if self._has_hw_register:
            setr("hardware_error_status", self.hardware_error())
        if self._has_tick and now is not None:
            setr("realtime_tick", int((now - self._t0) * 1000.0) % 32768)
        self._stale = False

    def refresh(self) -> None:
        """Apply changed faults now (held temperature, shutdown) without advancing time."""
        if self.faults.held_temperature_c is not None:
            self._temp = self.faults.held_temperature_c
        if self.torque_enabled and self._shutdown_active():
            self._set_torque_off()
        self._stale = True

    def _set_torque_off(self) -> None:
        self.set("torque_enable", 0)

    # ------------------------------------------------------------------ bus watchdog
    def heard(self, now: float | None = None) -> None:
        """The servo heard an instruction packet: restart its Bus Watchdog interval. If the
        watchdog had already expired, the motor model is first brought to ``now`` (so it
        trips at its deadline); otherwise the model moves on at the servo's next read or
        write: every packet reaches every servo, and stepping all of them for a packet
        addressed to one made the emulator, not the bus, set the pace at 250 Hz."""
        now = self.clock() if now is None else now
        deadline = self._watchdog_deadline()
        if deadline is not None and deadline <= now:
            self.advance(now)
        self._last_heard = now

    def _watchdog_deadline(self) -> float | None:
        """When the Bus Watchdog(98) fires: torque on, 1..127 x 20 ms after the last packet."""
        if not self._has_watchdog or self._g("torque_enable") != 1:
            return None
        period = self._g("bus_watchdog")
        if period <= 0:
            return None
        return max(self._last_heard, self._torque_on_at) + period * 0.020

    def _trip_watchdog(self) -> None:
        """Bus Watchdog error (e-Manual "Bus Watchdog(98)"): stop where it is, Bus Watchdog
        becomes -1 and the goal registers turn read-only (Data Range Error) until 0 is written."""
        self.set("bus_watchdog", -1)
        self.set("goal_position", int(round(self._pos)))
        for name in ("goal_velocity", "profile_velocity", "profile_acceleration"):
            if self.has(name):
                self.set(name, 0)
        self._stale = True

    def push(self, ticks: float) -> None:
        """An external hand moves the horn to ``ticks`` (a torque-on servo will return to its goal)."""
        self.advance()
        self._pos = float(ticks)
        self._sync_outputs(0.0, 0.0, self._last)

    # ------------------------------------------------------------------ protocol operations
    def read(self, address: int, length: int) -> bytes | None:
        """Raw bytes of the control table, or None if the span leaves the table."""
        self.advance()
        if self._stale:
            pos = self._present_span
            if pos[0] <= address and address + length <= pos[1]:
                # only Present Position is read (a sync read's usual span): refresh just it;
                # the other outputs stay stale until something reads them
                self.set("present_position", int(round(self._pos)))
            else:
                self._sync_outputs(self._vel, self._cur, self._last)
        if address < 0 or length < 0 or address + length > len(self._mem):
            return None
        return bytes(self._mem[address : address + length])

    def _registers_in(self, start: int, end: int) -> tuple:
        span = self._spans.get((start, end))
        if span is None:
            span = self._spans[(start, end)] = tuple(self.model.registers_in(start, end))
        return span

    def check_write(self, address: int, data: bytes) -> WriteResult:
        """Whether a write of ``data`` at ``address`` would be accepted (no side effects)."""
        end = address + len(data)
        regs = self._registers_in(address, end)
        if not regs or end > len(self._mem):
            return WriteResult("access")
        for r in regs:
            if r.address < address or r.end > end:
                return WriteResult("length")
        for r in regs:
            if not r.writable:
                return WriteResult("access")
        if self._has_watchdog and self._g("bus_watchdog") == -1 and any(r.name in _GOAL_REGISTERS for r in regs):
            return WriteResult("range")  # goals are read-only after a Bus Watchdog error
        if any(r.eeprom for r in regs):
            if self.model.protocol == 2 and self.torque_enabled:
                return WriteResult("access")
            if self.has("lock") and self._g("lock") == 1:
                return WriteResult("access")
        for r in regs:
            value = r.decode(data[r.address - address : r.end - address])
            if r.name == "goal_position":
                if self.model.protocol == 1 and not r.in_range(value):
                    return WriteResult("range")
                lo, hi = self._goal_limits()
                if lo is not None and not lo <= value <= hi:
                    return WriteResult("limit")
                continue
            if not r.in_range(value):
                return WriteResult("range")
        return WriteResult(None)

    def _goal_limits(self) -> tuple[int | None, int | None]:
        if self.has("min_position_limit"):
            mode = self._g("operating_mode") if self.has("operating_mode") else 3
            if mode != 3:
                return None, None
            return self._g("min_position_limit"), self._g("max_position_limit")
        if self.has("cw_angle_limit"):
            lo, hi = self._g("cw_angle_limit"), self._g("ccw_angle_limit")
            if lo == 0 and hi == 0:  # wheel mode
                return None, None
            return lo, hi
        return None, None

    def write(self, address: int, data: bytes, instruction: str = "WRITE") -> WriteResult:
        """Apply a write under the rules above; records every Goal Position it carries."""
        self.advance()
        data = bytes(data)
        g0, g1 = self._goal_span
        if address == g0 and len(data) == g1 - g0:
            return self._write_goal(data, instruction)
        result = self.check_write(address, data)
        goal_reg = self._regs["goal_position"]
        if address < g1 and g0 < address + len(data):
            # record any write touching Goal Position; a partial one as the bytes it
            # would have left in the register (it is refused with a length error)
            if address <= g0 and g1 <= address + len(data):
                ticks = goal_reg.decode(data[g0 - address : g1 - address])
            else:
                merged = bytearray(self._mem[g0:g1])
                for k in range(max(address, g0), min(address + len(data), g1)):
                    merged[k - g0] = data[k - address]
                ticks = goal_reg.decode(bytes(merged))
            self._record_goal(ticks, result.ok, instruction)
        if not result.ok:
            return result
        regs = self._registers_in(address, address + len(data))
        names = {r.name for r in regs}
        torque = "torque_enable" in names  # only these writes can switch torque or move the home
        homing = "homing_offset" in names
        was_on = self.torque_enabled if torque else True
        old_offset = self._g("homing_offset") if homing else 0
        for r in regs:
            self._mem[r.address : r.end] = data[r.address - address : r.end - address]
        self._cache.clear()
        if homing:
            self._pos += self._g("homing_offset") - old_offset
        if torque and self.torque_enabled and not was_on:
            self._torque_on_at = self.clock()
            if self._shutdown_active():
                self.set("torque_enable", 0)  # shutdown holds torque off until REBOOT
        self._stale = True
        return result

    def _write_goal(self, data: bytes, instruction: str) -> WriteResult:
        """A write of exactly Goal Position (every control tick's SYNC_WRITE): the checks
        :meth:`check_write` makes for that one register (a RAM register, always writable),
        without its generic span analysis: read-only after a Bus Watchdog error, the
        register's range on protocol 1.0, the position limits in position mode."""
        g0, g1 = self._goal_span
        reg = self._regs["goal_position"]
        ticks = reg.decode(data)
        if self._has_watchdog and self._g("bus_watchdog") == -1:
            result = _WRITE_RANGE
        elif self.model.protocol == 1 and not reg.in_range(ticks):
            result = _WRITE_RANGE
        else:
            lo, hi = self._goal_limits()
            result = _WRITE_LIMIT if lo is not None and not lo <= ticks <= hi else _WRITE_OK
        self._record_goal(ticks, result.ok, instruction)
        if result.ok:
            self._mem[g0:g1] = data
            self._cache.pop("goal_position", None)
            self._stale = True
        return result

    def _record_goal(self, ticks: int, accepted: bool, instruction: str) -> None:
        rec = GoalRecord(self.clock(), self.servo_id, ticks, accepted, instruction)
        self.goal_history.append(rec)
        if self.allowed_range is not None and not self.allowed_range[0] <= ticks <= self.allowed_range[1]:
            self.violations.append(rec)

    def reg_write(self, address: int, data: bytes) -> WriteResult:
        """REG_WRITE: check now, hold until ACTION (Registered Instruction = 1)."""
        self.advance()
        result = self.check_write(address, bytes(data))
        if result.ok:
            self._registered = (address, bytes(data))
            self.set(self._registered_name(), 1)
        return result

    def _registered_name(self) -> str:
        return "registered_instruction" if self.has("registered_instruction") else "registered"

    def action(self) -> bool:
        """ACTION: apply the registered write; False if nothing was registered."""
        if self._registered is None:
            return False
        address, data = self._registered
        self._registered = None
        self.set(self._registered_name(), 0)
        self.write(address, data, "ACTION")
        return True

    def reboot(self, downtime_s: float) -> None:
        """REBOOT: RAM back to factory values, errors cleared, torque off, goal = present;
        the servo answers nothing for ``downtime_s``."""
        self.advance()
        eeprom = {r.name: self._g(r.name) for r in self._regs.values() if r.eeprom}
        self._factory_fill(keep=())
        for name, value in eeprom.items():
            self.set(name, value)
        self._registered = None
        self._hw_latched = 0
        self._stall_time = 0.0
        if not self.faults.hw_error_survives_reboot:
            self.faults.injected_hw_error = 0
        self.set("goal_position", int(round(self._pos)))
        self._sync_outputs(0.0, 0.0, self._last)
        self.booting_until = self.clock() + downtime_s

    def factory_reset(self, option: int) -> None:
        """FACTORY_RESET: 0xFF everything, 0x01 all but ID, 0x02 all but ID and baud rate."""
        self.advance()
        keep = {0x01: ("id",), 0x02: ("id", "baud_rate")}.get(option, ())
        self._factory_fill(keep=keep)
        self._registered = None
        self.set("goal_position", int(round(self._pos)))
        self._sync_outputs(0.0, 0.0, self._last)
